"""Bayesian hyper-parameter search: ``sfs-torch-eval -m hydra/sweeper=optuna +search=forest`` (docs/sweeps.md)."""
import json
import subprocess
import sys
import warnings

import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.utils import instantiate
from omegaconf import OmegaConf

import sfs_torch.evaluate  # noqa: F401  (registers the eval config schema)
from sfs_torch.pipeline import resolve_config

with warnings.catch_warnings():  # optuna 2.10 (the plugin's newest) uses SQLAlchemy 1.x names on import
    warnings.simplefilter("ignore", DeprecationWarning)
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="pip install -e '.[sweep]'")
    from hydra_plugins.hydra_optuna_sweeper._impl import create_optuna_distribution_from_override  # noqa: E402

SEARCHED = {
    "pipeline.forest.n_trees", "pipeline.forest.max_depth", "pipeline.forest.max_features",
    "pipeline.forest.min_samples_leaf", "pipeline.training.brightness_jitter", "pipeline.training.colour_jitter",
}
# the tiny database of tests/test_evaluate.py (its forest options are the ones searched, so not fixed here)
TINY_DATABASE = [
    "pipeline.database.collection=blobby", "pipeline.database.n_shapes=12", "pipeline.database.n_views=4",
    "pipeline.database.resolution=64", "pipeline.database.n_eval_shapes=2",
]


def compose_eval(overrides=()):
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="eval", overrides=list(overrides), return_hydra_config=True)


def distributions(cfg):
    parser = OverridesParser.create()
    overrides = parser.parse_overrides([f"{key}={value}" for key, value in cfg.hydra.sweeper.params.items()])
    return {o.key_or_group: create_optuna_distribution_from_override(o) for o in overrides}


class TestForestSearchConfig:
    def test_composes_with_the_optuna_sweeper(self):
        cfg = compose_eval(["hydra/sweeper=optuna", "+search=forest", "out=/data/search"])
        sweeper = instantiate(cfg.hydra.sweeper)
        assert type(sweeper).__name__ == "OptunaSweeper"
        assert cfg.hydra.sweeper.direction == "minimize" and cfg.hydra.sweeper.n_trials == 30
        assert cfg.hydra.sweeper.sampler._target_ == "optuna.samplers.TPESampler"
        assert set(cfg.hydra.sweeper.params) == SEARCHED
        # scored on the validation side only, with the one method the objective is
        assert cfg.dataset.name == "synthetic" and cfg.dataset.side == "validation"
        assert list(cfg.methods) == ["estimated_lighting"]
        assert cfg.resume is False  # trial N never resumes another trial's rows
        assert cfg.hydra.sweep.dir == "/data/search"  # trial N writes into /data/search/N

    def test_the_search_selects_the_sweeper_itself(self):
        with_sweeper = compose_eval(["hydra/sweeper=optuna", "+search=forest"])
        alone = compose_eval(["+search=forest"])
        assert alone.hydra.sweeper == with_sweeper.hydra.sweeper

    def test_search_space(self):
        space = distributions(compose_eval(["+search=forest"]))
        assert set(space) == SEARCHED
        assert type(space["pipeline.forest.n_trees"]).__name__ == "IntUniformDistribution"
        assert type(space["pipeline.forest.min_samples_leaf"]).__name__ == "IntLogUniformDistribution"
        assert type(space["pipeline.training.colour_jitter"]).__name__ == "UniformDistribution"
        assert space["pipeline.forest.max_features"].choices == (4, 8, 12, 16)

    @pytest.mark.parametrize("end", ["low", "high"])
    def test_every_end_of_the_space_is_a_valid_pipeline(self, end):
        # each trial's overrides are typed and checked by the app (a bad range would fail only at its trial)
        space = distributions(compose_eval(["+search=forest"]))
        values = {}
        for key, dist in space.items():
            if hasattr(dist, "choices"):
                values[key] = dist.choices[0 if end == "low" else -1]
            else:
                values[key] = getattr(dist, end)
        cfg = compose_eval(["+search=forest", *(f"{k}={v}" for k, v in values.items())])
        pipeline = resolve_config(cfg.pipeline)
        for key, value in values.items():
            assert OmegaConf.select(OmegaConf.structured(pipeline), key.removeprefix("pipeline.")) == value, key

    def test_defaults_are_unchanged_without_it(self):
        cfg = compose_eval()
        assert cfg.hydra.sweeper._target_.endswith("BasicSweeper")
        assert cfg.dataset.side == "test" and "known_lighting" in cfg.methods


class TestForestSearchRun:
    def test_two_trials_write_their_objectives(self, tmp_path):
        out = tmp_path / "search"
        args = ["-m", "hydra/sweeper=optuna", "+search=forest", "hydra.sweeper.n_trials=2", *TINY_DATABASE,
                "dataset.shapes=1", "dataset.lights=1", "dataset.resolution=32", f"out={out}"]
        result = subprocess.run([sys.executable, "-c", "from sfs_torch.evaluate import main; main()", *args],
                                cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stderr[-4000:]
        objectives = []
        for job in ("0", "1"):
            summary = json.loads((out / job / "summary.json").read_text())
            assert summary["dataset"] == "synthetic" and summary["cases"] == 1
            assert json.loads((out / job / "eval_config.json").read_text())["dataset"]["side"] == "validation"
            objectives.append(summary["methods"]["estimated_lighting"]["median_deg"])
            trial = yaml.safe_load((out / job / ".hydra" / "overrides.yaml").read_text())
            assert {o.split("=")[0] for o in trial} >= SEARCHED  # the trial's own sample of the space
        assert all(isinstance(v, float) and 0 <= v <= 180 for v in objectives)
        results = yaml.safe_load((out / "optimization_results.yaml").read_text())
        assert results["name"] == "optuna" and set(results["best_params"]) == SEARCHED
        assert results["best_value"] == pytest.approx(min(objectives))
