import json

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from sfs_torch.forest import VMFForest
from sfs_torch.forest_cache import evict_forests, load_forest, save_forest
from sfs_torch.geometry_db import _sha256


@pytest.fixture(scope="module")
def forest():
    gen = torch.Generator().manual_seed(0)
    features = torch.rand(200, 4, generator=gen)
    normals = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen), dim=1)
    return VMFForest(n_trees=2, max_depth=3).fit(features, normals)


def _rewrite(path, tensors, metadata):
    # a valid checksum over content that does not load: only loading can tell
    save_file(tensors, str(path), metadata=metadata)
    path.with_suffix(".sha256").write_text(_sha256(path))


class TestLoadForest:
    def test_round_trip(self, forest, tmp_path):
        path = tmp_path / "f.safetensors"
        save_forest(forest, path)
        loaded = load_forest(path, torch.device("cpu"))
        assert torch.equal(loaded.kappa_, forest.kappa_) and torch.equal(loaded.mean_, forest.mean_)

    @pytest.mark.parametrize("change", ["renamed tensor", "unknown param"])
    def test_entry_that_does_not_load_is_deleted(self, forest, tmp_path, caplog, change):
        path = tmp_path / "f.safetensors"
        save_forest(forest, path)
        with safe_open(str(path), "pt") as handle:
            metadata = handle.metadata()
        tensors = load_file(str(path))
        if change == "renamed tensor":
            tensors["kappa_v2"] = tensors.pop("kappa")
        else:
            metadata["params"] = json.dumps({**json.loads(metadata["params"]), "min_gain": 0.0})
        _rewrite(path, tensors, metadata)
        with caplog.at_level("WARNING", logger="sfs_torch.forest_cache"):
            assert load_forest(path, torch.device("cpu")) is None
        assert "deleting unusable cached forest" in caplog.text
        assert not path.exists() and not path.with_suffix(".sha256").exists()


class TestEvictForests:
    def test_keep_zero_deletes_all(self, forest, tmp_path):
        for i in range(3):
            save_forest(forest, tmp_path / f"k{i}.safetensors")
        evict_forests(tmp_path, 0)
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("keep", [None, -1, 2.5, True])
    def test_bad_keep(self, forest, tmp_path, keep):
        save_forest(forest, tmp_path / "k.safetensors")
        with pytest.raises(ValueError, match=rf"keep must be an integer >= 0, got {keep!r}"):
            evict_forests(tmp_path, keep)
        assert (tmp_path / "k.safetensors").exists()
