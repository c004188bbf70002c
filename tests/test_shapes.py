import re
import subprocess
from collections import Counter

import numpy as np
import pytest
import trimesh

from sfs_torch import shapes
from sfs_torch.shapes import (
    COLLECTIONS,
    MeshSourceError,
    ShapeSplit,
    blobby_mesh,
    collection_names,
    fetch_sources,
    load_shape,
    normalize_mesh,
    read_msh,
    read_skn,
    split_shapes,
)

TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)


def _msh_bytes(v, f, n_normals=0, n_tex=0):
    head = np.array([len(v), n_normals, n_tex, len(f)], "<i4").tobytes()
    normals = np.ones((n_normals, 3), "<f4").tobytes()
    tex = np.zeros((n_tex, 2), "<f4").tobytes()
    return head + v.astype("<f4").tobytes() + normals + tex + f.astype("<i4").tobytes()


def _skn_bytes(v, f, bones=((b"root", [0, 1]), (b"tip", [3])), n_tex=0):
    out = np.array([len(v), n_tex, len(f), len(bones)], "<i4").tobytes()
    out += v.astype("<f4").tobytes() + np.zeros((n_tex, 2), "<f4").tobytes() + f.astype("<i4").tobytes()
    for name, ids in bones:
        out += name.ljust(40, b"\0") + np.zeros(7, "<f4").tobytes() + np.array([len(ids)], "<i4").tobytes()
        out += np.array(ids, "<i4").tobytes() + np.full(len(ids), 0.5, "<f4").tobytes()
    return out


class TestReadMsh:
    def test_hand_made_file(self, tmp_path):
        path = tmp_path / "tet.msh"
        path.write_bytes(_msh_bytes(TET_V, TET_F, n_normals=4, n_tex=4))
        mesh = read_msh(path)
        np.testing.assert_array_equal(mesh.vertices, TET_V)
        np.testing.assert_array_equal(mesh.faces, TET_F)
        assert mesh.volume == pytest.approx(1 / 6)

    def test_bytes_input(self):
        assert len(read_msh(_msh_bytes(TET_V, TET_F)).faces) == 4

    def test_exception(self):
        data = _msh_bytes(TET_V, TET_F)
        with pytest.raises(ValueError, match="does not match its header"):
            read_msh(data[:-4])
        with pytest.raises(ValueError, match="16-byte header"):
            read_msh(b"\0" * 8)
        with pytest.raises(ValueError, match="face indices"):
            read_msh(_msh_bytes(TET_V, TET_F + 1))


class TestReadSkn:
    def test_hand_made_file(self, tmp_path):
        path = tmp_path / "tet.skn"
        path.write_bytes(_skn_bytes(TET_V, TET_F, n_tex=4))
        mesh = read_skn(path)
        np.testing.assert_array_equal(mesh.vertices, TET_V)
        np.testing.assert_array_equal(mesh.faces, TET_F)

    def test_exception(self):
        data = _skn_bytes(TET_V, TET_F)
        with pytest.raises(ValueError, match="truncated|does not match"):
            read_skn(data[:-4])
        with pytest.raises(ValueError, match="does not match"):
            read_skn(data + b"\0" * 4)
        with pytest.raises(ValueError, match="header is invalid"):
            read_skn(np.array([0, 0, 0, 0], "<i4").tobytes())


class TestNormalizeMesh:
    def test_unit_bounding_sphere(self):
        box = trimesh.creation.box(extents=[4.0, 2.0, 1.0])
        box.apply_translation([10.0, -3.0, 2.0])
        out = normalize_mesh(box)
        radii = np.linalg.norm(out.vertices, axis=1)
        assert radii.max() == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose(out.vertices.mean(0), 0.0, atol=1e-6)
        # sharp edges stay sharp: every vertex normal of a box is a face normal (axis)
        assert np.abs(out.vertex_normals).max(1) == pytest.approx(1.0)

    def test_fixes_inverted_soup(self):
        sphere = trimesh.creation.icosphere(subdivisions=2)
        soup = sphere.vertices[sphere.faces[:, ::-1]].reshape(-1, 3)  # inverted winding, unshared vertices
        out = normalize_mesh(trimesh.Trimesh(soup, np.arange(len(soup)).reshape(-1, 3), process=False))
        assert len(out.vertices) == len(sphere.vertices)  # merged (smooth: no split)
        outward = np.einsum("ij,ij->i", out.vertex_normals, out.vertices)
        assert outward.min() > 0.99

    def test_exception(self):
        with pytest.raises(ValueError, match="no faces"):
            normalize_mesh(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int)))


class TestBlobbyMesh:
    def test_deterministic(self):
        np.testing.assert_array_equal(blobby_mesh(7).vertices, blobby_mesh(7).vertices)
        assert not np.allclose(blobby_mesh(7).vertices, blobby_mesh(8).vertices)

    def test_star_shaped_closed_outward(self):
        mesh = blobby_mesh(3)
        assert mesh.is_watertight and mesh.volume > 0
        assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-6)
        # star-shaped around the origin: every face sees the origin from its back side
        centres = mesh.triangles_center - mesh.centroid
        assert (np.einsum("ij,ij->i", mesh.face_normals, centres) > 0).all()

    def test_smooth(self):
        mesh = blobby_mesh(5)
        # neighbouring face normals differ little: no creases
        angles = mesh.face_adjacency_angles
        assert np.degrees(angles).max() < 18


class TestSplitShapes:
    GROUPS = {"a": [f"a/{i}" for i in range(50)], "b": [f"b/{i}" for i in range(200)], "c": ["c/0", "c/1"]}
    WEIGHTS = {"a": 0.5, "b": 0.25, "c": 0.25}

    def test_disjoint_and_sized(self):
        split = split_shapes(self.GROUPS, self.WEIGHTS, 40, 12, seed=0)
        assert len(split.train) == 40 and len(split.evaluation) == 12
        assert not set(split.train) & set(split.evaluation)
        assert len(set(split.train)) == 40

    def test_weights_and_exhausted_group(self):
        split = split_shapes(self.GROUPS, self.WEIGHTS, 60, 0, seed=1)
        counts = Counter(n.split("/")[0] for n in split.train)
        # "c" runs out after 2 shapes; its share goes to the others in proportion
        assert counts["c"] == 2 and counts["a"] == pytest.approx(2 * counts["b"], abs=2) and sum(counts.values()) == 60

    def test_evaluation_independent_of_n_train(self):
        a = split_shapes(self.GROUPS, self.WEIGHTS, 10, 8, seed=3)
        b = split_shapes(self.GROUPS, self.WEIGHTS, 100, 8, seed=3)
        assert a.evaluation == b.evaluation
        assert set(a.train) <= set(b.train)

    def test_seed(self):
        assert split_shapes(self.GROUPS, self.WEIGHTS, 10, 5, 0) != split_shapes(self.GROUPS, self.WEIGHTS, 10, 5, 1)

    def test_exception(self):
        with pytest.raises(ValueError, match="n_shapes"):
            split_shapes(self.GROUPS, self.WEIGHTS, 250, 10, 0)

    def test_zero_weight_group_gives_no_shapes(self):
        # used to spin for ever once only zero-weight groups were left (shares 0/0)
        split = split_shapes({"a": ["a/1"], "b": ["b/1", "b/2", "b/3"]}, {"a": 1.0, "b": 0.0}, 1, 0, 0)
        assert split == ShapeSplit(train=["a/1"], evaluation=[])
        with pytest.raises(ValueError, match=r"must be in \[1, 1\], got 2 \+ 0"):
            split_shapes({"a": ["a/1"], "b": ["b/1", "b/2", "b/3"]}, {"a": 1.0, "b": 0.0}, 2, 0, 0)

    @pytest.mark.parametrize("weights, match", [
        ({"a": 0.0}, r"positive for some group, got \{'a': 0.0\}"),
        ({"a": -1.0}, r"finite numbers >= 0, got \{'a': -1.0\}"),
        ({"a": float("nan")}, r"finite numbers >= 0, got \{'a': nan\}"),
        ({"b": 1.0}, r"every group a weight, missing \['a'\]"),
    ])
    def test_bad_weights(self, weights, match):
        with pytest.raises(ValueError, match=match):
            split_shapes({"a": ["a/1", "a/2"]}, weights, 1, 0, 0)


class TestCollections:
    def test_blobby(self):
        names = collection_names("blobby")
        assert list(names) == ["blobby"] and len(names["blobby"]) >= 1000
        assert load_shape(names["blobby"][3]).mesh.vertices.shape == blobby_mesh(3).vertices.shape

    @pytest.mark.parametrize("name", ["blobby/abc", "blobby/-1", "blobby/", "blobby/1.5", "blobby/\u00b2"])
    def test_a_blobby_name_needs_an_integer_seed(self, name):
        with pytest.raises(ValueError, match=rf"^unknown shape name '{re.escape(name)}': a blobby shape is"):
            load_shape(name)

    def test_exception(self, tmp_path):
        with pytest.raises(ValueError, match="collection must be one of"):
            collection_names("nope")
        with pytest.raises(MeshSourceError):
            collection_names("default", tmp_path)


class TestFetchSources:
    def test_offline_error_names_the_fallback(self, tmp_path, monkeypatch):
        failed = subprocess.CompletedProcess([], 1, "", "ERROR: Could not find a version (no network)")
        monkeypatch.setattr(shapes.subprocess, "run", lambda *a, **k: failed)
        with pytest.raises(MeshSourceError, match=r"database\.collection=blobby"):
            fetch_sources(tmp_path, progress=False)

    @pytest.mark.slow
    def test_pypi_meshes(self, tmp_path):
        root = fetch_sources(tmp_path, progress=False)
        dm = root / "dm-control-1.0.50"
        # known mesh: MuJoCo's test cube (.msh), a unit cube as 12 unshared triangles
        cube = read_msh(dm / "dm_control/mjcf/test_assets/meshes/cube.msh")
        np.testing.assert_allclose(cube.bounds, [[-0.5] * 3, [0.5] * 3], atol=1e-6)
        assert normalize_mesh(cube).volume == pytest.approx((2 / np.sqrt(3)) ** 3, rel=1e-5)
        rodent = read_skn(dm / "dm_control/locomotion/walkers/assets/rodent_walker_skin.skn")
        assert rodent.faces.shape == (10752, 3)
        groups = collection_names("default", root)
        assert len(groups["urdf"]) == 1000 and len(groups["mammal"]) > 100 and len(groups["fly"]) > 30
        for name in ["mammal/SKINbody", "mammal/rodent", "fly/thorax_body", "urdf/000"]:
            mesh = load_shape(name, root).mesh
            assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-6)
        assert set(COLLECTIONS["default"]) == set(groups)
