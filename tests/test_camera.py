import pytest
import torch

from sfs_torch.camera import (
    CameraRotation,
    centroid_rotation,
    perspective_rotation,
    pixel_grid,
    rotate_normals_to_camera,
)


def random_normals(b, h, w, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(b, 3, h, w, generator=g, dtype=dtype)
    n[:, 2] = n[:, 2].abs()
    return n / n.norm(dim=1, keepdim=True)


class TestPixelGrid:
    def test_convention(self):
        uv = pixel_grid(4, 6)
        # row 0, col 0 is the top-left pixel: left of centre (u < 0) and above it (v > 0)
        assert uv[:, 0, 0].tolist() == [-2.5, 1.5]
        assert uv[:, 3, 5].tolist() == [2.5, -1.5]

    def test_principal_point(self):
        uv = pixel_grid(3, 3, principal_point=(0.0, 0.0))
        assert uv[:, 0, 0].tolist() == [0.5, -0.5]


class TestPerspectiveRotation:
    def test_maps_optical_axis_to_camera_direction(self, dtype):
        g = torch.Generator().manual_seed(0)
        u = torch.randn(50, generator=g, dtype=dtype) * 300
        v = torch.randn(50, generator=g, dtype=dtype) * 300
        f = 500.0
        rot = perspective_rotation(u, v, f)
        d = rot @ torch.tensor([0, 0, 1], dtype=dtype)
        target = torch.stack([-u, -v, torch.full_like(u, f)], -1)
        target = target / target.norm(dim=-1, keepdim=True)
        assert torch.allclose(d, target, atol=1e-6)
        assert torch.allclose(rot @ rot.transpose(-1, -2), torch.eye(3, dtype=dtype).expand(50, 3, 3), atol=1e-6)
        assert torch.allclose(torch.det(rot), torch.ones(50, dtype=dtype), atol=1e-6)

    def test_keeps_horizontal_vectors_horizontal(self):
        rot = perspective_rotation(torch.tensor([120.0]), torch.tensor([-80.0]), 400.0)
        assert abs(float((rot @ torch.tensor([1.0, 0, 0]))[0, 1])) < 1e-7

    def test_centre_is_identity(self):
        assert torch.allclose(perspective_rotation(torch.zeros(1), torch.zeros(1), 100.0)[0], torch.eye(3))

    def test_exception(self):
        with pytest.raises(ValueError, match="focal"):
            perspective_rotation(torch.zeros(1), torch.zeros(1), 0.0)


class TestRotateNormalsToCamera:
    def test_front_facing_normals_point_to_camera(self):
        h, w, f = 8, 10, 20.0
        n = torch.zeros(2, 3, h, w)
        n[:, 2] = 1
        out = rotate_normals_to_camera(n, f)
        uv = pixel_grid(h, w)
        target = torch.stack([-uv[0], -uv[1], torch.full_like(uv[0], f)])
        target = target / target.norm(dim=0)
        assert torch.allclose(out[1], target, atol=1e-6)

    def test_centroid_rotation(self):
        mask = torch.zeros(1, 1, 9, 9, dtype=torch.bool)
        mask[0, 0, 0, 8] = True  # top-right pixel: u = 4, v = 4
        rot = centroid_rotation(mask, 10.0)
        assert torch.allclose(rot, perspective_rotation(torch.tensor([4.0]), torch.tensor([4.0]), 10.0))

    def test_centroid_rotation_mask_forms(self):
        mask = torch.zeros(1, 1, 9, 9, dtype=torch.bool)
        mask[0, 0, 2:4, 5:8] = True
        rot = centroid_rotation(mask, 10.0)
        assert torch.equal(centroid_rotation(mask[0], 10.0), rot[0])  # (1, H, W): one (3, 3)
        assert torch.equal(centroid_rotation(mask[0, 0].float(), 10.0), rot[0])  # (H, W), 0/1

    @pytest.mark.parametrize("mask, message", [
        (torch.zeros(1, 1, 9, 9, dtype=torch.bool), r"^mask is empty"),
        (torch.ones(1, 3, 9, 9), r"^mask must have shape \(B, 1, H, W\), got \(1, 3, 9, 9\)"),
        (torch.full((1, 1, 9, 9), 0.5), r"^mask must be boolean or hold only 0 and 1"),
    ])
    def test_centroid_rotation_checks_the_mask(self, mask, message):
        with pytest.raises(ValueError, match=message):
            centroid_rotation(mask, 10.0)

    @pytest.mark.parametrize("focal, principal_point, message", [
        ("50", None, r"^focal must be a positive focal length in pixels, got '50'$"),
        (float("inf"), None, r"^focal must be a positive focal length in pixels, got inf$"),
        (None, None, r"^focal must be a positive focal length in pixels, got None$"),
        (50.0, (float("nan"), 3.0), r"^principal_point must be two finite numbers \(cx, cy\) in pixels, got \(nan, 3.0\)$"),
        (50.0, (3.0,), r"^principal_point must be two finite numbers \(cx, cy\) in pixels, got \(3.0,\)$"),
        (50.0, "12", r"^principal_point must be two finite numbers"),
    ])
    def test_camera_is_checked(self, focal, principal_point, message):
        n = random_normals(1, 4, 4)
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        for call in (lambda: rotate_normals_to_camera(n, focal, principal_point),
                     lambda: centroid_rotation(mask, focal, principal_point),
                     lambda: CameraRotation(focal, principal_point)):
            with pytest.raises(ValueError, match=message):
                call()


class TestCameraRotation:
    def test_smoke(self, device, dtype):
        n = torch.zeros(1, 3, 4, 6, device=device, dtype=dtype)
        n[:, 2] = 1
        module = CameraRotation(12.0, principal_point=(2.0, 1.0))
        out = module(n)
        assert out.shape == (1, 3, 4, 6) and out.dtype == dtype and out.device.type == device.type
        # the optical axis turns towards the camera centre: (-u, -v, f) / |.|
        uv = pixel_grid(4, 6, (2.0, 1.0), device=device, dtype=dtype)
        target = torch.stack([-uv[0], -uv[1], torch.full_like(uv[0], 12.0)])
        torch.testing.assert_close(out[0], target / target.norm(dim=0))
        assert list(module.buffers()) == [] and "focal=12.0" in repr(module)

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        n = random_normals(batch, 5, 7).to(device)
        out = CameraRotation(20.0)(n)
        assert out.shape == (batch, 3, 5, 7)
        torch.testing.assert_close(out.norm(dim=1), torch.ones(batch, 5, 7, dtype=n.dtype, device=device))
        torch.testing.assert_close(CameraRotation(20.0)(n[0]), out[0])  # unbatched (3, H, W)

    def test_exception(self):
        with pytest.raises(ValueError, match="focal"):
            CameraRotation(0.0)
        with pytest.raises(ValueError, match="focal"):
            CameraRotation(None)
        with pytest.raises(ValueError, match="normals"):
            CameraRotation(10.0)(torch.zeros(1, 2, 4, 4))
        with pytest.raises(ValueError, match="normals"):
            rotate_normals_to_camera(torch.zeros(4, 4), 10.0)

    def test_gradcheck(self):
        n = random_normals(1, 3, 4).requires_grad_()
        assert torch.autograd.gradcheck(CameraRotation(8.0, (1.0, 2.0)), (n,), fast_mode=True)

    def test_module(self, device, dtype):
        n = random_normals(2, 6, 5, dtype).to(device)
        torch.testing.assert_close(CameraRotation(30.0, (2.0, 4.0))(n), rotate_normals_to_camera(n, 30.0, (2.0, 4.0)))

    def test_dynamo(self):
        n = random_normals(2, 6, 5)
        compiled = torch.compile(CameraRotation(30.0), backend="eager")
        torch.testing.assert_close(compiled(n), rotate_normals_to_camera(n, 30.0))
