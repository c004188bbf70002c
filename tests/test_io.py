import json
import re

import cv2
import numpy as np
import pytest
import torch
import trimesh
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb

from sfs_torch import io
from sfs_torch.integrability import depth_to_mesh
from sfs_torch.metrics import angular_error


def _write_raw(path, rgb):
    """Write integer samples with OpenCV, bypassing sfs_torch.io (RGB(A) -> BGR(A))."""
    if rgb.ndim == 3:
        order = [2, 1, 0, 3][: rgb.shape[2]]
        rgb = rgb[..., order]
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb))


def _read_raw(path):
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return raw[..., ::-1] if raw.ndim == 3 else raw


def _all_codes(bits):
    """(H, W, 3) RGB array holding every code of the bit depth, in a different order per channel."""
    dtype = np.uint8 if bits == 8 else np.uint16
    codes = np.arange(2**bits, dtype=dtype).reshape(2 ** (bits // 2), -1)
    perm = np.random.default_rng(0).permutation(codes.ravel()).reshape(codes.shape)
    return np.stack([codes, codes[::-1, ::-1], perm], axis=-1)


def _sphere_normals(size=24):
    c = (np.arange(size) + 0.5) / size * 2 - 1
    y, x = np.meshgrid(-c, c, indexing="ij")
    r2 = x * x + y * y
    inside = r2 < 0.9
    n = np.stack([x, y, np.sqrt(np.clip(1 - r2, 0, 1))]) * inside
    return torch.from_numpy(n).float(), torch.from_numpy(inside)[None]


class TestSRGB:
    def test_vs_kornia(self):
        x = torch.linspace(0, 1, 999, dtype=torch.float64).view(1, 3, 1, 333)
        torch.testing.assert_close(io.srgb_to_linear(x), rgb_to_linear_rgb(x))
        torch.testing.assert_close(io.linear_to_srgb(x), linear_rgb_to_rgb(x))

    def test_round_trip_and_values(self):
        x = torch.linspace(0, 1, 10001, dtype=torch.float64)
        torch.testing.assert_close(io.linear_to_srgb(io.srgb_to_linear(x)), x, atol=1e-12, rtol=0)
        assert io.srgb_to_linear(torch.tensor(0.5, dtype=torch.float64)).item() == pytest.approx(0.21404114, abs=1e-8)
        # the standard's two segments meet at 0.04045 to within its rounded constants
        lo, hi = io.srgb_to_linear(torch.tensor([0.04045, 0.04045 + 1e-9], dtype=torch.float64))
        assert abs(hi.item() - lo.item()) < 1e-8

    @pytest.mark.parametrize("dtype", [torch.uint8, torch.int64])
    def test_integer_codes_are_refused(self, dtype):
        # uint8 codes decoded to values up to 5.2e5
        codes = torch.tensor([0, 128, 255], dtype=dtype)
        for function, what in ((io.srgb_to_linear, "sRGB values in [0, 1]"), (io.linear_to_srgb, "linear values")):
            with pytest.raises(ValueError, match=rf"^x must be a floating-point tensor of {re.escape(what)}, got "
                                                 rf"{dtype}: divide 8-bit codes by 255 \(16-bit ones by 65535\) first$"):
                function(codes)

    def test_srgb_range(self):
        with pytest.raises(ValueError, match=r"^x must hold sRGB values in \[0, 1\], got values in \[0, 255\]: divide 8-bit"):
            io.srgb_to_linear(torch.tensor([0.0, 128.0, 255.0]))
        with pytest.raises(ValueError, match=r"got values in \[-0.1, 0.5\]"):
            io.srgb_to_linear(torch.tensor([-0.1, 0.5]))
        with pytest.raises(TypeError, match=r"^x must be a torch.Tensor of linear values, got list$"):
            io.linear_to_srgb([0.5])
        assert io.srgb_to_linear(torch.zeros(0)).shape == (0,)
        # linear values beyond 1 (highlights) still encode, along the curve
        assert io.linear_to_srgb(torch.tensor([2.0], dtype=torch.float64)).item() == pytest.approx(1.055 * 2 ** (1 / 2.4) - 0.055)


class TestReadWriteImage:
    @pytest.mark.parametrize("bits", [8, 16])
    @pytest.mark.parametrize("srgb", [False, True])
    def test_every_code_round_trips(self, tmp_path, bits, srgb):
        raw = _all_codes(bits)
        _write_raw(tmp_path / "in.png", raw)
        image = io.read_image(tmp_path / "in.png", srgb=srgb)
        assert image.shape == (3,) + raw.shape[:2] and image.dtype == torch.float32
        assert float(image.min()) == 0.0 and float(image.max()) == 1.0
        if not srgb:  # linear files: the value is code / max, channel by channel (RGB, not BGR)
            codes = np.round(image.double().numpy() * (2**bits - 1)).astype(raw.dtype)
            np.testing.assert_array_equal(codes, raw.transpose(2, 0, 1))
        io.write_image(tmp_path / "out.png", image, srgb=srgb, bits=bits)
        out = _read_raw(tmp_path / "out.png")
        assert out.dtype == raw.dtype
        np.testing.assert_array_equal(out, raw)

    def test_srgb_decoding(self, tmp_path):
        raw = np.array([[[0, 128, 255]]], dtype=np.uint8)
        _write_raw(tmp_path / "a.png", raw)
        image = io.read_image(tmp_path / "a.png")[:, 0, 0].double()
        expected = rgb_to_linear_rgb(torch.tensor([0, 128, 255], dtype=torch.float64).view(1, 3, 1, 1) / 255).flatten()
        torch.testing.assert_close(image, expected, atol=1e-7, rtol=0)

    def test_channel_order(self, tmp_path):
        red = torch.zeros(3, 2, 3)
        red[0] = 1.0
        io.write_image(tmp_path / "red.png", red)
        bgr = cv2.imread(str(tmp_path / "red.png"), cv2.IMREAD_UNCHANGED)
        assert (bgr[..., 2] == 255).all() and (bgr[..., :2] == 0).all()
        torch.testing.assert_close(io.read_image(tmp_path / "red.png"), red)

    def test_grey(self, tmp_path):
        raw = np.array([[0, 1000], [40000, 65535]], dtype=np.uint16)
        _write_raw(tmp_path / "g.png", raw)
        image = io.read_image(tmp_path / "g.png", srgb=False)
        assert image.shape == (3, 2, 2)
        torch.testing.assert_close(image, torch.from_numpy(raw / 65535).float().expand(3, 2, 2))
        io.write_image(tmp_path / "g_out.png", image[0], srgb=False, bits=16)
        np.testing.assert_array_equal(_read_raw(tmp_path / "g_out.png"), raw)

    def test_rgba_drops_alpha(self, tmp_path):
        raw = np.zeros((3, 4, 4), dtype=np.uint8)
        raw[..., 1] = 255
        raw[1:, :, 3] = 255
        _write_raw(tmp_path / "rgba.png", raw)
        image = io.read_image(tmp_path / "rgba.png")
        assert image.shape == (3, 3, 4) and (image[1] == 1).all() and (image[[0, 2]] == 0).all()

    def test_jpeg_exif_orientation_is_applied(self, tmp_path):
        from PIL import Image

        raw = np.zeros((16, 32, 3), dtype=np.uint8)
        raw[:8, :8] = 255  # a white block in the stored top-left corner
        exif = Image.new("RGB", (1, 1)).getexif()
        exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
        Image.fromarray(raw).save(tmp_path / "a.jpg", exif=exif, quality=95)
        Image.fromarray(raw[..., 0]).save(tmp_path / "m.jpg", exif=exif, quality=95)
        upright = np.rot90(raw, k=-1)[..., 0] > 127
        image = io.read_image(tmp_path / "a.jpg", srgb=False)
        assert image.shape == (3, 32, 16)
        np.testing.assert_array_equal(image[0].numpy() > 0.5, upright)
        np.testing.assert_array_equal(io.read_mask(tmp_path / "m.jpg")[0].numpy(), upright)

    def test_jpeg(self, tmp_path):
        raw = np.full((16, 16, 3), (200, 100, 50), dtype=np.uint8)
        _write_raw(tmp_path / "a.jpg", raw)
        image = io.read_image(tmp_path / "a.jpg")
        expected = io.srgb_to_linear(torch.tensor([200, 100, 50]) / 255.0)
        torch.testing.assert_close(image.mean((1, 2)), expected, atol=0.01, rtol=0)

    def test_npy_is_linear(self, tmp_path):
        array = np.random.default_rng(1).random((5, 6, 3)).astype(np.float32)
        np.save(tmp_path / "a.npy", array)
        for srgb in (True, False):
            image = io.read_image(tmp_path / "a.npy", srgb=srgb)
            np.testing.assert_array_equal(image.numpy(), array.transpose(2, 0, 1))
        np.save(tmp_path / "g.npy", array[..., 0].astype(np.float64))
        np.testing.assert_array_equal(io.read_image(tmp_path / "g.npy").numpy(), np.repeat(array[None, ..., 0], 3, 0))

    def test_write_exception(self, tmp_path):
        image = torch.full((3, 4, 4), 0.5)
        with pytest.raises(ValueError, match="bits must be 8 or 16"):
            io.write_image(tmp_path / "a.png", image, bits=12)
        with pytest.raises(ValueError, match=r"image values must lie in \[0, 1\]"):
            io.write_image(tmp_path / "a.png", image + 0.6)
        with pytest.raises(ValueError, match="image contains 3 NaN"):
            io.write_image(tmp_path / "a.png", torch.where(torch.arange(16).view(4, 4) == 3, float("nan"), image))
        with pytest.raises(ValueError, match="image must have shape"):
            io.write_image(tmp_path / "a.png", image[:2])
        with pytest.raises(ValueError, match="image must be a floating-point"):
            io.write_image(tmp_path / "a.png", torch.ones(3, 4, 4, dtype=torch.uint8))
        with pytest.raises(ValueError, match="must end in '.png'"):
            io.write_image(tmp_path / "a.jpg", image)
        assert not any(tmp_path.iterdir())


class TestReadMask:
    def test_png(self, tmp_path):
        raw = np.zeros((4, 5), dtype=np.uint8)
        raw[1:3, 1:4] = 255
        raw[0, 0] = 1
        _write_raw(tmp_path / "m.png", raw)
        mask = io.read_mask(tmp_path / "m.png")
        assert mask.shape == (1, 4, 5) and mask.dtype == torch.bool
        np.testing.assert_array_equal(mask[0].numpy(), raw != 0)
        rgb = np.zeros((4, 5, 3), dtype=np.uint16)
        rgb[2, 3, 2] = 7
        _write_raw(tmp_path / "rgb.png", rgb)
        assert io.read_mask(tmp_path / "rgb.png").nonzero().tolist() == [[0, 2, 3]]

    def test_jpeg_compression_noise_is_not_object(self, tmp_path):
        yy, xx = np.mgrid[:64, :64]
        truth = (yy - 30) ** 2 + (xx - 34) ** 2 < 20**2
        assert cv2.imwrite(str(tmp_path / "m.jpg"), truth.astype(np.uint8) * 255, [cv2.IMWRITE_JPEG_QUALITY, 40])
        noisy = _read_raw(tmp_path / "m.jpg")
        assert ((noisy != 0) & ~truth).sum() > 100  # the background really holds ringing
        mask = io.read_mask(tmp_path / "m.jpg")[0].numpy()
        assert (mask != truth).sum() <= 0.02 * truth.sum()

    def test_rgba_alpha(self, tmp_path):
        raw = np.full((4, 5, 4), 255, dtype=np.uint8)
        raw[..., 3] = 0
        raw[2:, 1:, 3] = 1
        raw[3, 4, :3] = 0  # a black object pixel is still object
        _write_raw(tmp_path / "m.png", raw)
        np.testing.assert_array_equal(io.read_mask(tmp_path / "m.png")[0].numpy(), raw[..., 3] > 0)

    def test_npy(self, tmp_path):
        array = np.random.default_rng(2).random((4, 5)) > 0.5
        files = {"b.npy": array, "f.npy": array.astype(np.float32), "u.npy": array[None].astype(np.uint8)}
        for name, value in files.items():
            np.save(tmp_path / name, value)
            np.testing.assert_array_equal(io.read_mask(tmp_path / name)[0].numpy(), array)

    def test_exception(self, tmp_path):
        np.save(tmp_path / "nan.npy", np.full((3, 3), np.nan))
        with pytest.raises(ValueError, match="NaN"):
            io.read_mask(tmp_path / "nan.npy")
        np.save(tmp_path / "shape.npy", np.ones((2, 3, 3)))
        with pytest.raises(ValueError, match=r"path .*shape \(2, 3, 3\)"):
            io.read_mask(tmp_path / "shape.npy")


class TestReadImageAndMask:
    def _rgba(self, path):
        raw = np.full((4, 6, 4), 200, dtype=np.uint8)
        raw[..., 3] = 0
        raw[1:3, 2:5, 3] = 255
        _write_raw(path, raw)
        return raw

    def test_alpha_as_mask(self, tmp_path):
        raw = self._rgba(tmp_path / "a.png")
        loaded = io.read_image_and_mask(tmp_path / "a.png")
        assert isinstance(loaded, io.ImageAndMask)
        assert loaded.image.shape == (3, 4, 6) and loaded.mask.shape == (1, 4, 6)
        np.testing.assert_array_equal(loaded.mask[0].numpy(), raw[..., 3] > 0)

    def test_mask_file_wins(self, tmp_path):
        self._rgba(tmp_path / "a.png")
        np.save(tmp_path / "m.npy", np.eye(4, 6, dtype=bool))
        loaded = io.read_image_and_mask(tmp_path / "a.png", tmp_path / "m.npy", srgb=False)
        np.testing.assert_array_equal(loaded.mask[0].numpy(), np.eye(4, 6, dtype=bool))
        assert loaded.image[0, 0, 0].item() == pytest.approx(200 / 255)

    def test_exception(self, tmp_path):
        _write_raw(tmp_path / "rgb.png", np.zeros((4, 6, 3), dtype=np.uint8))
        with pytest.raises(ValueError, match="mask_path is required"):
            io.read_image_and_mask(tmp_path / "rgb.png")
        np.save(tmp_path / "m.npy", np.ones((4, 5), dtype=bool))
        with pytest.raises(ValueError, match="same size"):
            io.read_image_and_mask(tmp_path / "rgb.png", tmp_path / "m.npy")
        with pytest.raises(FileNotFoundError, match="mask_path: no such file: '.*nope.png'"):
            io.read_image_and_mask(tmp_path / "rgb.png", tmp_path / "nope.png")
        (tmp_path / "junk.png").write_text("not an image")
        with pytest.raises(ValueError, match="image_path '.*junk.png': expected"):
            io.read_image_and_mask(tmp_path / "junk.png", tmp_path / "m.npy")


class TestNormalsPNG:
    def test_round_trip(self, tmp_path):
        normals, mask = _sphere_normals()
        io.write_normals_png(tmp_path / "n.png", normals)
        raw = cv2.imread(str(tmp_path / "n.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (24, 24, 3)
        colour = torch.from_numpy(raw[..., ::-1].astype(np.float64) / 65535).permute(2, 0, 1)
        torch.testing.assert_close(colour, (normals.double() + 1) / 2, atol=2e-5, rtol=0)
        back = io.read_normals_png(tmp_path / "n.png")
        assert back.shape == (3, 24, 24) and back.dtype == torch.float32
        assert bool((back[:, ~mask[0]] == 0).all())
        assert float(angular_error(back, normals, mask).max()) < 0.01
        assert float((back.norm(dim=0)[mask[0]] - 1).abs().max()) < 5e-5

    def test_every_code_round_trips(self, tmp_path):
        raw = _all_codes(16)
        _write_raw(tmp_path / "in.png", raw)
        io.write_normals_png(tmp_path / "out.png", io.read_normals_png(tmp_path / "in.png"))
        np.testing.assert_array_equal(_read_raw(tmp_path / "out.png"), raw)

    def test_exception(self, tmp_path):
        normals, _ = _sphere_normals(4)
        with pytest.raises(ValueError, match="normals must have shape"):
            io.write_normals_png(tmp_path / "n.png", normals[None])
        with pytest.raises(ValueError, match=r"normals components must lie in \[-1, 1\]"):
            io.write_normals_png(tmp_path / "n.png", 1.5 * normals)
        _write_raw(tmp_path / "n8.png", np.zeros((4, 4, 3), dtype=np.uint8))
        with pytest.raises(ValueError, match="expected a 16-bit RGB PNG"):
            io.read_normals_png(tmp_path / "n8.png")


class TestNormalsNpy:
    def test_layout_and_round_trip(self, tmp_path):
        normals, _ = _sphere_normals(8)
        io.write_normals_npy(tmp_path / "n.npy", normals.double())
        array = np.load(tmp_path / "n.npy")
        assert array.shape == (8, 8, 3) and array.dtype == np.float32
        np.testing.assert_array_equal(array, normals.permute(1, 2, 0).numpy())
        back = io.read_normals_npy(tmp_path / "n.npy")
        assert back.dtype == torch.float32
        assert torch.equal(back, normals)

    def test_exception(self, tmp_path):
        with pytest.raises(ValueError, match="must end in '.npy'"):
            io.write_normals_npy(tmp_path / "n", torch.zeros(3, 2, 2))
        np.save(tmp_path / "chw.npy", np.zeros((3, 4, 5), dtype=np.float32))
        expected = r"expected a float .npy normal map of shape \(H, W, 3\), got an array of shape \(3, 4, 5\)"
        with pytest.raises(ValueError, match=expected):
            io.read_normals_npy(tmp_path / "chw.npy")
        np.save(tmp_path / "int.npy", np.zeros((4, 5, 3), dtype=np.int32))
        with pytest.raises(ValueError, match="dtype int32"):
            io.read_normals_npy(tmp_path / "int.npy")


def _hemisphere(size=24, radius=9.0):
    """Height ``(H, W)`` float32 of a hemisphere over a disk mask, its mask and unit normals ``(3, H, W)``."""
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    v, u = torch.meshgrid(-c, c, indexing="ij")
    mask = u**2 + v**2 < (radius - 1) ** 2
    z = torch.sqrt((radius**2 - u**2 - v**2).clamp_min(0))
    normals = torch.stack([u, v, z]) / radius * mask
    return (z * mask).float(), mask, normals.float()


def _load_mesh(path):
    loaded = trimesh.load(path, process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):  # GLB: one mesh under an identity node
        (node,) = loaded.graph.nodes_geometry
        np.testing.assert_array_equal(loaded.graph[node][0], np.eye(4))
        (loaded,) = loaded.geometry.values()
    return loaded


class TestDepthPNG:
    def test_round_trip_within_the_quantisation_step(self, tmp_path):
        depth, mask, _ = _hemisphere()
        depth = depth - 4.0  # negative heights too
        info = io.write_depth_png(tmp_path / "d.png", depth, mask[None])
        assert set(info) == {"scale", "offset", "depth_min", "depth_max"}
        assert all(type(v) is float for v in info.values())
        assert info["depth_min"] == float(depth[mask].min()) and info["depth_max"] == float(depth[mask].max())
        assert info["scale"] == pytest.approx((info["depth_max"] - info["depth_min"]) / 65534, rel=1e-12)
        raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (24, 24)
        # the full 16-bit range on the mask, 0 outside
        assert raw[mask.numpy()].min() == 1 and raw[mask.numpy()].max() == 65535
        assert np.all(raw[~mask.numpy()] == 0)
        back = io.read_depth_png(tmp_path / "d.png", scale=info["scale"], offset=info["offset"])
        assert back.depth.shape == (1, 24, 24) and back.depth.dtype == torch.float32
        assert torch.equal(back.mask[0], mask)
        assert bool((back.depth[0][~mask] == 0).all())
        error = (back.depth[0].double() - depth.double())[mask].abs().max()
        assert float(error) <= info["scale"] / 2 + 1e-6
        # JSON keeps the floats exactly
        assert json.loads(json.dumps(info)) == info

    def test_background_values_are_ignored_and_constant_depth(self, tmp_path):
        depth, mask, _ = _hemisphere(8, 4.0)
        info = io.write_depth_png(tmp_path / "d.png", torch.where(mask, 2.5, float("nan")), mask)
        assert info["scale"] == 0 and info["offset"] == 2.5
        back = io.read_depth_png(tmp_path / "d.png", **{k: info[k] for k in ("scale", "offset")})
        assert torch.equal(back.depth[0], torch.where(mask, 2.5, 0.0))
        raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
        assert set(np.unique(raw[mask.numpy()])) == {1}

    def test_exception(self, tmp_path):
        depth, mask, _ = _hemisphere(8, 4.0)
        with pytest.raises(ValueError, match="must end in '.png'"):
            io.write_depth_png(tmp_path / "d.tif", depth, mask)
        with pytest.raises(ValueError, match="mask is empty"):
            io.write_depth_png(tmp_path / "d.png", depth, torch.zeros_like(mask))
        with pytest.raises(ValueError, match="same size"):
            io.write_depth_png(tmp_path / "d.png", depth, mask[:4])
        with pytest.raises(ValueError, match=r"depth must have shape \(1, H, W\) or \(H, W\)"):
            io.write_depth_png(tmp_path / "d.png", depth.expand(3, 8, 8), mask)
        bad = depth.clone()
        bad[4, 4] = float("inf")
        assert mask[4, 4]
        with pytest.raises(ValueError, match="depth on the mask contains 1 NaN or infinite"):
            io.write_depth_png(tmp_path / "d.png", bad, mask)
        assert not (tmp_path / "d.png").exists()
        _write_raw(tmp_path / "rgb.png", np.zeros((4, 4, 3), dtype=np.uint16))
        with pytest.raises(ValueError, match="expected a 16-bit grey PNG"):
            io.read_depth_png(tmp_path / "rgb.png", scale=1.0, offset=0.0)


class TestWriteMesh:
    @pytest.mark.parametrize("kind", io.MESH_FORMATS)
    def test_round_trip_with_normals(self, tmp_path, kind):
        depth, mask, normals = _hemisphere()
        mesh = depth_to_mesh(depth, mask)
        assert len(np.unique(mesh.faces)) == len(mesh.vertices)  # trimesh's OBJ reader drops unused vertices
        vertex_normals = normals[:, mask].T  # the estimate at each vertex, unlike the faces' average
        own = mesh.vertex_normals.copy()  # trimesh's, from the faces
        assert not np.allclose(own, vertex_normals.numpy(), atol=1e-3)
        io.write_mesh(tmp_path / f"mesh.{kind}", mesh, vertex_normals=vertex_normals)
        np.testing.assert_array_equal(mesh.vertex_normals, own)  # the caller's mesh is left alone
        back = _load_mesh(tmp_path / f"mesh.{kind}")
        assert "vertex_normals" in back._cache  # read from the file, not recomputed
        np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(back.faces, mesh.faces)
        np.testing.assert_allclose(back.vertex_normals, vertex_normals.numpy(), rtol=0, atol=1e-6)

    @pytest.mark.parametrize("kind", ["ply", "glb"])
    def test_unused_vertices_are_kept(self, tmp_path, kind):
        depth, mask, normals = _hemisphere(12, 5.0)
        mask[0, 0] = True  # an isolated pixel: a vertex without faces
        mesh = depth_to_mesh(depth, mask)
        vertex_normals = torch.nn.functional.normalize(normals[:, mask].T + torch.tensor([0.0, 0.0, 1e-3]), dim=1)
        io.write_mesh(tmp_path / f"m.{kind}", mesh, vertex_normals=vertex_normals)
        back = _load_mesh(tmp_path / f"m.{kind}")
        assert len(back.vertices) == int(mask.sum())
        np.testing.assert_allclose(back.vertex_normals, vertex_normals.numpy(), rtol=0, atol=1e-6)

    def test_obj_text_and_default_normals(self, tmp_path):
        depth, mask, _ = _hemisphere(8, 4.0)
        mesh = depth_to_mesh(depth, mask)
        io.write_mesh(tmp_path / "m.obj", mesh)  # trimesh's own normals (from the faces)
        lines = (tmp_path / "m.obj").read_text().splitlines()
        count = {kind: sum(line.startswith(kind + " ") for line in lines) for kind in ("v", "vn")}
        assert count == {"v": len(mesh.vertices), "vn": len(mesh.vertices)}
        assert not list(tmp_path.glob("*.mtl"))
        np.testing.assert_allclose(_load_mesh(tmp_path / "m.obj").vertex_normals, mesh.vertex_normals, atol=1e-7)

    def test_exception(self, tmp_path):
        depth, mask, normals = _hemisphere(8, 4.0)
        mesh = depth_to_mesh(depth, mask)
        with pytest.raises(ValueError, match=r"path must end in .ply, .obj, .glb, got '.*m.stl'"):
            io.write_mesh(tmp_path / "m.stl", mesh)
        with pytest.raises(TypeError, match="trimesh.Trimesh"):
            io.write_mesh(tmp_path / "m.ply", mesh.vertices)
        with pytest.raises(ValueError, match=r"vertex_normals must have shape \(\d+, 3\)"):
            io.write_mesh(tmp_path / "m.ply", mesh, vertex_normals=normals[:, mask])
        bad = normals[:, mask].T.clone()
        bad[0, 0] = float("nan")
        with pytest.raises(ValueError, match="1 NaN or infinite"):
            io.write_mesh(tmp_path / "m.ply", mesh, vertex_normals=bad)
        with pytest.raises(ValueError, match="mesh has no vertices"):
            io.write_mesh(tmp_path / "m.ply", trimesh.Trimesh())
        assert not list(tmp_path.iterdir())

    def test_glb_refuses_zero_normals(self, tmp_path):
        depth, mask, normals = _hemisphere(8, 4.0)
        mesh = depth_to_mesh(depth, mask)
        zero = normals[:, mask].T.clone()
        zero[:2] = 0
        with pytest.raises(ValueError, match=r"vertex_normals holds 2 zero-length normals, which glTF \(.glb\)"):
            io.write_mesh(tmp_path / "m.glb", mesh, vertex_normals=zero)
        assert not list(tmp_path.iterdir())
        io.write_mesh(tmp_path / "m.ply", mesh, vertex_normals=zero)  # PLY stores them as they are
        np.testing.assert_array_equal(_load_mesh(tmp_path / "m.ply").vertex_normals[:2], 0.0)


class TestLighting:
    def test_round_trip(self, tmp_path):
        sh = torch.randn(3, 9, generator=torch.Generator().manual_seed(3))
        io.write_lighting(tmp_path / "l.json", sh)
        content = json.loads((tmp_path / "l.json").read_text())
        assert list(content) == ["sh"] and [len(row) for row in content["sh"]] == [9, 9, 9]
        back = io.read_lighting(tmp_path / "l.json")
        assert back.dtype == torch.float32 and torch.equal(back, sh)
        io.write_lighting(tmp_path / "d.json", sh.double() / 3)
        np.testing.assert_array_equal(json.loads((tmp_path / "d.json").read_text())["sh"], (sh.double() / 3).numpy())

    @pytest.mark.parametrize(
        "text, match",
        [
            ("{not json", "not valid JSON"),
            ('{"coefficients": []}', "no 'sh' key"),
            ('{"sh": [[1, 2, 3]]}', r"'sh' of shape \(1, 3\)"),
            ('{"sh": [[1, 2], [3]]}', "not lists of numbers"),
            ('{"sh": ' + json.dumps([[float("nan")] * 9] * 3) + "}", "NaN or infinite"),
            ('{"sh": ' + json.dumps([[1e300] * 9] * 3) + "}", "beyond float32's range"),  # inf once float32
        ],
    )
    def test_read_exception(self, tmp_path, text, match):
        (tmp_path / "l.json").write_text(text)
        with pytest.raises(ValueError, match=match):
            io.read_lighting(tmp_path / "l.json")

    def test_write_exception(self, tmp_path):
        with pytest.raises(ValueError, match=r"sh must have shape \(3, 9\)"):
            io.write_lighting(tmp_path / "l.json", torch.zeros(1, 3, 9))
        bad = torch.zeros(3, 9)
        bad[1, 4] = float("nan")
        with pytest.raises(ValueError, match="sh contains 1 NaN"):
            io.write_lighting(tmp_path / "l.json", bad)
        with pytest.raises(ValueError, match="must end in '.json'"):
            io.write_lighting(tmp_path / "l.txt", torch.zeros(3, 9))


@pytest.mark.parametrize(
    "reader", [io.read_image, io.read_mask, io.read_normals_png, io.read_normals_npy, io.read_lighting]
)
def test_missing_file(tmp_path, reader):
    path = tmp_path / "missing.file"
    with pytest.raises(FileNotFoundError, match="missing.file"):
        reader(path)
    with pytest.raises(ValueError, match="must be a file"):
        reader(tmp_path)


class TestBadImageFiles:
    def test_undecodable(self, tmp_path):
        (tmp_path / "text.png").write_text("hello")
        (tmp_path / "empty.png").write_bytes(b"")
        for name in ("text.png", "empty.png"):
            with pytest.raises(ValueError, match=r"path '.*': expected an 8- or 16-bit PNG.*OpenCV cannot decode"):
                io.read_image(tmp_path / name)

    @pytest.mark.parametrize(
        "array, match",
        [
            (np.zeros((4, 4, 4), dtype=np.float32), r"shape \(4, 4, 4\)"),
            (np.zeros((4, 4, 3), dtype=np.uint8), "dtype uint8"),
            (np.full((4, 4, 3), np.inf, dtype=np.float32), "48 NaN or infinite"),
            (np.full((4, 4, 3), 1.5, dtype=np.float32), r"expected values in \[0, 1\], got values in \[1.5, 1.5\]"),
        ],
    )
    def test_bad_npy(self, tmp_path, array, match):
        np.save(tmp_path / "a.npy", array)
        with pytest.raises(ValueError, match=match):
            io.read_image(tmp_path / "a.npy")

    def test_no_pickle(self, tmp_path):
        np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
        with pytest.raises(ValueError, match="NumPy cannot load"):
            io.read_image(tmp_path / "obj.npy")
