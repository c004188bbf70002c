import json

import numpy as np
import pytest
import scipy.io
import torch

from sfs_torch.dataset_loaders import (
    DILIGENT_INTRINSICS,
    Intrinsics,
    directional_light_sh,
    height_to_normals,
    load_diligent,
    load_folder,
    load_mit_berkeley,
    read_intrinsics,
)
from sfs_torch.datasets import Scene, evaluation_lightings
from sfs_torch.io import read_image, write_image, write_lighting, write_normals_png, write_normals_npy
from sfs_torch.lighting import render_sh, rotate_sh, sphere_normals
from sfs_torch.natural_lighting import random_camera_rotations


def _angles_deg(a, b):
    """Per-pixel angle between (3, H, W) normal maps (atan2: acos is coarse near 0)."""
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b, dim=0).norm(dim=0), (a * b).sum(0)))


def _sphere_cap(height, width, radius, min_nz):
    """Height (H, W) float64 of a sphere cap (NaN off it), its analytic normals (3, H, W) and mask (H, W)."""
    i = torch.arange(height, dtype=torch.float64)
    j = torch.arange(width, dtype=torch.float64)
    v, u = torch.meshgrid(height / 2 - (i + 0.5), j + 0.5 - width / 2, indexing="ij")
    r2 = u * u + v * v
    mask = r2 <= radius * radius * (1 - min_nz * min_nz)
    z = torch.sqrt((radius * radius - r2).clamp_min(0))
    normals = torch.stack([u, v, z]) / radius * mask
    return torch.where(mask, z, float("nan")), normals, mask


def _write_mask(path, mask):
    write_image(path, mask.double()[None], srgb=False, bits=8)


def _lighting():
    """A natural lighting bright enough to fill [0, 1] on a sphere cap without clipping."""
    return evaluation_lightings(1)[0][1] * 4.0


class TestHeightToNormals:
    def test_plane_of_known_slope(self):
        # height rises 0.3 per column (right) and 0.2 per row (down): dz/du = 0.3, dz/dv = -0.2
        i, j = torch.meshgrid(torch.arange(6.0, dtype=torch.float64), torch.arange(7.0, dtype=torch.float64), indexing="ij")
        normals = height_to_normals(0.3 * j + 0.2 * i)
        expected = torch.tensor([-0.3, 0.2, 1.0], dtype=torch.float64)
        expected = expected / expected.norm()
        assert normals.shape == (3, 6, 7)
        assert torch.allclose(normals.permute(1, 2, 0), expected.expand(6, 7, 3), atol=1e-12)

    def test_sphere_cap_matches_analytic_normals(self):
        height, analytic, mask = _sphere_cap(104, 104, 50.0, 0.5)
        normals = height_to_normals(height[None, None])[0]
        assert _angles_deg(normals, analytic)[mask].max() < 0.5
        assert torch.equal(normals.abs().sum(0) > 0, mask)  # NaN outside -> exactly 0

    def test_mask_restricts_the_object(self):
        height, _, mask = _sphere_cap(40, 40, 18.0, 0.5)
        left = torch.zeros_like(mask)
        left[:, :20] = True
        normals = height_to_normals(height, left)
        assert torch.equal(normals.abs().sum(0) > 0, mask & left)

    def test_exception(self):
        with pytest.raises(ValueError, match="height"):
            height_to_normals(torch.zeros(2, 3, 4, 5))
        with pytest.raises(ValueError, match="mask"):
            height_to_normals(torch.zeros(4, 5), torch.ones(4, 6, dtype=torch.bool))


class TestDirectionalLightSH:
    @pytest.mark.parametrize("direction", [(0.0, 0.0, 1.0), (0.6, 0.3, 0.74), (1.0, 0.0, 0.0)])
    def test_lambertian_sphere(self, direction):
        sphere = sphere_normals(96)
        l = torch.tensor(direction)
        l = l / l.norm()
        colour = torch.tensor([0.9, 0.6, 0.3])
        shading = render_sh(sphere.normals, directional_light_sh(l, colour)[None])[0]
        inside = sphere.mask[0, 0]
        exact = colour[:, None] * (sphere.normals[0].permute(1, 2, 0)[inside] @ l).clamp_min(0)[None]
        error = (shading[:, inside] - exact) / colour[:, None]
        # the known 9-term truncation error of the clamped cosine
        assert error.pow(2).mean().sqrt() < 0.04
        assert error.abs().max() < 0.1

    def test_peak_facing_the_light(self):
        l = torch.tensor([0.2, -0.5, 0.7])
        sh = directional_light_sh(l, [1.0, 2.0, 0.5])
        n = (l / l.norm()).view(1, 3, 1, 1)
        # sum_l A_l sum_m Y_lm(l)^2 = 1/4 + 1/2 + 5/16
        assert torch.allclose(render_sh(n, sh[None]).flatten(), 1.0625 * torch.tensor([1.0, 2.0, 0.5]), rtol=1e-4)

    def test_rotates_with_its_direction(self):
        rotation = random_camera_rotations(1, torch.Generator().manual_seed(0))[0].float()
        l = torch.tensor([0.2, 0.3, 0.9])
        colour = torch.tensor([0.5, 0.4, 0.3])
        assert torch.allclose(directional_light_sh(rotation @ l, colour),
                              rotate_sh(directional_light_sh(l, colour), rotation), atol=1e-5)

    def test_cardinality(self):
        directions = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
        sh = directional_light_sh(directions, torch.ones(2, 3, dtype=torch.float64))
        assert sh.shape == (2, 3, 9) and sh.dtype == torch.float64
        assert torch.allclose(sh[1], directional_light_sh(directions[1], 1.0))
        assert directional_light_sh([0.0, 0.0, 2.0]).shape == (3, 9)  # any length

    def test_exception(self):
        with pytest.raises(ValueError, match="zero"):
            directional_light_sh([0.0, 0.0, 0.0])
        with pytest.raises(ValueError, match="direction"):
            directional_light_sh([0.0, 1.0])
        with pytest.raises(ValueError, match="colour"):
            directional_light_sh([0.0, 0.0, 1.0], [1.0, 1.0])


def _mit_fixture(root, name="sphere", mask_in="Laboratory"):
    """One object in the SIRFS release layout: a sphere cap under a natural lighting."""
    height, _, mask = _sphere_cap(104, 104, 50.0, 0.5)
    normals = height_to_normals(height[None, None]).float()
    sh = _lighting()
    image = (render_sh(normals, sh[None]) * mask).clamp(0, 1)[0]
    laboratory = root / "MIT-Berkeley-Laboratory" / name
    natural = root / "MIT-Berkeley-Natural" / name
    laboratory.mkdir(parents=True)
    natural.mkdir(parents=True)
    scipy.io.savemat(laboratory / "Z.mat", {"depth": height.numpy()})
    write_image(natural / "shading_color.png", image, srgb=False, bits=16)
    _write_mask((laboratory if mask_in == "Laboratory" else natural) / "mask.png", mask)
    return height, mask, normals, sh, image


class TestLoadMitBerkeley:
    def test_case(self, tmp_path):
        height, mask, normals, sh, image = _mit_fixture(tmp_path)
        (scene,) = load_mit_berkeley(tmp_path)
        assert isinstance(scene, Scene)
        assert (scene.name, scene.shape, scene.lighting_name, scene.focal, scene.principal_point) == (
            "sphere|natural", "sphere", "natural", None, None)
        assert scene.image.shape == (1, 3, 104, 104) and scene.image.dtype == torch.float32
        assert torch.equal(scene.mask[0, 0], mask)
        # 16-bit PNG read as linear, not sRGB
        assert torch.allclose(scene.image[0], image, atol=1e-5)
        _, analytic, _ = _sphere_cap(104, 104, 50.0, 0.5)
        assert _angles_deg(scene.normals[0].double(), analytic)[mask].max() < 0.5
        # the known lighting: the SH fit over the ground-truth normals recovers the lighting
        assert torch.allclose(scene.lighting[0], sh, atol=2e-3 * float(sh.abs().max()))
        fitted = render_sh(scene.normals, scene.lighting)[0][:, mask]
        assert (fitted - image[:, mask]).abs().max() < 1e-4
        assert torch.equal(scene.source_lighting, scene.lighting)

    def test_natural_mask_and_finite_depth(self, tmp_path):
        height, mask, *_ = _mit_fixture(tmp_path, mask_in="Natural")
        left = torch.zeros_like(mask)
        left[:, :60] = True
        _write_mask(tmp_path / "MIT-Berkeley-Natural" / "sphere" / "mask.png", left)
        (scene,) = load_mit_berkeley(tmp_path, objects=["sphere"])
        assert torch.equal(scene.mask[0, 0], left & mask)
        assert float(scene.image[0][:, ~(left & mask)].abs().max()) == 0

    def test_objects(self, tmp_path):
        _mit_fixture(tmp_path, "b")
        _mit_fixture(tmp_path, "a")
        assert [s.shape for s in load_mit_berkeley(tmp_path)] == ["a", "b"]
        assert [s.shape for s in load_mit_berkeley(tmp_path, objects="b")] == ["b"]
        with pytest.raises(FileNotFoundError, match="no object 'c'.*available: a, b"):
            load_mit_berkeley(tmp_path, objects=["a", "c"])
        with pytest.raises(ValueError, match=r"objects\[1\] names the object 'a' again"):
            load_mit_berkeley(tmp_path, objects=["a", "a"])

    def test_release_data_folder(self, tmp_path):
        _mit_fixture(tmp_path / "data")
        assert len(load_mit_berkeley(tmp_path)) == 1

    def test_missing_files(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="MIT-Berkeley-Natural"):
            load_mit_berkeley(tmp_path)
        _mit_fixture(tmp_path)
        (tmp_path / "MIT-Berkeley-Laboratory" / "sphere" / "Z.mat").unlink()
        with pytest.raises(FileNotFoundError, match="Z.mat"):
            load_mit_berkeley(tmp_path)
        with pytest.raises(FileNotFoundError, match="nowhere"):
            load_mit_berkeley(tmp_path / "nowhere")

    def test_missing_mask(self, tmp_path):
        _mit_fixture(tmp_path)
        (tmp_path / "MIT-Berkeley-Laboratory" / "sphere" / "mask.png").unlink()
        with pytest.raises(FileNotFoundError, match="no mask.*mask.png"):
            load_mit_berkeley(tmp_path)

    def test_bad_mat_files(self, tmp_path):
        _mit_fixture(tmp_path)
        z = tmp_path / "MIT-Berkeley-Laboratory" / "sphere" / "Z.mat"
        scipy.io.savemat(z, {"height": np.zeros((104, 104))})
        with pytest.raises(ValueError, match="no variable 'depth'.*height"):
            load_mit_berkeley(tmp_path)
        scipy.io.savemat(z, {"depth": np.zeros((50, 104))})
        with pytest.raises(ValueError, match="same size"):
            load_mit_berkeley(tmp_path)
        # the 128-byte header of a MATLAB v7.3 (HDF5) file
        header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 .".ljust(116) + bytes(8) + b"\x00\x02IM"
        z.write_bytes(header + bytes(384))
        with pytest.raises(ValueError, match="v7.3"):
            load_mit_berkeley(tmp_path)
        z.write_bytes(b"not a mat file")
        with pytest.raises(ValueError, match="Z.mat"):
            load_mit_berkeley(tmp_path)


_ALBEDO = torch.tensor([0.7, 0.6, 0.5], dtype=torch.float64)
_DIRECTIONS = [(0.0, 0.0, 1.0), (0.5, 0.3, 0.81), (-0.4, -0.2, 0.89)]
_INTENSITIES = [(1.0, 1.2, 1.4), (0.8, 0.9, 1.0), (1.3, 1.1, 0.9)]


def _diligent_fixture(root, name="ball", size=(40, 48)):
    """One object in DiLiGenT's layout: a Lambertian sphere under three calibrated lights."""
    folder = root / "pmsData" / f"{name}PNG"
    folder.mkdir(parents=True)
    _, normals, mask = _sphere_cap(size[0], size[1], 18.0, 0.0)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": normals.permute(1, 2, 0).numpy()})
    _write_mask(folder / "mask.png", mask)
    names = [f"{k + 1:03d}.png" for k in range(len(_DIRECTIONS))]
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", np.array(_DIRECTIONS) / np.linalg.norm(_DIRECTIONS, axis=1, keepdims=True))
    np.savetxt(folder / "light_intensities.txt", np.array(_INTENSITIES))
    for file, direction, intensity in zip(names, _DIRECTIONS, _INTENSITIES):
        l = torch.tensor(direction, dtype=torch.float64)
        shading = (normals.permute(1, 2, 0) @ (l / l.norm())).clamp_min(0)
        photo = _ALBEDO[:, None, None] * torch.tensor(intensity, dtype=torch.float64)[:, None, None] * shading * 0.7
        write_image(folder / file, photo, srgb=False, bits=16)
    return folder, normals, mask


class TestLoadDiligent:
    def test_cases(self, tmp_path):
        folder, normals, mask = _diligent_fixture(tmp_path)
        # not DiLiGenT's 612x512 and no K.txt: orthographic (the camera: test_published_intrinsics_*)
        scenes = list(load_diligent(tmp_path, perspective=False))
        assert [s.name for s in scenes] == ["ball|001", "ball|002", "ball|003"]
        for k, scene in enumerate(scenes):
            assert (scene.shape, scene.lighting_name) == ("ball", f"{k + 1:03d}")
            assert torch.equal(scene.mask[0, 0], mask)
            # DiLiGenT's frame is SPEC's: the normals are used as they are
            assert torch.allclose(scene.normals[0].double(), normals, atol=1e-6)
            # the photograph divided by its light's intensity, then by one scale into [0, 1]
            photo = read_image(folder / f"{k + 1:03d}.png", srgb=False).double()
            divided = photo / torch.tensor(_INTENSITIES[k], dtype=torch.float64)[:, None, None] * mask
            scale = float(divided.max())
            assert float(scene.image.max()) == pytest.approx(1.0)
            assert torch.allclose(scene.image[0].double(), divided / scale, atol=1e-6)
            # the known lighting: the light's direction with the colour albedo / scale
            expected = directional_light_sh(torch.tensor(_DIRECTIONS[k], dtype=torch.float64), _ALBEDO * 0.7 / scale)
            assert torch.allclose(scene.lighting[0].double(), expected, atol=1e-4)
            assert scene.focal is None and scene.principal_point is None

    def test_published_intrinsics(self):
        assert DILIGENT_INTRINSICS.focal == pytest.approx(3765.54, abs=0.01)
        assert DILIGENT_INTRINSICS.principal_point == pytest.approx((306.375, 255.625))

    def test_published_intrinsics_only_for_the_release_size(self, tmp_path):
        _diligent_fixture(tmp_path / "release", size=(512, 612))
        scene = next(iter(load_diligent(tmp_path / "release", lights=[0])))
        assert scene.focal == DILIGENT_INTRINSICS.focal
        assert scene.principal_point == DILIGENT_INTRINSICS.principal_point
        # a resized copy, or any other size, without its K.txt: the published camera does not fit
        for name, size in (("half", (256, 306)), ("small", (40, 48))):
            folder, *_ = _diligent_fixture(tmp_path / name, size=size)
            with pytest.raises(ValueError, match=rf"'{folder}' holds {size[1]}x{size[0]} images but has no K.txt"):
                load_diligent(tmp_path / name)  # raised by the call, not when iterating
            assert len(list(load_diligent(tmp_path / name, lights=[0], perspective=False))) == 1

    def test_repeated_lights_or_objects(self, tmp_path):
        _diligent_fixture(tmp_path)
        with pytest.raises(ValueError, match=r"lights\[2\] = 0 repeats lights\[0\]"):
            load_diligent(tmp_path, lights=[0, 1, 0], perspective=False)
        with pytest.raises(ValueError, match=r"objects\[1\] names the object 'ball' again \(objects\[0\]\)"):
            load_diligent(tmp_path, objects=["ball", "ballPNG"], perspective=False)

    def test_lights_objects_and_orthographic(self, tmp_path):
        _diligent_fixture(tmp_path, "cat")
        _diligent_fixture(tmp_path, "ball")
        scenes = list(load_diligent(tmp_path / "pmsData", objects=["catPNG", "ball"], lights=[2, 0], perspective=False))
        assert [s.name for s in scenes] == ["cat|003", "cat|001", "ball|003", "ball|001"]
        assert all(s.focal is None and s.principal_point is None for s in scenes)

    def test_focal_from_k_txt(self, tmp_path):
        folder, *_ = _diligent_fixture(tmp_path)
        np.savetxt(folder.parent / "K.txt", [[1000.0, 0, 23.5], [0, 1002.0, 19.5], [0, 0, 1]])
        scene = next(iter(load_diligent(tmp_path, lights=[0])))
        assert scene.focal == pytest.approx(1001.0)
        assert scene.principal_point == pytest.approx((24.0, 20.0))  # OpenCV pixel centres -> SPEC
        np.savetxt(folder / "K.txt", [[500.0, 0, 10.0], [0, 500.0, 12.0], [0, 0, 1]])  # the object's own wins
        scene = next(iter(load_diligent(tmp_path, lights=[0])))
        assert (scene.focal, scene.principal_point) == (500.0, (10.5, 12.5))

    def test_missing_file_named_before_any_case(self, tmp_path):
        folder, *_ = _diligent_fixture(tmp_path)
        (folder / "light_intensities.txt").unlink()
        with pytest.raises(FileNotFoundError, match="light_intensities.txt"):
            load_diligent(tmp_path)  # raised by the call, not when iterating
        (tmp_path / "empty").mkdir()
        with pytest.raises(FileNotFoundError, match="pmsData"):
            load_diligent(tmp_path / "empty")

    def test_missing_photograph(self, tmp_path):
        folder, *_ = _diligent_fixture(tmp_path)
        (folder / "002.png").unlink()
        assert len(list(load_diligent(tmp_path, lights=[0, 2], perspective=False))) == 2
        with pytest.raises(FileNotFoundError, match="002.png"):
            load_diligent(tmp_path)

    def test_bad_values(self, tmp_path):
        folder, *_ = _diligent_fixture(tmp_path)
        with pytest.raises(ValueError, match=r"lights\[1\] = 3 is out of range"):
            load_diligent(tmp_path, lights=[0, 3])
        with pytest.raises(FileNotFoundError, match="no object 'bear'"):
            load_diligent(tmp_path, objects=["bear"])
        np.savetxt(folder / "light_directions.txt", np.ones((2, 3)))
        with pytest.raises(ValueError, match="light_directions.txt.*3 rows"):
            load_diligent(tmp_path)
        np.savetxt(folder / "light_directions.txt", np.ones((3, 3)))
        np.savetxt(folder.parent / "K.txt", [[1000.0, 0, 20], [0, 1100.0, 20], [0, 0, 1]])
        with pytest.raises(ValueError, match="K.txt.*square pixels"):
            load_diligent(tmp_path)


class TestReadIntrinsics:
    def test_read(self, tmp_path):
        np.savetxt(tmp_path / "K.txt", [[800.0, 0, 99.5], [0, 800.0, 79.5], [0, 0, 1]])
        assert read_intrinsics(tmp_path / "K.txt") == Intrinsics(800.0, (100.0, 80.0))

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="K.txt"):
            read_intrinsics(tmp_path / "K.txt")
        (tmp_path / "K.txt").write_text("1 2\n3 4\n")
        with pytest.raises(ValueError, match="3x3"):
            read_intrinsics(tmp_path / "K.txt")


def _folder_fixture(root):
    """Three cases: full ground truth, image and mask only, normals without a lighting."""
    height, _, mask = _sphere_cap(40, 40, 18.0, 0.4)
    normals = height_to_normals(height[None, None]).float()
    sh = _lighting()
    image = (render_sh(normals, sh[None]) * mask).clamp(0, 1)[0]
    full, bare, fitted = root / "full", root / "bare", root / "fitted"
    for case in (full, bare, fitted):
        case.mkdir(parents=True)
        _write_mask(case / "mask.png", mask)
    write_image(full / "image.png", image, srgb=True, bits=16)
    write_normals_npy(full / "normals.npy", normals[0])
    write_lighting(full / "lighting.json", sh)
    (full / "camera.json").write_text(json.dumps({"focal": 600.0, "principal_point": [21.0, 19.5]}))
    np.save(bare / "image.npy", image.permute(1, 2, 0).numpy())
    np.save(fitted / "image.npy", image.permute(1, 2, 0).numpy())
    write_normals_png(fitted / "normals.png", normals[0])
    (root / ".hidden").mkdir()
    return image, normals, mask, sh


class TestLoadFolder:
    def test_cases(self, tmp_path):
        image, normals, mask, sh = _folder_fixture(tmp_path)
        bare, fitted, full = load_folder(tmp_path)
        assert [s.name for s in (bare, fitted, full)] == ["bare", "fitted", "full"]
        assert [s.lighting_name for s in (bare, fitted, full)] == ["unknown", "fitted", "given"]
        for scene in (bare, fitted, full):
            assert torch.equal(scene.mask[0, 0], mask)
            assert torch.allclose(scene.image[0], image, atol=1e-4)  # the PNG decoded from sRGB
        assert bare.normals is None and bare.lighting is None and bare.source_lighting is None
        assert (bare.focal, bare.principal_point) == (None, None)
        assert torch.allclose(full.normals[0], normals[0], atol=1e-6)
        assert torch.equal(full.lighting[0], sh)
        assert (full.focal, full.principal_point) == (600.0, (21.0, 19.5))
        assert _angles_deg(fitted.normals[0], normals[0])[mask].max() < 0.01
        assert torch.allclose(fitted.lighting[0], sh, atol=2e-3 * float(sh.abs().max()))

    def test_missing_and_bad_files(self, tmp_path):
        with pytest.raises(ValueError, match="no case folder"):
            load_folder(tmp_path)
        _folder_fixture(tmp_path)
        (tmp_path / "bare" / "mask.png").unlink()
        with pytest.raises(FileNotFoundError, match="mask.png"):
            load_folder(tmp_path)
        _write_mask(tmp_path / "bare" / "mask.png", torch.ones(40, 40, dtype=torch.bool))
        (tmp_path / "full" / "camera.json").write_text(json.dumps({"focal": -5}))
        with pytest.raises(ValueError, match="camera.json.*focal"):
            load_folder(tmp_path)
        (tmp_path / "full" / "camera.json").write_text(json.dumps({"focal": 5, "cx": 3}))
        with pytest.raises(ValueError, match="unknown keys"):
            load_folder(tmp_path)
        (tmp_path / "full" / "camera.json").unlink()
        np.save(tmp_path / "full" / "image.npy", np.zeros((40, 40, 3), np.float32))
        with pytest.raises(ValueError, match="both image.png and image.npy"):
            load_folder(tmp_path)
        (tmp_path / "full" / "image.npy").unlink()
        np.save(tmp_path / "full" / "normals.npy", np.zeros((40, 40, 3), np.float32))
        with pytest.raises(ValueError, match="normals.npy.*unit length"):
            load_folder(tmp_path)
