from dataclasses import asdict
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

import sfs_torch.cli  # noqa: F401  (registers the config schema)
from sfs_torch.pipeline import PipelineConfig

CONF = Path(__file__).resolve().parents[1] / "conf"
GROUPS = sorted(p.name for p in CONF.iterdir() if p.is_dir() and p.name not in {"experiment", "__pycache__"})


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
