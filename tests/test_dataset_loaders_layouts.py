"""The loaders agree with docs/conventions.md on axes: an analytic sphere rendered into each
layout on disk (written with numpy, scipy and OpenCV directly, not with sfs_torch.io, so
that the files follow each dataset's own convention and not ours by construction) comes
back with its normals, its mask, its image and its lighting; and an incomplete folder
gets one error naming the missing file.

The sphere sits off the image centre of a non-square image and the lighting comes from
the upper right in colour, so a flipped axis, a transpose or a swapped colour channel
changes the result at each pixel.
"""
import cv2
import numpy as np
import pytest
import scipy.io
import torch

from sfs_torch.dataset_loaders import directional_light_sh, load_diligent, load_folder, load_mit_berkeley
from sfs_torch.lighting import render_sh

H, W = 72, 96
# the sphere's centre in SPEC's camera frame (u right, v up, from the image centre), pixels
CENTRE_U, CENTRE_V, RADIUS = 9.0, 5.0, 28.0
# light from the upper right, towards the viewer; a reddish colour
LIGHT = np.array([0.5, 0.4, 0.768])
LIGHT = LIGHT / np.linalg.norm(LIGHT)
COLOUR = np.array([0.6, 0.5, 0.35])


def sphere(min_nz=0.0):
    """Analytic height (H, W) (NaN off the object), normals (3, H, W) and mask (H, W) of
    the sphere, from SPEC's pixel convention: pixel (i, j) sits at u = j + 0.5 - W/2,
    v = H/2 - (i + 0.5); x right, y up, z towards the viewer."""
    i = torch.arange(H, dtype=torch.float64)
    j = torch.arange(W, dtype=torch.float64)
    v, u = torch.meshgrid(H / 2 - (i + 0.5) - CENTRE_V, j + 0.5 - W / 2 - CENTRE_U, indexing="ij")
    r2 = u * u + v * v
    mask = r2 < RADIUS * RADIUS * (1 - min_nz * min_nz)
    z = torch.sqrt((RADIUS * RADIUS - r2).clamp_min(0))
    normals = torch.stack([u, v, z]) / RADIUS * mask
    return torch.where(mask, z + 10.0, float("nan")), normals, mask


def lighting():
    """SPEC SH (3, 9): the directional light plus an ambient term, positive on the whole sphere."""
    sh = directional_light_sh(torch.from_numpy(LIGHT), torch.from_numpy(COLOUR))
    sh[:, 0] += 0.3
    return sh


def angles_deg(a, b):
    """Per-pixel angle in degrees between (3, H, W) normal maps."""
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b, dim=0).norm(dim=0), (a * b).sum(0)))


def write_png(path, rgb, bits):
    """An RGB (or grey) float image in [0, 1], (H, W, 3) numpy, as a PNG of `bits` bits,
    with OpenCV (which takes BGR, so the file holds RGB)."""
    top = 65535 if bits == 16 else 255
    codes = np.round(np.clip(rgb, 0, 1) * top).astype(np.uint16 if bits == 16 else np.uint8)
    assert cv2.imwrite(str(path), codes[..., ::-1] if codes.ndim == 3 else codes)


def write_mask(path, mask):
    write_png(path, mask.numpy().astype(np.float64), 8)


def hwc(x):
    """(3, H, W) tensor -> (H, W, 3) float64 numpy, as files store it."""
    return x.permute(1, 2, 0).double().numpy()


def interior(mask):
    """Pixels whose 3x3 neighbourhood lies inside the mask (central differences there)."""
    m = mask.float()[None, None]
    return torch.nn.functional.max_pool2d(1 - m, 3, stride=1, padding=1)[0, 0] == 0


class TestSphereInEveryLayout:
    def test_mit_berkeley(self, tmp_path):
        height, analytic, mask = sphere(min_nz=0.3)
        sh = lighting()
        image = render_sh(analytic[None].float(), sh[None])[0].double() * mask
        lab = tmp_path / "MIT-Berkeley-Laboratory" / "ball"
        nat = tmp_path / "MIT-Berkeley-Natural" / "ball"
        lab.mkdir(parents=True)
        nat.mkdir(parents=True)
        scipy.io.savemat(lab / "Z.mat", {"depth": height.numpy()})  # row 0 is the image's top
        write_mask(lab / "mask.png", mask)
        write_png(nat / "shading_color.png", hwc(image), 16)

        (scene,) = load_mit_berkeley(tmp_path)
        assert scene.image.shape == (1, 3, H, W) and torch.equal(scene.mask[0, 0], mask)
        assert torch.allclose(scene.image[0].double(), image, atol=1 / 65535)  # 16-bit: linear
        # normals by central differences of the height: exact up to the differences'
        # truncation error, which grows with the slope (0.02 deg at n_z = 0.9, 0.5 deg at 0.4
        # on this 28 px sphere; an axis flipped would be tens of degrees off)
        errors = angles_deg(scene.normals[0], analytic)
        inner = interior(mask)
        assert errors[inner & (analytic[2] > 0.7)].max() < 0.08
        assert errors[inner].max() < 0.6 and errors[inner].median() < 0.06
        assert errors[mask].max() < 1.5  # one-sided differences at the edge
        assert float(scene.normals[0].abs().sum(0)[~mask].max()) == 0
        # the known lighting (a fit over those normals) is the lighting the image was made
        # with: its terms in x and y exactly; on a cap the terms in 1, z and z^2 trade off
        # against each other, so those are compared by what they render
        odd = [1, 3, 4, 5, 7, 8]
        assert torch.allclose(scene.lighting[0, :, odd].double(), sh[:, odd].double(), atol=3e-3)
        assert (render_sh(analytic[None].float(), scene.lighting)[0].double() - image)[:, mask].abs().max() < 6e-3
        again = render_sh(scene.normals, scene.lighting)[0].double()
        assert (again - image)[:, inner].abs().max() < 6e-3

    @pytest.mark.parametrize("normals_file, image_file", [("normals.npy", "image.npy"), ("normals.png", "image.png")])
    def test_folder(self, tmp_path, normals_file, image_file):
        _, analytic, mask = sphere()
        sh = lighting()
        image = render_sh(analytic[None].float(), sh[None])[0].double() * mask
        case = tmp_path / "ball"
        case.mkdir()
        write_mask(case / "mask.png", mask)
        if normals_file == "normals.npy":
            np.save(case / "normals.npy", hwc(analytic).astype(np.float32))  # (H, W, 3), SPEC frame
        else:  # 16-bit (n + 1) / 2
            write_png(case / "normals.png", (hwc(analytic) + 1) / 2, 16)
        if image_file == "image.npy":
            np.save(case / "image.npy", hwc(image).astype(np.float32))  # linear
        else:  # sRGB
            linear = hwc(image)
            srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)
            write_png(case / "image.png", srgb, 16)
        # no lighting.json: the known lighting is fitted to the image over the normals
        (scene,) = load_folder(tmp_path)
        assert scene.lighting_name == "fitted" and torch.equal(scene.mask[0, 0], mask)
        tolerance = 1e-4 if normals_file == "normals.npy" else 0.01  # float32 / 16-bit codes
        assert angles_deg(scene.normals[0], analytic)[mask].max() < tolerance
        assert float(scene.normals[0].abs().sum(0)[~mask].max()) == 0
        assert torch.allclose(scene.image[0].double(), image, atol=1e-6 if image_file == "image.npy" else 1e-4)
        assert torch.allclose(scene.lighting[0].double(), sh.double(), atol=1e-3)
        again = render_sh(scene.normals, scene.lighting)[0].double()
        assert (again - image)[:, mask].abs().max() < 1e-3

    def test_diligent(self, tmp_path):
        _, analytic, mask = sphere()
        folder = tmp_path / "pmsData" / "ballPNG"
        folder.mkdir(parents=True)
        # DiLiGenT's frame is SPEC's (docs/dataset_loaders.md): (H, W, 3), x right, y up, z out
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": hwc(analytic)})
        write_mask(folder / "mask.png", mask)
        directions = np.stack([LIGHT, [-0.3, 0.2, 0.93]])
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        intensities = np.array([[1.0, 1.2, 1.5], [0.9, 1.0, 1.1]])
        (folder / "filenames.txt").write_text("001.png\n002.png\n")
        np.savetxt(folder / "light_directions.txt", directions)
        np.savetxt(folder / "light_intensities.txt", intensities)
        shadings = []
        for k in range(2):
            shading = (hwc(analytic) @ directions[k]).clip(0) * mask.numpy()  # max(0, n . l)
            shadings.append(torch.from_numpy(shading))
            write_png(folder / f"{k + 1:03d}.png", COLOUR * intensities[k] * shading[..., None], 16)
        np.savetxt(folder / "K.txt", [[800.0, 0, W / 2 - 0.5], [0, 800.0, H / 2 - 0.5], [0, 0, 1]])

        scenes = list(load_diligent(tmp_path))
        assert [s.name for s in scenes] == ["ball|001", "ball|002"]
        for k, scene in enumerate(scenes):
            assert torch.equal(scene.mask[0, 0], mask)
            assert angles_deg(scene.normals[0], analytic)[mask].max() < 1e-3
            # the photograph over its light's intensity, scaled into [0, 1]: the albedo's shading
            peak = float(scene.image.max())
            assert peak == pytest.approx(1.0)
            expected = torch.from_numpy(COLOUR)[:, None, None] * shadings[k]
            scale = float(expected.max())
            assert torch.allclose(scene.image[0].double(), expected / scale, atol=5e-4)
            # the known lighting: the calibrated light (its direction in the camera frame)
            # with the image's colour, so that its clamped cosine is the image
            truth = directional_light_sh(torch.from_numpy(directions[k]), torch.from_numpy(COLOUR / scale))
            assert torch.allclose(scene.lighting[0].double(), truth, atol=1e-3)
            # its 9 SH terms reproduce the image up to the known truncation of the clamped
            # cosine (docs/dataset_loaders.md): 3.5% RMS of the colour, 9% at most
            again = render_sh(scene.normals, scene.lighting)[0].double()
            error = (again - scene.image[0].double())[:, mask] / torch.from_numpy(COLOUR / scale)[:, None]
            assert error.pow(2).mean().sqrt() < 0.045 and error.abs().max() < 0.12
            # camera centred on the image (OpenCV's cx = W/2 - 0.5 is SPEC's W/2)
            assert scene.focal == 800.0 and scene.principal_point == pytest.approx((W / 2, H / 2))


# --- an incomplete folder: one FileNotFoundError naming the missing file -------------------


def mit_layout(root):
    height, _, mask = sphere(min_nz=0.3)
    lab = root / "MIT-Berkeley-Laboratory" / "ball"
    nat = root / "MIT-Berkeley-Natural" / "ball"
    lab.mkdir(parents=True)
    nat.mkdir(parents=True)
    scipy.io.savemat(lab / "Z.mat", {"depth": height.numpy()})
    write_mask(lab / "mask.png", mask)
    write_png(nat / "shading_color.png", np.full((H, W, 3), 0.5) * mask.numpy()[..., None], 16)


def diligent_layout(root):
    _, analytic, mask = sphere()
    folder = root / "pmsData" / "ballPNG"
    folder.mkdir(parents=True)
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": hwc(analytic)})
    write_mask(folder / "mask.png", mask)
    (folder / "filenames.txt").write_text("001.png\n002.png\n")
    np.savetxt(folder / "light_directions.txt", [[0.0, 0.0, 1.0], [0.5, 0.0, 0.866]])
    np.savetxt(folder / "light_intensities.txt", np.ones((2, 3)))
    for k in range(2):
        write_png(folder / f"{k + 1:03d}.png", np.full((H, W, 3), 0.5), 16)


def folder_layout(root):
    _, analytic, mask = sphere()
    case = root / "ball"
    case.mkdir()
    write_mask(case / "mask.png", mask)
    np.save(case / "image.npy", np.full((H, W, 3), 0.5, np.float32))
    np.save(case / "normals.npy", hwc(analytic).astype(np.float32))


def check_one_error_naming(call, missing):
    with pytest.raises(FileNotFoundError) as caught:
        call()
    message = str(caught.value)
    assert str(missing) in message, message
    assert "\n" not in message  # one line, as sfs-torch-eval prints it


class TestIncompleteFolder:
    @pytest.mark.parametrize("file", ["MIT-Berkeley-Laboratory/ball/Z.mat",
                                      "MIT-Berkeley-Natural/ball/shading_color.png",
                                      "MIT-Berkeley-Laboratory/ball/mask.png"])
    def test_mit_berkeley(self, tmp_path, file):
        mit_layout(tmp_path)
        (tmp_path / file).unlink()
        check_one_error_naming(lambda: load_mit_berkeley(tmp_path), tmp_path / file)

    def test_mit_berkeley_dataset_folder(self, tmp_path):
        mit_layout(tmp_path)
        for path in sorted((tmp_path / "MIT-Berkeley-Laboratory").rglob("*"), reverse=True):
            path.unlink() if path.is_file() else path.rmdir()
        (tmp_path / "MIT-Berkeley-Laboratory").rmdir()
        check_one_error_naming(lambda: load_mit_berkeley(tmp_path), tmp_path / "MIT-Berkeley-Laboratory")

    @pytest.mark.parametrize("file", ["filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png",
                                      "Normal_gt.mat", "002.png"])
    def test_diligent(self, tmp_path, file):
        diligent_layout(tmp_path)
        (tmp_path / "pmsData" / "ballPNG" / file).unlink()
        # raised by the call itself, before any case is iterated
        check_one_error_naming(lambda: load_diligent(tmp_path), tmp_path / "pmsData" / "ballPNG" / file)

    @pytest.mark.parametrize("file", ["image.npy", "mask.png"])
    def test_folder(self, tmp_path, file):
        folder_layout(tmp_path)
        (tmp_path / "ball" / file).unlink()
        check_one_error_naming(lambda: load_folder(tmp_path), tmp_path / "ball" / file.replace(".npy", ".png"))

    def test_folder_optional_files_are_optional(self, tmp_path):
        folder_layout(tmp_path)
        (tmp_path / "ball" / "normals.npy").unlink()
        (scene,) = load_folder(tmp_path)
        assert scene.normals is None and scene.lighting is None
