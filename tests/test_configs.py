import math
import re
from dataclasses import asdict, is_dataclass, replace
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from sfs_torch._checks import is_integer, is_number
from sfs_torch.camera import CameraConfig
from sfs_torch.cli import STAGE_GROUPS, AppConfig, _pipeline_config  # registers the schema and the stage groups
from sfs_torch.denoise import DenoiseConfig
from sfs_torch.forest import ForestConfig, VMFForest
from sfs_torch.geometry_db import DatabaseConfig
from sfs_torch.integrability import IntegrabilityConfig, Integrator
from sfs_torch.pipeline import MOVED_OPTIONS, FeatureConfig, PipelineConfig, TrainingConfig
from sfs_torch.reflectance_map import ReflectanceMapConfig
from sfs_torch.refine import RefineConfig
from sfs_torch.silhouette import SilhouetteConfig
from sfs_torch.texton import TextonConfig

CONF = Path(__file__).resolve().parents[1] / "conf"
# dataset/ and search/ belong to the sfs-torch-eval app (conf/eval.yaml), composed in
# tests/test_evaluate.py and tests/test_sweeps.py
APP_ONLY = {"experiment", "dataset", "search", "__pycache__"}
YAML_OPTIONS = {(p.parent.name, p.stem) for p in CONF.glob("*/*.yaml") if p.parent.name not in APP_ONLY}
OPTIONS = sorted(YAML_OPTIONS | {(group, "default") for group in STAGE_GROUPS})

# what every group option composes to: the whole stage config, every value
EXPECTED = {
    ("database", "default"): DatabaseConfig(),
    ("database", "blobby"): DatabaseConfig(collection="blobby"),
    ("denoise", "default"): DenoiseConfig(),
    ("silhouette", "default"): SilhouetteConfig(),
    ("texton", "default"): TextonConfig(),
    ("reflectance_map", "default"): ReflectanceMapConfig(),
    ("training", "default"): TrainingConfig(),
    ("forest", "default"): ForestConfig(),
    ("features", "all"): FeatureConfig(rgb=True, silhouette=True, texton=True),
    ("features", "rgb"): FeatureConfig(rgb=True, silhouette=False, texton=False),
    ("features", "rgb_silh"): FeatureConfig(rgb=True, silhouette=True, texton=False),
    ("features", "rgb_tex"): FeatureConfig(rgb=True, silhouette=False, texton=True),
    ("integrate", "none"): IntegrabilityConfig(method="none"),
    ("integrate", "l2"): IntegrabilityConfig(method="l2"),
    ("integrate", "l1"): IntegrabilityConfig(method="l1"),
    ("integrate", "conv"): IntegrabilityConfig(method="conv"),
    ("camera", "ortho"): CameraConfig(focal=None, principal_point=None),
    ("camera", "persp"): CameraConfig(focal=1000.0, principal_point=None),
    ("refine", "never"): RefineConfig(when="never"),
    ("refine", "known"): RefineConfig(when="known"),
    ("refine", "always"): RefineConfig(when="always"),
}


def compose_app(overrides=(), hydra_config=False):
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides), return_hydra_config=hydra_config)


class TestConfigs:
    def test_defaults_equal_the_dataclasses(self):
        cfg = compose_app()
        assert OmegaConf.to_object(cfg) == AppConfig()
        assert _pipeline_config(cfg) == PipelineConfig()

    def test_every_stage_is_a_group_with_a_default(self):
        cfg = compose_app(hydra_config=True)
        choices = cfg.hydra.runtime.choices
        stages = [name for name in PipelineConfig.__dataclass_fields__ if is_dataclass(getattr(PipelineConfig(), name))]
        assert set(stages) == {"database", "denoise", "silhouette", "texton", "reflectance_map", "features", "training",
                               "forest", "integrate", "camera", "refine"}
        assert {stage: choices[stage] for stage in stages} == {
            "database": "default", "denoise": "default", "silhouette": "default", "texton": "default",
            "reflectance_map": "default", "features": "all", "training": "default", "forest": "default", "integrate": "none", "camera": "ortho",
            "refine": "always",
        }

    def test_every_option_is_expected(self):
        # a new option file (or stage group) needs its values listed in EXPECTED
        assert sorted(EXPECTED) == OPTIONS

    def test_the_comment_only_defaults_are_gone(self):
        # one truth: the stage groups' default is the config class, not a YAML file beside it
        assert not [p for p in CONF.glob("*/default.yaml")]

    @pytest.mark.parametrize("group, option", OPTIONS, ids=[f"{g}={o}" for g, o in OPTIONS])
    def test_every_option_composes_to_its_values(self, group, option):
        cfg = compose_app([f"{group}={option}"])
        expected = EXPECTED[(group, option)]
        assert OmegaConf.to_container(cfg[group]) == asdict(expected)
        # the option changes its group and nothing else; the pipeline receives it as composed
        assert _pipeline_config(cfg) == replace(PipelineConfig(), **{group: expected})

    def test_pipeline_options_are_top_level_keys(self):
        overrides = ["refine_rounds=0", "valid_refit=false", "keep_prior=false", "prior_check_highlight=null",
                     "prior_check_tie=0.8", "normal_rotation=pixel", "conv_samples_per_tree=3"]
        pipeline = _pipeline_config(compose_app(overrides))
        assert (pipeline.refine_rounds, pipeline.valid_refit, pipeline.keep_prior, pipeline.prior_check_highlight,
                pipeline.prior_check_tie, pipeline.normal_rotation,
                pipeline.conv_samples_per_tree) == (0, False, False, None, 0.8, "pixel", 3)
        assert replace(pipeline, refine_rounds=1, valid_refit=True, keep_prior=True, prior_check_highlight=0.1,
                       prior_check_tie=0.5, normal_rotation="centroid", conv_samples_per_tree=1) == PipelineConfig()

    def test_values_inside_a_group(self):
        cfg = compose_app(["silhouette.prune_angle=45", "silhouette.gradient_sigma=0", "forest.n_trees=3",
                           "features=rgb", "camera=persp", "camera.focal=300"])
        pipeline = _pipeline_config(cfg)
        assert pipeline.silhouette == SilhouetteConfig(prune_angle=45.0, gradient_sigma=0.0)
        assert pipeline.forest == ForestConfig(n_trees=3) and pipeline.camera == CameraConfig(focal=300.0)

    @pytest.mark.parametrize("old", sorted(MOVED_OPTIONS))
    def test_moved_keys_are_gone_from_the_stages(self, old):
        with pytest.raises(ConfigCompositionException, match=old.split(".")[1]):
            compose_app([f"{old}=1"])
        assert MOVED_OPTIONS[old] in PipelineConfig.__dataclass_fields__

    def test_targets_instantiate_the_composed_stage(self):
        cfg = compose_app(["forest.n_trees=3", "forest.max_depth=5", "integrate=l1", "integrate.l1_iter=4"])
        forest = instantiate(cfg.forest)
        assert isinstance(forest, VMFForest) and (forest.n_trees, forest.max_depth) == (3, 5)
        assert forest.min_samples_leaf == ForestConfig().min_samples_leaf
        integrator = instantiate(cfg.integrate)
        assert isinstance(integrator, Integrator) and (integrator.method, integrator.l1_iter) == ("l1", 4)
        # integrate=none is the pipeline's choice not to integrate, not a solver: it builds no Integrator
        with pytest.raises(Exception, match=r"method must be one of \('l2', 'l1', 'conv'\), got 'none'"):
            instantiate(compose_app().integrate)

    @pytest.mark.parametrize("option", ["none", "l2", "l1", "conv"])
    def test_integrate_options_with_solver_options(self, option):
        # a sweep like `integrate=none,l2,l1,conv integrate.max_iter=50` composes in every job:
        # the method is the option's, the solver options the override's (unused with none)
        pipeline = _pipeline_config(compose_app([f"integrate={option}", "integrate.max_iter=50", "integrate.l1_iter=3"]))
        assert pipeline.integrate == IntegrabilityConfig(method=option, max_iter=50, l1_iter=3)
        alone = _pipeline_config(compose_app(["integrate.max_iter=50"]))  # the default method, none
        assert alone.integrate == IntegrabilityConfig(method="none", max_iter=50)

    @pytest.mark.parametrize("override, match", [
        ("integrate=l3", "integrate"),  # no such option file
        ("integrate.method=l3", r"^integrate.method must be one of \('none', 'l2', 'l1', 'conv'\)"),
        ("integrate.max_iter=0", r"^integrate.max_iter must be an integer >= 1, got 0"),
    ])
    def test_bad_integrate_values_name_the_key(self, override, match):
        with pytest.raises((ConfigCompositionException, ValueError), match=match):
            _pipeline_config(compose_app([override]))

    def test_experiment_composes(self):
        cfg = compose_app(["+experiment=ablation"], hydra_config=True)
        assert cfg.integrate.method == "none"
        assert cfg.hydra.sweeper.params.features == "rgb,rgb_silh,rgb_tex,all"

    def test_typo_is_rejected(self):
        with pytest.raises(Exception, match="n_treez"):
            compose_app(["forest.n_treez=3"])


def compose_with_hydra(overrides=()):
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides), return_hydra_config=True)


class TestLaunchers:
    """``hydra/launcher=joblib`` and ``=submitit_slurm`` (the ``sweep`` extra) compose and build; no cluster needed."""

    def test_joblib(self):
        pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="pip install -e '.[sweep]'")
        cfg = compose_with_hydra(["hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "out=/data/sweep"])
        launcher = instantiate(cfg.hydra.launcher)
        assert type(launcher).__name__ == "JoblibLauncher"
        assert launcher.joblib["n_jobs"] == 2 and launcher.joblib["prefer"] == "processes"
        assert cfg.hydra.sweep.dir == "/data/sweep"  # job N writes into /data/sweep/N
        assert OmegaConf.to_container(cfg.hydra.sweep)["subdir"] == "${hydra.job.num}"
        OmegaConf.to_object(cfg.forest)  # the app's part is untouched by the launcher choice

    def test_submitit_slurm(self):
        pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install -e '.[sweep]'")
        overrides = [
            "hydra/launcher=submitit_slurm", "hydra.launcher.partition=gpu", "hydra.launcher.timeout_min=30",
            "hydra.launcher.cpus_per_task=8", "hydra.launcher.gpus_per_node=1", "hydra.launcher.array_parallelism=4",
            "device=cuda", "out=/data/sweep",
        ]
        cfg = compose_with_hydra(overrides)
        launcher = instantiate(cfg.hydra.launcher)
        assert type(launcher).__name__ == "SlurmLauncher"
        params = launcher.params
        asked = {"partition": "gpu", "timeout_min": 30, "cpus_per_task": 8, "gpus_per_node": 1, "array_parallelism": 4}
        assert {key: params[key] for key in asked} == asked
        # submitit's job logs land beside the jobs' output folders
        assert params["submitit_folder"] == "/data/sweep/.submitit/%j"
        assert cfg.device == "cuda"

    def test_without_out_sweeps_go_to_a_dated_folder(self):
        cfg = compose_with_hydra()
        assert cfg.hydra.sweep.dir.startswith("multirun/")


@pytest.mark.parametrize("value, minimum, strict, expected", [
    (0.5, 0, False, True), (0, 0, False, True), (0, 0, True, False), (3, 0, True, True),
    (-1.0, 0, False, False), (-1.0, -math.inf, False, True),
    (True, 0, False, False), (float("nan"), 0, False, False), (float("inf"), 0, False, False),
    ("1", 0, False, False), (None, 0, False, False),
])
def test_a_numeric_option_is_a_finite_real_number(value, minimum, strict, expected):
    assert is_number(value, minimum, strict=strict) is expected


@pytest.mark.parametrize("value, minimum, maximum, expected", [
    (1, 1, 16, True), (16, 1, 16, True), (0, 1, 16, False), (17, 1, 16, False), (-3, -math.inf, math.inf, True),
    (True, 0, 16, False), (2.0, 0, 16, False), ("2", 0, 16, False), (None, 0, 16, False),
])
def test_an_integer_option_is_an_int_in_range(value, minimum, maximum, expected):
    assert is_integer(value, minimum, maximum) is expected


def _checks_of_stage_configs():
    """Each stage's own check, as its building block runs it without the pipeline (where
    OmegaConf would already refuse a non-integer for an ``int`` field)."""
    from sfs_torch.geometry_db import _check_config as check_database_config
    from sfs_torch.integrability import check_integrability_config
    from sfs_torch.reflectance_map import check_reflectance_map_config
    from sfs_torch.refine import check_refine_config

    return {
        "refine": (RefineConfig, check_refine_config),
        "integrate": (IntegrabilityConfig, check_integrability_config),
        "reflectance_map": (ReflectanceMapConfig, check_reflectance_map_config),
        "database": (DatabaseConfig, check_database_config),
    }


@pytest.mark.parametrize("stage, field", [
    ("refine", "iterations"), ("refine", "levels"), ("integrate", "max_iter"), ("integrate", "l1_iter"),
    ("integrate", "conv_iter"), ("reflectance_map", "n_directions"), ("reflectance_map", "min_k"),
    ("reflectance_map", "max_pixels"), ("database", "n_shapes"), ("database", "n_views"),
    ("database", "samples_per_view"), ("database", "n_eval_shapes"), ("database", "seed"),
    ("database", "patch_size"), ("database", "resolution"),
])
@pytest.mark.parametrize("bad", [True, 2.5, "3"])
def test_an_integer_option_of_a_stage_refuses_bools_floats_and_strings(stage, field, bad):
    config_class, check = _checks_of_stage_configs()[stage]
    check(config_class())  # the defaults pass
    with pytest.raises(ValueError, match=rf"{field} must be a.* integer.*got {re.escape(repr(bad))}$"):
        check(replace(config_class(), **{field: bad}))


@pytest.mark.parametrize("bad", ["0.5", True, None, 0, 1.0, float("nan")])
def test_the_database_scale_is_a_number_inside_the_image(bad):
    _, check = _checks_of_stage_configs()["database"]
    with pytest.raises(ValueError, match=rf"^scale must be a number in \(0, 1\).*got {re.escape(repr(bad))}$"):
        check(replace(DatabaseConfig(), scale=bad))


def test_integer_arguments_of_functions_refuse_bools():
    import torch

    from sfs_torch.forest import VMF, sample_vmf
    from sfs_torch.image_formation import sphere_directions
    from sfs_torch.refine import free_lighting_residual
    from sfs_torch.texton import texton_features

    with pytest.raises(ValueError, match="n must be a positive integer, got True"):
        sphere_directions(True)
    vmf = VMF(mean=torch.tensor([[0.0, 0.0, 1.0]]), kappa=torch.tensor([10.0]))
    with pytest.raises(ValueError, match="n_samples must be a positive int, got True"):
        sample_vmf(vmf, True)
    image, mask = torch.rand(1, 3, 8, 8), torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    mask[..., 2:6, 2:6] = True
    with pytest.raises(ValueError, match="kernel_size must be a positive odd integer, got True"):
        texton_features(image, mask, kernel_size=True)
    normals = torch.zeros(1, 3, 8, 8)
    normals[:, 2] = 1.0
    with pytest.raises(ValueError, match="highlight_rounds must be an integer >= 0, got True"):
        free_lighting_residual(normals, image, mask, highlight_rounds=True)
