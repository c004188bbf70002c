import json
import logging
import os
import subprocess
import sys
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from sfs_torch import geometry_db, shapes
from sfs_torch.geometry_db import (
    DatabaseConfig,
    GeometryDatabase,
    build_database,
    cache_dir,
    database_split,
    evaluation_shapes,
    load_database,
    main,
)
from sfs_torch.rendering import random_view_rotations, render_normals
from sfs_torch.shapes import MeshSourceError, load_shape
from sfs_torch.silhouette import silhouette_features

TINY = DatabaseConfig(collection="blobby", n_shapes=3, n_views=2, resolution=48, samples_per_view=40,
                      n_eval_shapes=2, seed=0)


@pytest.fixture(scope="module")
def tiny_db():
    return build_database(TINY, progress=False)


def _fields(db):
    return [db.normals, db.masks, db.silhouette, db.shape_id, db.view_id]


class TestBuildDatabase:
    def test_fields(self, tiny_db):
        n = TINY.n_shapes * TINY.n_views * TINY.samples_per_view
        assert tiny_db.normals.shape == (n, 3, 5, 5) and tiny_db.normals.dtype == torch.float32
        assert tiny_db.masks.shape == (n, 1, 5, 5) and tiny_db.masks.dtype == torch.bool
        assert tiny_db.silhouette.shape == (n, 3) and tiny_db.silhouette.dtype == torch.float32
        assert tiny_db.shape_id.dtype == torch.int64 and tiny_db.view_id.dtype == torch.int64
        assert sorted(tiny_db.shape_id.unique().tolist()) == [0, 1, 2]
        assert sorted(tiny_db.view_id.unique().tolist()) == [0, 1]
        assert len(tiny_db.shape_names) == TINY.n_shapes

    def test_patch_values(self, tiny_db):
        m = tiny_db.masks.expand_as(tiny_db.normals)
        assert tiny_db.masks[:, 0, 2, 2].all()  # the centre pixel is an object pixel
        assert (tiny_db.normals[~m] == 0).all()
        norm = tiny_db.normals.norm(dim=1)[tiny_db.masks[:, 0]]
        assert torch.allclose(norm, torch.ones_like(norm), atol=1e-5)
        assert (tiny_db.normals[:, 2][tiny_db.masks[:, 0]] >= 0).all()  # visible normals face the camera
        d_rel, cos_b, sin_b = tiny_db.silhouette.T
        assert ((d_rel >= 0) & (d_rel <= 1)).all()
        assert torch.allclose(cos_b**2 + sin_b**2, torch.ones_like(d_rel), atol=1e-5)

    def test_samples_consistent_with_rendered_view(self, tiny_db):
        # Re-render shape 0 exactly as the build does: its rotations are the first draws.
        split = database_split(TINY)
        mesh = load_shape(split.train[0]).mesh
        rots = random_view_rotations(TINY.n_views, torch.Generator().manual_seed(TINY.seed))
        views = [render_normals(mesh, rot, TINY.resolution, scale=TINY.scale) for rot in rots]
        sil = silhouette_features(torch.stack([v.mask for v in views]))
        for k, view in enumerate(views):
            pix = F.unfold(F.pad(view.normals[None], (2, 2, 2, 2)), 5)[0].T  # (H W, 75): every patch
            pick = (tiny_db.shape_id == 0) & (tiny_db.view_id == k)
            dist = torch.cdist(tiny_db.normals[pick].flatten(1).double(), pix.double(),
                               compute_mode="donot_use_mm_for_euclid_dist")
            best = dist.argmin(1)
            assert dist.min(1).values.max() == 0  # every sample is exactly one of the view's patches
            assert torch.equal(tiny_db.silhouette[pick], sil[k].flatten(1).T[best])
            assert view.mask.flatten()[best].all()
            assert best.unique().numel() == best.numel() == TINY.samples_per_view  # without replacement

    def test_deterministic(self, tiny_db):
        again = build_database(TINY, progress=False)
        for a, b in zip(_fields(tiny_db), _fields(again)):
            assert torch.equal(a, b)
        other = build_database(replace(TINY, seed=1), progress=False)
        assert not torch.equal(other.normals, tiny_db.normals)

    def test_few_object_pixels_keeps_all(self):
        cfg = replace(TINY, n_shapes=1, n_views=1, resolution=8, samples_per_view=1000)
        db = build_database(cfg, progress=False)
        view = render_normals(load_shape(database_split(cfg).train[0]).mesh,
                              random_view_rotations(1, torch.Generator().manual_seed(0))[0], 8)
        assert db.normals.shape[0] == int(view.mask.sum())

    def test_exception(self):
        for bad in [dict(collection="nope"), dict(patch_size=4), dict(n_shapes=0), dict(resolution=4),
                    dict(scale=1.2), dict(n_eval_shapes=-1)]:
            name = next(iter(bad))
            with pytest.raises(ValueError, match=name):
                build_database(replace(TINY, **bad), progress=False)

    def test_to_moves_every_tensor_and_keeps_the_names(self, tiny_db):
        assert tiny_db.to("cpu") is tiny_db  # already there: no copy
        moved = tiny_db.to(torch.device("meta"))  # a device every machine has
        assert all(t.device.type == "meta" for t in _fields(moved))
        assert [t.shape for t in _fields(moved)] == [t.shape for t in _fields(tiny_db)]
        assert [t.dtype for t in _fields(moved)] == [t.dtype for t in _fields(tiny_db)]
        assert moved.shape_names == tiny_db.shape_names
        assert all(t.device.type == "cpu" for t in _fields(tiny_db))  # the original is untouched


class TestSplit:
    def test_never_overlaps(self):
        for seed in range(3):
            split = database_split(replace(TINY, n_shapes=20, n_eval_shapes=10, seed=seed))
            assert len(split.train) == 20 and len(split.evaluation) == 10
            assert not set(split.train) & set(split.evaluation)

    def test_evaluation_shapes(self, tiny_db):
        shapes_ = evaluation_shapes(TINY)
        assert len(shapes_) == TINY.n_eval_shapes
        assert not {s.name for s in shapes_} & set(tiny_db.shape_names)
        assert all(abs(s.mesh.vertices).max() <= 1 + 1e-9 for s in shapes_)


class TestLoadDatabase:
    def test_round_trip_bit_exact(self, tiny_db):
        first = load_database(TINY, progress=False)
        cached = load_database(TINY, progress=False)
        for a, b, c in zip(_fields(tiny_db), _fields(first), _fields(cached)):
            assert torch.equal(a, b) and torch.equal(a, c) and a.dtype == c.dtype
        assert cached.shape_names == tiny_db.shape_names

    def test_concurrent_first_runs_build_once(self, tmp_path):
        script = (
            "import logging, sys; logging.basicConfig(level=logging.INFO, stream=sys.stdout)\n"
            "from sfs_torch.geometry_db import DatabaseConfig, load_database\n"
            "cfg = DatabaseConfig(collection='blobby', n_shapes=6, n_views=3, resolution=64, n_eval_shapes=2)\n"
            "print('samples', load_database(cfg, progress=False).normals.shape[0])\n"
        )
        env = {**os.environ, "SFS_TORCH_CACHE": str(tmp_path)}
        runs = [subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True) for _ in range(2)]
        outputs = [run.communicate(timeout=300)[0] for run in runs]
        assert all(run.returncode == 0 for run in runs), outputs
        assert sum("built the geometry database" in out for out in outputs) == 1, outputs
        counts = {line for out in outputs for line in out.splitlines() if line.startswith("samples")}
        assert len(counts) == 1  # both got the same database

    def test_second_load_reads_cache(self, monkeypatch):
        load_database(TINY, progress=False)
        monkeypatch.setattr(geometry_db, "build_database", lambda *a, **k: pytest.fail("rebuilt"))
        assert isinstance(load_database(TINY, progress=False), GeometryDatabase)

    def test_corruption_rebuilt(self, tiny_db, caplog):
        load_database(TINY, progress=False)
        data_path, _ = geometry_db._cache_paths(TINY)
        raw = bytearray(data_path.read_bytes())
        raw[-100:-90] = bytes(b ^ 0xFF for b in raw[-100:-90])  # flip bytes inside the tensor data
        data_path.write_bytes(bytes(raw))
        with caplog.at_level(logging.WARNING, logger="sfs_torch.geometry_db"):
            db = load_database(TINY, progress=False)
        assert "checksum" in caplog.text and "rebuilding" in caplog.text
        assert torch.equal(db.normals, tiny_db.normals)
        assert data_path.read_bytes() != bytes(raw)  # the repaired file replaced the corrupt one

    def test_stale_or_broken_metadata_rebuilt(self, tiny_db, caplog):
        load_database(TINY, progress=False)
        _, meta_path = geometry_db._cache_paths(TINY)
        meta = json.loads(meta_path.read_text())
        meta["format"] = -1
        meta_path.write_text(json.dumps(meta))
        with caplog.at_level(logging.WARNING, logger="sfs_torch.geometry_db"):
            db = load_database(TINY, progress=False)
        assert "stale" in caplog.text
        assert torch.equal(db.silhouette, tiny_db.silhouette)
        meta_path.write_text("{not json")
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="sfs_torch.geometry_db"):
            load_database(TINY, progress=False)
        assert "rebuilding" in caplog.text

    def test_config_change_changes_key(self):
        keys = {geometry_db._cache_key(replace(TINY, **change)) for change in
                [{}, {"seed": 1}, {"n_views": 3}, {"resolution": 64}, {"collection": "default"}]}
        assert len(keys) == 5
        assert geometry_db._cache_key(TINY) == geometry_db._cache_key(replace(TINY))

    def test_cache_dir_env(self, tmp_path, monkeypatch):
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        assert cache_dir() == tmp_path
        load_database(replace(TINY, n_shapes=1, n_views=1), progress=False)
        assert list((tmp_path / "geometry").glob("db-*.safetensors"))


class TestMeshSources:
    def test_offline_default_collection_says_use_blobby(self, monkeypatch, tmp_path):
        def offline(root, progress=True):
            raise MeshSourceError("could not download ... set `database.collection=blobby`")

        # a cache of its own without the meshes: another test of this worker may have fetched them
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        monkeypatch.setattr(geometry_db, "sources_present", lambda root: False)
        monkeypatch.setattr(geometry_db, "fetch_sources", offline)
        with pytest.raises(MeshSourceError, match=r"database\.collection=blobby"):
            load_database(DatabaseConfig(), progress=False)

    def test_main_blobby(self, tmp_path, monkeypatch):
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        main(["--collection", "blobby", "--n-shapes", "1", "--n-views", "1", "--resolution", "32"])
        assert len(list((tmp_path / "geometry").glob("db-*.json"))) == 1

    @pytest.mark.parametrize("argv, message", [
        (["--n-shapes", "0"], "n_shapes must be a positive integer, got 0"),
        (["--collection", "foo"], "collection must be one of ['blobby', 'default', 'organic'], got 'foo'"),
    ])
    def test_main_refuses_bad_options_before_fetching(self, argv, message, monkeypatch, capsys):
        def fetch(*args, **kwargs):
            raise AssertionError("fetched the meshes before checking the options")

        monkeypatch.setattr(geometry_db, "fetch_sources", fetch)
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == f"sfs-torch-data: error: {message}"

    @pytest.mark.slow
    def test_default_collection(self):
        cfg = DatabaseConfig(n_shapes=6, n_views=2)
        db = load_database(cfg, progress=False)
        groups = {name.split("/")[0] for name in db.shape_names}
        assert groups <= set(shapes.COLLECTIONS["default"]) and len(db.shape_names) == 6
        assert db.normals.shape[0] > 6 * 2 * 100
        assert not {s.name for s in evaluation_shapes(cfg)} & set(db.shape_names)
