import math
from dataclasses import FrozenInstanceError

import numpy as np
import pytest
import torch

from sfs_torch.lighting import natural_lightings, render_sphere, sphere_normals
from sfs_torch.metrics import NormalMetrics, angular_error, lmse, normal_metrics


def _unit(x):
    return x / x.norm(dim=-3, keepdim=True)


def _random_normals(shape, seed, dtype=torch.float64, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    n = _unit(torch.randn(shape, generator=gen, dtype=torch.float64))
    n = torch.cat([n[..., :2, :, :], n[..., 2:, :, :].abs()], dim=-3)
    return n.to(device, dtype)


def _tilted(gt, degrees, seed=0):
    """Each normal of ``gt`` (float64) turned by exactly ``degrees`` in a random direction."""
    gen = torch.Generator().manual_seed(seed)
    r = torch.randn(gt.shape, generator=gen, dtype=torch.float64)
    t = _unit(r - (r * gt).sum(-3, keepdim=True) * gt)
    a = torch.deg2rad(torch.as_tensor(degrees, dtype=torch.float64))
    return torch.cos(a) * gt + torch.sin(a) * t


def _tol(dtype):
    return 2e-3 if dtype == torch.float32 else 1e-9


class TestAngularError:
    def test_constant_tilt(self, device, dtype):
        gt = _random_normals((2, 3, 6, 7), seed=1)
        est = _tilted(gt, 10.0)
        mask = torch.ones(2, 1, 6, 7, dtype=torch.bool)
        err = angular_error(est.to(device, dtype), gt.to(device, dtype), mask.to(device))
        assert err.shape == (2, 1, 6, 7) and err.dtype == dtype and err.device.type == device.type
        torch.testing.assert_close(err, torch.full_like(err, 10.0), atol=_tol(dtype), rtol=0)

    def test_vs_numpy_arccos(self):
        gt = _random_normals((1, 3, 8, 8), seed=2)
        est = _random_normals((1, 3, 8, 8), seed=3)
        ref = np.degrees(np.arccos(np.clip((est * gt).sum(1).numpy(), -1, 1)))
        err = angular_error(est, gt, torch.ones(1, 1, 8, 8, dtype=torch.bool))
        np.testing.assert_allclose(err[:, 0].numpy(), ref, atol=1e-6)

    def test_exact_at_zero_and_180(self, dtype):
        gt = _random_normals((3, 5, 5), seed=4, dtype=dtype)
        mask = torch.ones(5, 5, dtype=torch.bool)
        assert bool((angular_error(gt, gt, mask) == 0).all())
        torch.testing.assert_close(angular_error(-gt, gt, mask), torch.full((1, 5, 5), 180.0, dtype=dtype))

    def test_small_angle_float32(self):
        # acos of a float32 dot product cannot resolve 0.01 deg (cos differs from 1 by 1.5e-8).
        gt64 = _random_normals((3, 4, 4), seed=5)
        gt, est = gt64.float(), _tilted(gt64, 0.01).float()
        a, b = _unit(est.double()), _unit(gt.double())
        ref = torch.rad2deg(2 * torch.asin((a - b).norm(dim=0) / 2))
        err = angular_error(est, gt, torch.ones(4, 4, dtype=torch.bool))[0]
        torch.testing.assert_close(err.double(), ref, rtol=1e-3, atol=0)

    def test_mask_and_scale(self):
        gt = _random_normals((3, 4, 4), seed=6)
        est = _tilted(gt, 25.0)
        mask = torch.zeros(1, 4, 4, dtype=torch.bool)
        mask[:, 1:3, :] = True
        err = angular_error(3.0 * est, gt, mask)
        assert bool((err[~mask] == 0).all())
        torch.testing.assert_close(err[mask], torch.full((8,), 25.0, dtype=torch.float64))

    def test_cardinality(self):
        gt = _random_normals((2, 3, 4, 5), seed=7)
        est = _random_normals((2, 3, 4, 5), seed=8)
        mask = torch.rand(4, 5, generator=torch.Generator().manual_seed(0)) > 0.3
        batched = angular_error(est, gt, mask[None])
        assert batched.shape == (2, 1, 4, 5)
        for b in range(2):
            single = angular_error(est[b], gt[b], mask)
            assert single.shape == (1, 4, 5)
            torch.testing.assert_close(single, batched[b])

    def test_exception(self):
        n = _random_normals((1, 3, 4, 4), seed=9)
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        with pytest.raises(ValueError, match="est"):
            angular_error(n[:, :2], n[:, :2], mask)
        with pytest.raises(ValueError, match="gt"):
            angular_error(n, n[..., :3], mask)
        with pytest.raises(ValueError, match="mask"):
            angular_error(n, n, mask[..., :3])
        with pytest.raises(ValueError, match="mask is empty"):
            angular_error(n, n, torch.zeros_like(mask))
        with pytest.raises(ValueError, match="mask"):
            angular_error(n, n, 2 * mask.int())
        bad = n.clone()
        bad[0, 0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="est contains 1 NaN"):
            angular_error(bad, n, mask)
        zero = n.clone()
        zero[0, :, 1, 1] = 0
        with pytest.raises(ValueError, match="gt has 1 zero-length"):
            angular_error(n, zero, mask)
        part = mask.clone()
        part[0, 0, 1, 1] = False
        angular_error(zero, n, part)  # zero outside the mask is the SPEC background


class TestNormalMetrics:
    def test_constant_tilt(self, device, dtype):
        gt = _random_normals((3, 8, 8), seed=10)
        est = _tilted(gt, 10.0)
        mask = torch.ones(8, 8, dtype=torch.bool, device=device)
        res = normal_metrics(est.to(device, dtype), gt.to(device, dtype), mask)
        assert res.median.shape == () and res.median.dtype == dtype
        tol = _tol(dtype)
        assert res.median.item() == pytest.approx(10.0, abs=tol)
        assert res.mean.item() == pytest.approx(10.0, abs=tol)
        assert (res.under_11_25.item(), res.under_22_5.item(), res.under_30.item()) == (1.0, 1.0, 1.0)
        assert res.nmse.item() == pytest.approx(2 - 2 * math.cos(math.radians(10)), rel=10 * tol)

    def test_two_levels(self):
        gt = _random_normals((1, 3, 4, 6), seed=11)
        degrees = torch.tensor([20.0, 40.0], dtype=torch.float64).repeat_interleave(12).view(1, 1, 4, 6)
        res = normal_metrics(_tilted(gt, degrees), gt, torch.ones(1, 1, 4, 6, dtype=torch.bool))
        out = res.as_dict()
        assert out["median"] == pytest.approx(30.0) and out["mean"] == pytest.approx(30.0)
        assert (out["under_11_25"], out["under_22_5"], out["under_30"]) == (0.0, 0.5, 0.5)
        expected = 2 - math.cos(math.radians(20)) - math.cos(math.radians(40))
        assert out["nmse"] == pytest.approx(expected, rel=1e-9)

    @pytest.mark.parametrize("count_odd", [True, False])
    def test_vs_numpy(self, count_odd):
        gt = _random_normals((1, 3, 9, 9), seed=12)
        gen = torch.Generator().manual_seed(13)
        degrees = 45 * torch.rand(1, 1, 9, 9, generator=gen, dtype=torch.float64)
        mask = torch.rand(1, 1, 9, 9, generator=gen) > 0.4
        mask[0, 0, 0, 0] = True
        if (int(mask.sum()) % 2 == 1) != count_odd:
            mask[0, 0, 0, 0] = False
        degrees[~mask] = 170.0  # background errors must not count
        res = normal_metrics(_tilted(gt, degrees, seed=14), gt, mask)
        inside = degrees[mask].numpy()
        assert res.median.item() == pytest.approx(np.median(inside), abs=1e-9)
        assert res.mean.item() == pytest.approx(inside.mean(), abs=1e-9)
        assert res.under_22_5.item() == pytest.approx((inside < 22.5).mean())
        assert res.nmse.item() == pytest.approx((2 - 2 * np.cos(np.radians(inside))).mean(), rel=1e-9)

    def test_non_unit_input(self):
        gt = _random_normals((3, 5, 5), seed=15)
        est = _tilted(gt, 30.0)
        mask = torch.ones(5, 5, dtype=torch.bool)
        a, b = normal_metrics(est, gt, mask), normal_metrics(0.5 * est, 4 * gt, mask)
        assert a.nmse.item() == pytest.approx(b.nmse.item(), rel=1e-12)
        assert a.nmse.item() == pytest.approx(2 - 2 * math.cos(math.radians(30)), rel=1e-9)

    def test_batch_vs_single(self):
        gt = _random_normals((2, 3, 6, 6), seed=16)
        est = torch.stack([_tilted(gt[0], 5.0), _tilted(gt[1], 25.0)])
        mask = torch.ones(2, 1, 6, 6, dtype=torch.bool)
        mask[1, :, :3] = False
        batched = normal_metrics(est, gt, mask)
        assert batched.median.shape == (2,)
        out = batched.as_dict()
        assert out["median"] == pytest.approx([5.0, 25.0]) and out["under_22_5"] == [1.0, 0.0]
        for b in range(2):
            single = normal_metrics(est[b], gt[b], mask[b])
            for name, value in single.as_dict().items():
                assert value == pytest.approx(out[name][b], abs=1e-12)
        one = normal_metrics(est[:1], gt[:1], mask[:1])
        assert one.median.shape == (1,) and isinstance(one.as_dict()["median"], float)

    @pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
    def test_half_precision_large_object(self, dtype):
        # 25600 pixels at 10 degrees sum to 256000, past float16's 65504: the mean was inf
        gt = _random_normals((3, 160, 160), seed=19)
        est = _tilted(gt, 10.0)
        res = normal_metrics(est.to(dtype), gt.to(dtype), torch.ones(160, 160, dtype=torch.bool))
        assert res.mean.dtype == dtype
        assert res.mean.item() == pytest.approx(10.0, abs=0.1)
        assert res.under_11_25.item() == 1.0
        assert res.nmse.item() == pytest.approx(2 - 2 * math.cos(math.radians(10)), rel=0.05)

    def test_frozen(self):
        n = _random_normals((3, 2, 2), seed=17)
        res = normal_metrics(n, n, torch.ones(2, 2, dtype=torch.bool))
        assert isinstance(res, NormalMetrics)
        with pytest.raises(FrozenInstanceError):
            res.median = torch.tensor(1.0)

    def test_exception(self):
        n = _random_normals((2, 3, 4, 4), seed=18)
        with pytest.raises(ValueError, match="mask"):
            normal_metrics(n, n, torch.ones(3, 1, 4, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="est"):
            normal_metrics(n[..., None], n, torch.ones(4, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask is empty"):
            normal_metrics(n, n, torch.zeros(2, 1, 4, 4, dtype=torch.bool))


def _reference_lmse(est_sh, gt_sh, resolution):
    """NumPy lMSE: SPEC basis written out, scale by least squares."""
    sphere = sphere_normals(resolution)
    x, y, z = (c[sphere.mask[0, 0]].double().numpy() for c in sphere.normals[0])
    basis = np.stack([
        0.282095 * np.ones_like(x), 0.488603 * y, 0.488603 * z, 0.488603 * x,
        1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z,
        0.546274 * (x * x - y * y),
    ])
    est = (est_sh.double().numpy() @ basis).ravel()
    gt = (gt_sh.double().numpy() @ basis).ravel()
    scale = np.linalg.lstsq(est[:, None], gt, rcond=None)[0][0]
    return np.mean((scale * est - gt) ** 2)


class TestLMSE:
    @pytest.fixture
    def probes(self):
        return natural_lightings()

    def test_scaled_copy(self, probes, device, dtype):
        sh = probes["grace_cathedral"].to(device, dtype)
        assert lmse(sh, sh).item() == pytest.approx(0.0, abs=1e-12)
        assert lmse(2.5 * sh, sh).item() == pytest.approx(0.0, abs=1e-10)
        assert lmse(0.1 * sh, sh).item() == pytest.approx(0.0, abs=1e-10)

    def test_vs_reference(self, probes):
        names = sorted(probes)
        for a, b in zip(names, names[1:]):
            est, gt = probes[a].double(), probes[b].double()
            value = lmse(est, gt).item()
            assert value > 1e-6
            assert value == pytest.approx(_reference_lmse(est, gt, 64), rel=1e-5)
            # only the direction of the estimate matters
            assert lmse(7.0 * est, gt).item() == pytest.approx(value, rel=1e-9)

    def test_resolution_and_black_estimate(self, probes):
        gt = probes["grace_cathedral"].double()
        est = gt.clone()
        est[0, 1] += 0.3
        assert lmse(est, gt, resolution=32).item() == pytest.approx(_reference_lmse(est, gt, 32), rel=1e-5)
        sphere = sphere_normals(64)
        mean_square = (render_sphere(gt) ** 2).sum() / (3 * sphere.mask.sum())
        assert lmse(torch.zeros_like(gt), gt).item() == pytest.approx(mean_square.item(), rel=1e-9)

    def test_cardinality(self, probes):
        est = torch.stack([probes["grace_cathedral"], probes["uffizi_gallery"]])
        gt = torch.stack([probes["uffizi_gallery"], probes["uffizi_gallery"]])
        batched = lmse(est, gt)
        assert batched.shape == (2,) and batched[1].item() == pytest.approx(0.0, abs=1e-10)
        single = lmse(est[0], gt[0])
        assert single.shape == ()
        torch.testing.assert_close(single, batched[0])

    def test_exception(self):
        sh = torch.zeros(2, 3, 9)
        with pytest.raises(ValueError, match="est_sh"):
            lmse(sh[..., :8], sh)
        with pytest.raises(ValueError, match="gt_sh"):
            lmse(sh, sh[:, :2])
        with pytest.raises(ValueError, match="batch size"):
            lmse(sh, sh[:1])
        bad = sh.clone()
        bad[1, 2, 3] = float("inf")
        with pytest.raises(ValueError, match="gt_sh contains 1 NaN or infinite"):
            lmse(sh, bad)
        with pytest.raises(ValueError, match="resolution"):
            lmse(sh, sh, resolution=1)
