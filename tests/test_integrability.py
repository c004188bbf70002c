import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scenes import sphere

from sfs_torch.camera import pixel_grid
from sfs_torch.integrability import (
    DepthToNormals,
    IntegrabilityConfig,
    Integrator,
    Surface,
    _CoarseInverse,
    _Level,
    _Multigrid,
    bas_relief_normals,
    check_integrability_config,
    depth_to_mesh,
    depth_to_normals,
    integrate_convex,
    integrate_normals,
    mask_components,
    median_slope,
)

F64 = torch.float64


def _ortho_normals(p, q):
    n = torch.stack([-p, -q, torch.ones_like(p)])
    return n / n.norm(dim=0)


def _grid(size, dtype=F64, device="cpu"):
    return pixel_grid(size, size, device=device, dtype=dtype)


def sphere_cap(size=64, dtype=F64, device="cpu"):
    u, v = _grid(size, dtype, device)
    r = 0.45 * size
    mask = u * u + v * v < (0.85 * r) ** 2
    z = torch.sqrt((r * r - u * u - v * v).clamp_min(0))
    n = torch.stack([u, v, z]) / r
    return z, torch.where(mask, n, 0.0), mask


def gaussian_bump(size=64, dtype=F64, device="cpu"):
    u, v = _grid(size, dtype, device)
    z = 12.0 * torch.exp(-(u * u + v * v) / 200.0)
    mask = (u.abs() < 0.44 * size) & (v.abs() < 0.41 * size)
    n = _ortho_normals(-u / 100.0 * z, -v / 100.0 * z)
    return z, torch.where(mask, n, 0.0), mask


def crease(size=64, dtype=F64, device="cpu"):
    # a roof ridge along u = 0 (between two pixel columns), tilted along v
    u, v = _grid(size, dtype, device)
    z = 20.0 - 0.6 * u.abs() + 0.2 * v
    mask = (u.abs() < 0.44 * size) & (v.abs() < 0.41 * size)
    n = _ortho_normals(-0.6 * torch.sign(u), torch.full_like(u, 0.2))
    return z, torch.where(mask, n, 0.0), mask


def perspective_sphere(size=64, focal=80.0, dtype=F64):
    """Depth and normals of a sphere in front of a pinhole camera, rendered by ray casting."""
    u, v = _grid(size, dtype)
    ray = torch.stack([u / focal, v / focal, -torch.ones_like(u)])  # depth-1 points
    c = torch.tensor([3.0, -2.0, -60.0], dtype=dtype)
    rc, r2 = (ray * c[:, None, None]).sum(0), (ray * ray).sum(0)
    disc = rc * rc - r2 * (c @ c - 20.0**2)
    depth = (rc - disc.clamp_min(0).sqrt()) / r2
    point = depth * ray
    n = (point - c[:, None, None]) / 20.0
    mask = (disc > 0) & ((n * -point).sum(0) / point.norm(dim=0) > 0.3)
    return torch.where(mask, depth, 0.0), torch.where(mask, n, 0.0), mask


def _batch(z, n, mask):
    return z[None, None], n[None], mask[None, None]


def depth_rmse(depth, z, mask):
    """RMSE after removing the best offset on every connected component."""
    labels = mask_components(mask)[0, 0]
    err = (depth[0, 0] - z)[mask[0, 0]]
    lab = labels[mask[0, 0]]
    for k in lab.unique():
        err[lab == k] -= err[lab == k].mean()
    return float(err.pow(2).mean().sqrt())


def angular_error(a, b, mask):
    cos = (a * b).sum(1).clamp(-1, 1)[mask[:, 0]]
    return torch.rad2deg(torch.acos(cos))


class TestIntegrateL2:
    @pytest.mark.parametrize("surface, tol", [(sphere_cap, 0.02), (gaussian_bump, 0.01), (crease, 1e-5)])
    def test_exact_recovery(self, surface, tol):
        z, n, mask = _batch(*surface())
        out = integrate_normals(n, mask, tol=1e-10)
        assert isinstance(out, Surface)
        assert depth_rmse(out.depth, z[0, 0], mask) < tol
        # zero mean on the mask, zero outside
        assert abs(float(out.depth[mask].mean())) < 1e-9
        assert float(out.depth[~mask].abs().max()) == 0.0
        assert float(out.normals.abs().sum(1)[~mask[:, 0]].max()) == 0.0

    def test_smoke(self, device, dtype):
        z, n, mask = _batch(*gaussian_bump(48, dtype, device))
        out = integrate_normals(n, mask)
        assert out.depth.shape == (1, 1, 48, 48) and out.normals.shape == (1, 3, 48, 48)
        assert out.depth.device.type == device.type and out.depth.dtype == dtype
        assert depth_rmse(out.depth.double().cpu(), z[0, 0].double().cpu(), mask.cpu()) < 0.02

    def test_cardinality(self):
        z, n, mask = gaussian_bump(32)
        single = integrate_normals(n, mask[None])
        assert single.depth.shape == (1, 32, 32) and single.normals.shape == (3, 32, 32)
        mirrored = n.flip(-1) * torch.tensor([-1.0, 1.0, 1.0], dtype=F64)[:, None, None]  # u -> -u
        batch = integrate_normals(torch.stack([n, mirrored]), torch.stack([mask, mask.flip(-1)])[:, None])
        assert batch.depth.shape == (2, 1, 32, 32)
        torch.testing.assert_close(batch.depth[0], single.depth, atol=1e-6, rtol=0)
        torch.testing.assert_close(batch.depth[1], single.depth.flip(-1), atol=1e-6, rtol=0)

    def test_integrable_input_is_kept(self):
        # a quadratic surface is reproduced exactly by the solver's edge rule and by
        # depth_to_normals, so its refined normals must equal the input
        u, v = _grid(64)
        mask = u * u + v * v < 25.0**2
        p, q = -0.02 * u + 0.02 * v, -0.02 * v + 0.02 * u
        z = -0.01 * (u * u + v * v) + 0.02 * u * v
        n = torch.where(mask, _ortho_normals(p, q), 0.0)[None]
        out = integrate_normals(n, mask[None, None], tol=1e-12)
        torch.testing.assert_close(out.normals, n, atol=1e-9, rtol=0)
        assert depth_rmse(out.depth, z, mask[None, None]) < 1e-9

    def test_holes_and_components(self):
        z, n, _ = gaussian_bump(64)
        u, v = _grid(64)
        ring = ((u + 12) ** 2 + v * v < 14**2) & ((u + 12) ** 2 + v * v > 5**2)  # a disk with a hole
        blob = (u - 16).abs().lt(8) & (v - 10).abs().lt(12)
        dot = (u - 20).abs().lt(1) & (v + 20).abs().lt(1)  # a 2x2 island
        mask = (ring | blob | dot)[None, None]
        n = torch.where(mask[0], n, 0.0)[None]
        labels = mask_components(mask)
        assert labels[mask].unique().numel() == 3
        out = integrate_normals(n, mask, tol=1e-10)
        assert depth_rmse(out.depth, z, mask) < 0.01
        for k in labels[mask].unique():
            assert abs(float(out.depth[labels == k].mean())) < 1e-9

    def test_weights(self):
        # low confidence on corrupted pixels keeps them from bending their neighbours
        z, n, mask = _batch(*gaussian_bump(48))
        g = torch.Generator().manual_seed(1)
        bad = (torch.rand(1, 1, 48, 48, generator=g, dtype=F64) < 0.05) & mask
        corrupted = torch.where(bad, torch.tensor([0.6, 0.0, 0.8], dtype=F64)[:, None, None], n)
        weights = torch.where(bad, 1e-4, 1.0).to(F64)
        good = mask & ~bad
        plain = integrate_normals(corrupted, mask).depth
        weighted = integrate_normals(corrupted, mask, weights=weights, tol=1e-10).depth
        assert depth_rmse(weighted, z[0, 0], good) < 0.02 < depth_rmse(plain, z[0, 0], good)

    def test_exception(self):
        z, n, mask = _batch(*gaussian_bump(16))
        with pytest.raises(ValueError, match="method"):
            integrate_normals(n, mask, method="l3")
        with pytest.raises(ValueError, match="normals"):
            integrate_normals(n[:, :2], mask)
        with pytest.raises(ValueError, match="normals"):
            integrate_normals(torch.full_like(n, float("nan")), mask)
        with pytest.raises(ValueError, match="mask"):
            integrate_normals(n, mask[..., :8])
        with pytest.raises(ValueError, match="mask"):
            integrate_normals(n, torch.zeros_like(mask))
        with pytest.raises(ValueError, match="weights"):
            integrate_normals(n, mask, weights=-torch.ones_like(z))
        with pytest.raises(ValueError, match="focal"):
            integrate_normals(n, mask, focal=0.0)
        with pytest.raises(ValueError, match="unknown options"):
            integrate_normals(n, mask, conv_iter=3)

    def test_tol_below_the_dtype_precision(self):
        # float32 cannot reach a residual of 1e-9: CG used to iterate on rounding noise and
        # return a depth off by thousands; the tolerance is floored at float32's epsilon
        n, m = sphere()
        default = integrate_normals(n[None], m[None]).depth
        tight = integrate_normals(n[None], m[None], tol=1e-9).depth
        assert float((tight - default).abs().max()) < 1e-3

    @pytest.mark.parametrize("dtype, bound", [(torch.float16, 0.02), (torch.bfloat16, 0.1)])
    def test_half_precision(self, dtype, bound):
        # half-precision normals are integrated in float32 (the depth was off by 5.3)
        n, m = sphere()
        expected = integrate_normals(n[None], m[None]).depth
        out = integrate_normals(n[None].to(dtype), m[None])
        assert out.depth.dtype == out.normals.dtype == dtype
        assert float((out.depth.float() - expected).abs().max()) < bound  # depth spans 0..26 pixels
        conv = integrate_convex(n[None, None].to(dtype), m[None], conv_iter=2)
        assert conv.depth.dtype == dtype and float((conv.depth.float() - expected).abs().max()) < bound

    def test_weights_take_the_normals_dtype(self):
        n, m = sphere()
        normals = n[None].double()
        out = integrate_normals(normals, m[None], weights=torch.ones(1, 1, *m.shape[-2:]))  # float32 weights
        assert out.depth.dtype == torch.float64
        assert torch.equal(out.depth, integrate_normals(normals, m[None]).depth)

    @pytest.mark.parametrize("camera, message", [
        ({"focal": float("inf")}, r"^focal must be a positive focal length in pixels, got inf$"),
        ({"focal": "50"}, r"^focal must be a positive focal length in pixels, got '50'$"),
        ({"focal": 50.0, "principal_point": (float("nan"), 3.0)}, r"^principal_point must be two finite numbers"),
        ({"focal": 50.0, "principal_point": (3.0,)}, r"^principal_point must be two finite numbers"),
    ])
    def test_camera_is_checked(self, camera, message):
        n, m = sphere()
        depth = torch.ones(1, 1, *m.shape[-2:])
        for call in (lambda: integrate_normals(n[None], m[None], **camera),
                     lambda: integrate_convex(n[None, None], m[None], **camera),
                     lambda: depth_to_normals(depth, m[None], **camera),
                     lambda: depth_to_mesh(depth[0], m, **camera),
                     lambda: DepthToNormals(**camera),
                     lambda: Integrator(**camera)):
            with pytest.raises(ValueError, match=message):
                call()

    @pytest.mark.parametrize("focal", [None, 10.0])
    def test_gradcheck(self, focal):
        g = torch.Generator().manual_seed(0)
        n = torch.randn(1, 3, 6, 6, generator=g, dtype=F64)
        n[:, 2] = n[:, 2].abs() + 1.0
        n = (n / n.norm(dim=1, keepdim=True)).requires_grad_()
        w = (torch.rand(1, 1, 6, 6, generator=g, dtype=F64) + 0.5).requires_grad_()
        mask = torch.ones(1, 1, 6, 6, dtype=torch.bool)
        mask[0, 0, 0, :2] = False
        mask[0, 0, 3, :] = False  # two components

        def f(n, w):
            out = integrate_normals(n, mask, weights=w, focal=focal, tol=1e-12)
            return out.depth, out.normals

        assert torch.autograd.gradcheck(f, (n, w), eps=1e-6, atol=1e-6, fast_mode=True)

    def test_module(self):
        z, n, mask = _batch(*gaussian_bump(32))
        cfg = IntegrabilityConfig(method="l1", l1_iter=3)
        module = Integrator(**{k: v for k, v in vars(cfg).items() if k != "_target_"})
        torch.testing.assert_close(module(n, mask).depth, integrate_normals(n, mask, method="l1", l1_iter=3).depth)
        with pytest.raises(ValueError, match="method"):
            Integrator(method="nope")

    def test_instantiate_from_config(self):
        # the config's _target_ builds the module with Hydra, as a user's own config would
        from hydra.utils import instantiate

        z, n, mask = _batch(*gaussian_bump(32))
        module = instantiate(IntegrabilityConfig(method="l1", l1_iter=3))
        assert isinstance(module, Integrator) and module.l1_iter == 3
        torch.testing.assert_close(module(n, mask).depth, integrate_normals(n, mask, method="l1", l1_iter=3).depth)

    def test_instantiate_the_default_config(self):
        # the stage config's defaults build a working solver: L2 with the default options
        from hydra.utils import instantiate

        z, n, mask = _batch(*sphere_cap())
        module = instantiate(IntegrabilityConfig())
        assert isinstance(module, Integrator) and module.method == "l2"
        assert {k: getattr(module, k) for k in vars(IntegrabilityConfig()) if k != "_target_"} == {
            k: v for k, v in vars(IntegrabilityConfig()).items() if k != "_target_"}
        out = module(n, mask)
        assert torch.equal(out.depth, integrate_normals(n, mask).depth)
        # the sphere comes back (test_exact_recovery's tolerance, at the default solver tolerance)
        assert depth_rmse(out.depth, z[0, 0], mask) < 0.02
        assert abs(float(out.depth[mask].mean())) < 1e-9 and float(out.depth[~mask].abs().max()) == 0.0
        assert float(angular_error(out.normals, n, mask).max()) < 0.5  # degrees; 0.22 here

    @pytest.mark.parametrize("method", ["none", None, "L2"])
    def test_only_solvers(self, method):
        # "none" is the pipeline's integrate=none: it builds no Integrator
        with pytest.raises(ValueError, match=r"^method must be one of \('l2', 'l1', 'conv'\)"):
            Integrator(method=method)


class TestCheckIntegrabilityConfig:
    @pytest.mark.parametrize("options, message", [
        ({"method": "none"}, r"method must be one of \('l2', 'l1', 'conv'\), got 'none'"),
        ({"max_iter": 0}, r"max_iter must be an integer >= 1, got 0"),
        ({"l1_iter": -1}, r"l1_iter must be an integer >= 0, got -1"),
        ({"tol": 0.0}, r"tol must be > 0, got 0.0"),
        ({"l1_delta": -0.1}, r"l1_delta must be > 0, got -0.1"),
        ({"min_nz": 1.0}, r"min_nz must be in \(0, 1\), got 1.0"),
        ({"conv_prior": -1.0}, r"conv_prior must be >= 0, got -1.0"),
    ])
    @pytest.mark.parametrize("prefix", ["", "integrate."])
    def test_exception_names_the_key(self, options, message, prefix):
        with pytest.raises(ValueError, match=f"^{re.escape(prefix)}{message}$"):
            check_integrability_config(IntegrabilityConfig(**options), prefix=prefix)

    @pytest.mark.parametrize("options, message", [
        ({"tol": math.inf}, r"tol must be > 0, got inf"),  # gave an all-zero depth
        ({"l1_delta": math.inf}, r"l1_delta must be > 0, got inf"),
        ({"tol": "1e-6"}, r"tol must be > 0, got '1e-6'"),  # these four raised a TypeError from a comparison
        ({"l1_delta": "0.1"}, r"l1_delta must be > 0, got '0.1'"),
        ({"min_nz": "0.5"}, r"min_nz must be in \(0, 1\), got '0.5'"),
        ({"conv_prior": "0.1"}, r"conv_prior must be >= 0, got '0.1'"),
        ({"tol": math.nan}, r"tol must be > 0, got nan"),
    ])
    def test_options_must_be_finite_numbers(self, options, message):
        with pytest.raises(ValueError, match=f"^integrate.{message}$"):
            check_integrability_config(IntegrabilityConfig(**options), prefix="integrate.")

    def test_valid(self):
        for method in ("l2", "l1", "conv"):
            check_integrability_config(IntegrabilityConfig(method=method, l1_iter=0, conv_iter=0, conv_prior=0.0))

    @pytest.mark.parametrize("function, options, message", [
        (integrate_normals, {"tol": 0.0}, r"^tol must be > 0, got 0.0$"),
        (integrate_normals, {"max_iter": 0}, r"^max_iter must be an integer >= 1, got 0$"),
        (integrate_normals, {"min_nz": 0.0}, r"^min_nz must be in \(0, 1\), got 0.0$"),
        (integrate_normals, {"method": "l1", "l1_delta": 0.0}, r"^l1_delta must be > 0, got 0.0$"),
        (integrate_convex, {"tol": 0.0}, r"^tol must be > 0, got 0.0$"),
        (integrate_convex, {"max_iter": 0}, r"^max_iter must be an integer >= 1, got 0$"),
        (integrate_convex, {"conv_prior": -1.0}, r"^conv_prior must be >= 0, got -1.0$"),
    ])
    def test_the_functions_check_their_options(self, function, options, message):
        # max_iter=0 returned an all-zero depth, min_nz=0 or l1_delta=0 a FloatingPointError
        z, n, mask = _batch(*gaussian_bump(16))
        with pytest.raises(ValueError, match=message):
            function(n[:, None] if function is integrate_convex else n, mask, **options)

    def test_the_module_checks_its_arguments(self):
        with pytest.raises(ValueError, match=r"^tol must be > 0, got 0.0$"):
            Integrator(tol=0.0)
        with pytest.raises(ValueError, match=r"^min_nz must be in \(0, 1\), got 0.0$"):
            Integrator(method="l1", min_nz=0.0)


class TestMultigrid:
    def test_coarse_pseudo_inverse_of_a_degenerate_level_is_finite(self):
        # the coarsest level of a real benchmark image (thin shape, 52 of 64 rows empty),
        # on which float32 eigh returned NaN and the whole solve went NaN
        data = np.load(Path(__file__).parent / "data" / "coarse_level_eigh_nan.npz")
        level = _Level(torch.from_numpy(data["wx"]), torch.from_numpy(data["wy"]))
        a = level.dense()
        inv = _Multigrid(level).coarse_inv
        assert inv.dtype == torch.float32 and bool(torch.isfinite(inv).all())
        torch.testing.assert_close(a @ inv @ a, a, atol=1e-2, rtol=1e-3)

    @staticmethod
    def _outliers(size=48, fraction=0.05):
        z, n, mask = _batch(*gaussian_bump(size))
        g = torch.Generator().manual_seed(1)
        bad = (torch.rand(size, size, generator=g, dtype=F64) < fraction) & mask[0, 0]
        rnd = torch.randn(3, size, size, generator=g, dtype=F64)
        rnd[2] = rnd[2].abs() + 0.2
        return z, torch.where(bad, rnd / rnd.norm(dim=0), n[0])[None], mask

    def test_l1_computes_the_coarse_inverse_once(self, monkeypatch):
        _, noisy, mask = self._outliers()
        calls = []
        pinv = torch.linalg.pinv
        monkeypatch.setattr(torch.linalg, "pinv", lambda a, **kw: calls.append(a.shape) or pinv(a, **kw))
        integrate_normals(noisy, mask, method="l1", l1_iter=6)
        assert len(calls) == 1

    def test_l1_equals_per_round_inverse(self, monkeypatch):
        # the solver before the coarse inverse was shared: every IRLS round recomputed it
        z, noisy, mask = self._outliers()
        shared = integrate_normals(noisy, mask, method="l1", tol=1e-12, max_iter=2000)
        init = _Multigrid.__init__
        monkeypatch.setattr(_Multigrid, "__init__", lambda self, level, coarse=None, **kw: init(self, level, **kw))
        per_round = integrate_normals(noisy, mask, method="l1", tol=1e-12, max_iter=2000)
        torch.testing.assert_close(shared.depth, per_round.depth, atol=1e-8, rtol=0)
        # and the robust solve still does its job
        l2 = integrate_normals(noisy, mask).depth
        assert depth_rmse(shared.depth, z[0, 0], mask) < 0.3 * depth_rmse(l2, z[0, 0], mask)

    def test_rescaled_inverse_of_a_scaled_level_is_exact(self):
        # another reweighting of the same mask reuses the inverse, times the trace ratio:
        # exact when the new weights are the old ones times a constant
        _, _, mask = _batch(*sphere_cap(40))
        m = mask[:, 0]
        g = torch.Generator().manual_seed(0)
        wx = torch.rand(1, 40, 40, generator=g, dtype=F64) * F.pad(m[..., :, 1:] & m[..., :, :-1], (0, 1))
        wy = torch.rand(1, 40, 40, generator=g, dtype=F64) * F.pad(m[..., 1:, :] & m[..., :-1, :], (0, 0, 0, 1))
        coarse = _Multigrid(_Level(wx, wy)).coarse
        scaled = _Multigrid(_Level(0.25 * wx, 0.25 * wy), coarse=coarse)
        fresh = _Multigrid(_Level(0.25 * wx, 0.25 * wy))
        assert scaled.coarse is coarse
        torch.testing.assert_close(scaled.coarse_inv, fresh.coarse_inv, atol=1e-9, rtol=1e-9)

    def test_coarse_inverse_on_the_input_device(self, device, monkeypatch):
        _, n, mask = _batch(*gaussian_bump(32, device=device))
        seen = []
        pinv = torch.linalg.pinv
        monkeypatch.setattr(torch.linalg, "pinv", lambda a, **kw: seen.append((a.device, a.dtype)) or pinv(a, **kw))
        out = integrate_normals(n.float(), mask, method="l1", l1_iter=2)
        assert seen == [(n.device, F64)]
        assert out.depth.device == n.device and out.depth.dtype == torch.float32
        inv = _CoarseInverse(_Level(torch.ones(1, 4, 4, device=device), torch.ones(1, 4, 4, device=device))).inv
        assert inv.device == n.device and inv.dtype == torch.float32


class TestIntegrateL1:
    def test_outliers(self):
        z, n, mask = _batch(*gaussian_bump(64))
        g = torch.Generator().manual_seed(0)
        bad = (torch.rand(64, 64, generator=g, dtype=F64) < 0.05) & mask[0, 0]
        rnd = torch.randn(3, 64, 64, generator=g, dtype=F64)
        rnd[2] = rnd[2].abs() + 0.2
        noisy = torch.where(bad, rnd / rnd.norm(dim=0), n[0])[None]
        l2 = depth_rmse(integrate_normals(noisy, mask).depth, z[0, 0], mask)
        l1 = depth_rmse(integrate_normals(noisy, mask, method="l1").depth, z[0, 0], mask)
        assert l1 < 0.3 * l2

    @pytest.mark.parametrize("l1_iter", [0, 1])
    def test_no_reweighting_is_l2(self, l1_iter):
        # the first IRLS round is the weighted L2 solve; l1_iter=0 used to crash
        z, n, mask = _batch(*gaussian_bump(32))
        assert torch.equal(Integrator(method="l1", l1_iter=l1_iter)(n, mask).depth, integrate_normals(n, mask).depth)

    def test_crease(self):
        z, n, mask = _batch(*crease(48))
        out = integrate_normals(n, mask, method="l1", tol=1e-10)
        assert depth_rmse(out.depth, z[0, 0], mask) < 1e-5


class TestPerspective:
    def test_sphere(self):
        depth, n, mask = _batch(*perspective_sphere())
        out = integrate_normals(n, mask, focal=80.0, tol=1e-10)
        d = out.depth[mask]
        truth = depth[mask] / torch.exp(torch.log(depth[mask]).mean())
        assert float(torch.exp(torch.log(d).mean())) == pytest.approx(1.0, abs=1e-9)
        assert float(((d - truth) / truth).abs().max()) < 2e-3
        # the orthographic model cannot explain these normals as well
        ortho = integrate_normals(n, mask, tol=1e-10)
        assert float(angular_error(out.normals, n, mask).median()) < 0.5 * float(angular_error(ortho.normals, n, mask).median())

    def test_plane_exact(self):
        # a tilted plane: log-depth is not quadratic, so differences are exact to O(h^2) only
        focal = 50.0
        u, v = _grid(32)
        normal = torch.tensor([0.3, -0.2, 0.9], dtype=F64)
        normal = normal / normal.norm()
        depth = 100.0 / (normal[2] - (u * normal[0] + v * normal[1]) / focal)
        mask = torch.ones(1, 1, 32, 32, dtype=torch.bool)
        n = normal[:, None, None].expand(3, 32, 32)[None]
        out = integrate_normals(n, mask, focal=focal, tol=1e-12)
        assert float(angular_error(out.normals, n, mask).max()) < 1e-3
        torch.testing.assert_close(depth_to_normals(depth[None, None], mask, focal), n, atol=1e-4, rtol=0)

    def test_depth_to_normals(self):
        depth, n, mask = _batch(*perspective_sphere())
        err = angular_error(depth_to_normals(depth, mask, focal=80.0), n, mask)
        assert float(err.median()) < 0.1 and float(err.max()) < 2.0
        with pytest.raises(ValueError, match="positive"):
            depth_to_normals(-depth, mask, focal=80.0)


class TestConvex:
    def test_better_than_mean(self):
        z, n, mask = _batch(*gaussian_bump(48))
        g = torch.Generator().manual_seed(0)
        cands = n[0] + 0.5 * torch.randn(3, 3, 48, 48, generator=g, dtype=F64)
        cands[:, 2] = cands[:, 2].abs()
        cands = cands / cands.norm(dim=1, keepdim=True)
        slot = torch.randint(0, 3, (48, 48), generator=g)
        cands = torch.where(slot == torch.arange(3)[:, None, None, None], n[0], cands)  # truth in one slot
        cands = torch.where(mask[0], cands, 0.0)[None]
        mean = cands.sum(1)
        mean = mean / mean.norm(dim=1, keepdim=True).clamp_min(1e-12)
        base = integrate_normals(mean, mask)
        conv = integrate_convex(cands, mask)
        assert depth_rmse(conv.depth, z[0, 0], mask) < 0.8 * depth_rmse(base.depth, z[0, 0], mask)
        assert float(angular_error(conv.normals, n, mask).median()) < 0.9 * float(angular_error(base.normals, n, mask).median())
        # same path through integrate_normals
        torch.testing.assert_close(integrate_normals(cands, mask, method="conv").depth, conv.depth)

    def test_single_candidate_is_l2(self):
        z, n, mask = _batch(*gaussian_bump(32))
        torch.testing.assert_close(integrate_convex(n[:, None], mask, conv_iter=3).depth, integrate_normals(n, mask).depth)

    def test_gradient(self):
        z, n, mask = _batch(*gaussian_bump(16))
        cands = torch.stack([n, n.flip(-1)], 1).requires_grad_()
        integrate_convex(cands, mask, conv_iter=3).depth.square().sum().backward()
        assert cands.grad is not None and bool(torch.isfinite(cands.grad).all()) and float(cands.grad.abs().sum()) > 0

    def test_exception(self):
        z, n, mask = _batch(*gaussian_bump(16))
        with pytest.raises(ValueError, match="candidates"):
            integrate_convex(n[:, :2, None], mask)


class TestDepthToNormals:
    def test_round_trip(self, device, dtype):
        z, n, mask = _batch(*sphere_cap(48, dtype, device))
        err = angular_error(depth_to_normals(z, mask), n, mask)
        assert float(err.median()) < 0.2
        assert depth_to_normals(z, mask).dtype == dtype

    @pytest.mark.parametrize("focal", [None, 9.0], ids=["orthographic", "perspective"])
    def test_each_pixel_follows_the_derivative_rule(self, focal):
        # a mask with runs of 1 to 5 pixels in both directions, so that every rule applies
        # somewhere: central, second- and first-order one-sided, none; checked against the
        # rule written out pixel by pixel
        mask = torch.zeros(12, 12, dtype=torch.bool)
        mask[1, 1], mask[3, 1:3], mask[5, 1:4], mask[7:12, 6], mask[1:6, 8:12] = True, True, True, True, True
        depth = 2.0 + torch.rand(12, 12, dtype=F64, generator=torch.Generator().manual_seed(0))
        s = torch.log(depth) if focal else depth

        def derivative(i, j, di, dj):
            def at(k):
                y, x = i + k * di, j + k * dj
                return bool(mask[y, x]) if 0 <= y < 12 and 0 <= x < 12 else False

            val = lambda k: float(s[i + k * di, j + k * dj])  # noqa: E731
            if at(1) and at(-1):
                return 0.5 * (val(1) - val(-1))
            if at(1) and at(2):
                return 0.5 * (-3 * val(0) + 4 * val(1) - val(2))
            if at(-1) and at(-2):
                return 0.5 * (3 * val(0) - 4 * val(-1) + val(-2))
            if at(1):
                return val(1) - val(0)
            return val(0) - val(-1) if at(-1) else 0.0

        u, v = pixel_grid(12, 12, dtype=F64)
        expected = torch.zeros(3, 12, 12, dtype=F64)
        for i, j in mask.nonzero().tolist():
            gu, gv = derivative(i, j, 0, 1), -derivative(i, j, 1, 0)
            n = torch.tensor([-gu, -gv, 1.0] if focal is None else
                             [focal * gu, focal * gv, 1.0 + float(u[i, j]) * gu + float(v[i, j]) * gv], dtype=F64)
            expected[:, i, j] = n / n.norm()
        got = depth_to_normals(torch.where(mask, depth, 0.0)[None, None], mask[None, None], focal)[0]
        torch.testing.assert_close(got, expected, atol=1e-12, rtol=0)

    def test_exception(self):
        with pytest.raises(ValueError, match="depth"):
            depth_to_normals(torch.zeros(1, 2, 4, 4), torch.ones(1, 1, 4, 4))


class TestBasReliefNormals:
    @pytest.mark.parametrize("scale, tilt_x, tilt_y", [(1.0, 0.0, 0.0), (1.3, 0.0, 0.0), (0.7, 0.4, -0.2)])
    def test_normals_of_the_transformed_surface(self, scale, tilt_x, tilt_y):
        # the bump's analytic gradients, transformed: z' = scale z + tilt_x u + tilt_y v
        u, v = _grid(64)
        z, n, mask = gaussian_bump(64)
        p, q = -u / 100.0 * z, -v / 100.0 * z
        expected = torch.where(mask, _ortho_normals(scale * p + tilt_x, scale * q + tilt_y), 0.0)
        torch.testing.assert_close(bas_relief_normals(n[None], scale, tilt_x, tilt_y)[0], expected)

    def test_background_stays_zero(self):
        _, n, mask = gaussian_bump(32)
        assert bool((bas_relief_normals(n[None], 1.5, 0.3, 0.3)[0][:, ~mask] == 0).all())

    def test_unbatched_input_gives_unbatched_output(self):
        _, n, _ = gaussian_bump(32)
        torch.testing.assert_close(bas_relief_normals(n, 1.2, 0.1), bas_relief_normals(n[None], 1.2, 0.1)[0])
        with pytest.raises(ValueError, match="normals"):
            bas_relief_normals(torch.zeros(1, 2, 4, 4), 1.2)

    def test_one_transform_per_image_from_tensors(self):
        _, n, _ = gaussian_bump(32)
        batch = torch.stack([n, n])
        scale, tilt = torch.tensor([1.2, 0.8], requires_grad=True), torch.tensor([0.1, -0.3])
        out = bas_relief_normals(batch, scale, tilt, 0.2)
        for b in range(2):
            torch.testing.assert_close(out[b], bas_relief_normals(n, float(scale[b].detach()), float(tilt[b]), 0.2))
        out.sum().backward()
        assert scale.grad is not None and bool(torch.isfinite(scale.grad).all())
        with pytest.raises(ValueError, match=r"tilt_x must be a number or hold one value per image \(2\)"):
            bas_relief_normals(batch, 1.0, torch.zeros(3))


class TestMedianSlope:
    def test_a_plane_reads_its_gradient(self):
        # z = 0.3 u + 0.4 v: slope 0.5 at every pixel
        mask = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        mask[..., 4:12, 4:12] = True
        n = torch.nn.functional.normalize(torch.tensor([-0.3, -0.4, 1.0]), dim=0)
        normals = n[None, :, None, None] * mask
        torch.testing.assert_close(median_slope(normals, mask), torch.tensor([0.5]))

    def test_a_bas_relief_scale_multiplies_it(self):
        _, n, mask = gaussian_bump(48)
        before = median_slope(n, mask[None])
        assert 0.05 < float(before) < 5
        torch.testing.assert_close(median_slope(bas_relief_normals(n, 1.7), mask[None]), 1.7 * before)

    def test_unbatched_and_errors(self):
        _, n, mask = gaussian_bump(32)
        assert median_slope(n, mask[None]).shape == ()
        with pytest.raises(ValueError, match="empty"):
            median_slope(n[None], torch.zeros(1, 1, 32, 32, dtype=torch.bool))
        with pytest.raises(ValueError, match="normals"):
            median_slope(torch.zeros(1, 2, 32, 32), mask[None, None])


class TestDepthToMesh:
    def test_orthographic(self):
        z, n, mask = sphere_cap(32)
        mesh = depth_to_mesh(z[None], mask[None])
        assert len(mesh.vertices) == int(mask.sum())
        assert float(mesh.face_normals[:, 2].min()) > 0  # faces look at the viewer
        full = depth_to_mesh(torch.zeros(5, 5), torch.ones(5, 5, dtype=torch.bool))
        assert len(full.faces) == 2 * 4 * 4 and full.area == pytest.approx(16.0)

    def test_perspective(self):
        depth, n, mask = perspective_sphere(32, focal=40.0)
        mesh = depth_to_mesh(depth, mask, focal=40.0)
        centres = mesh.triangles_center
        assert float((mesh.face_normals * -centres).sum(1).min()) > 0  # towards the camera centre
        assert float(mesh.vertices[:, 2].max()) < 0  # in front of the camera (z towards the viewer)

    def test_exception(self):
        with pytest.raises(ValueError, match="depth and mask"):
            depth_to_mesh(torch.zeros(2, 4, 4), torch.ones(4, 4))


class TestDepthToNormalsModule:
    def test_smoke(self, device, dtype):
        z, n, mask = _batch(*sphere_cap(24, dtype, device))
        module = DepthToNormals()
        out = module(z, mask)
        assert out.shape == (1, 3, 24, 24) and out.dtype == dtype and out.device.type == device.type
        assert float(angular_error(out, n, mask).median()) < 0.5
        assert list(module.buffers()) == [] and "focal=None" in repr(module)

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        z, _, mask = sphere_cap(16, F64, device)
        depth = torch.stack([z * (1 + b) for b in range(batch)])[:, None]
        masks = mask[None, None].expand(batch, -1, -1, -1)
        assert DepthToNormals()(depth, masks).shape == (batch, 3, 16, 16)
        assert DepthToNormals(focal=40.0)(depth + 50.0, masks).shape == (batch, 3, 16, 16)
        assert DepthToNormals()(z, mask).shape == (3, 16, 16)  # unbatched (H, W)

    def test_exception(self):
        with pytest.raises(ValueError, match="focal"):
            DepthToNormals(focal=-3.0)
        with pytest.raises(ValueError, match="depth"):
            DepthToNormals()(torch.zeros(1, 2, 4, 4), torch.ones(1, 1, 4, 4))
        with pytest.raises(ValueError, match="depth"):
            DepthToNormals(focal=10.0)(torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 4))  # not positive
        with pytest.raises(ValueError, match="mask"):
            DepthToNormals()(torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 5))

    @pytest.mark.parametrize("focal", [None, 30.0])
    def test_gradcheck(self, focal):
        g = torch.Generator().manual_seed(2)
        depth = (5.0 + torch.rand(1, 1, 5, 6, generator=g, dtype=F64)).requires_grad_()
        mask = torch.ones(1, 1, 5, 6, dtype=torch.bool)
        mask[0, 0, 0, :2] = False
        module = DepthToNormals(focal=focal)
        assert torch.autograd.gradcheck(lambda d: module(d, mask), (depth,), fast_mode=True)

    def test_module(self, device, dtype):
        depth, _, mask = perspective_sphere(32, 80.0, dtype)
        depth, mask = depth[None, None].to(device), mask[None, None].to(device)
        expected = depth_to_normals(depth, mask, 80.0, (15.0, 17.0))
        torch.testing.assert_close(DepthToNormals(80.0, (15.0, 17.0))(depth, mask), expected)
        torch.testing.assert_close(DepthToNormals()(depth, mask), depth_to_normals(depth, mask))

    def test_dynamo(self):
        z, _, mask = _batch(*sphere_cap(16))
        compiled = torch.compile(DepthToNormals(), backend="eager")
        torch.testing.assert_close(compiled(z, mask), depth_to_normals(z, mask))
