from dataclasses import asdict
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from omegaconf import OmegaConf

import sfs_torch.cli  # noqa: F401  (registers the config schema)
from sfs_torch.pipeline import PipelineConfig

CONF = Path(__file__).resolve().parents[1] / "conf"
# dataset/ and search/ belong to the sfs-torch-eval app (conf/eval.yaml), composed in
# tests/test_evaluate.py and tests/test_sweeps.py
GROUPS = sorted(p.name for p in CONF.iterdir()
                if p.is_dir() and p.name not in {"experiment", "dataset", "search", "__pycache__"})


def compose_app(overrides=()):
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


class TestConfigs:
    def test_defaults_equal_the_dataclasses(self):
        cfg = compose_app()
        defaults = asdict(PipelineConfig())
        for group in defaults:
            assert OmegaConf.to_container(cfg[group]) == defaults[group], group

    @pytest.mark.parametrize("group", GROUPS)
    def test_every_option_composes(self, group):
        for option in sorted((CONF / group).glob("*.yaml")):
            cfg = compose_app([f"{group}={option.stem}"])
            OmegaConf.to_object(cfg)  # validates against the schema

    def test_experiment_composes(self):
        cfg = compose_app(["+experiment=ablation"])
        assert cfg.integrate.method is None

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
