import math

import pytest
import torch

from sfs_torch import _blocks
from sfs_torch.lighting import (
    SHFit,
    SHRenderer,
    SHRotation,
    fit_sh,
    fit_sh_vectors,
    irradiance_to_sh,
    matrix_to_sh,
    natural_lightings,
    render_sh,
    render_sphere,
    rotate_sh,
    sh_basis,
    sh_basis_vectors,
    sh_to_matrix,
    sphere_normals,
)


def random_normals(b, h, w, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(b, 3, h, w, generator=g, dtype=dtype)
    return n / n.norm(dim=1, keepdim=True)


def random_sh(b, dtype=torch.float64, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, 3, 9, generator=g, dtype=dtype)


def random_rotation(seed=2, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


class TestSHBasis:
    def test_orthonormal_on_sphere(self):
        # Monte-Carlo-free check: a fine Fibonacci sphere integrates products exactly enough.
        n = 200_000
        i = torch.arange(n, dtype=torch.float64) + 0.5
        z = 1 - 2 * i / n
        phi = math.pi * (1 + 5**0.5) * i
        r = torch.sqrt(1 - z * z)
        dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 0).view(1, 3, 1, n)
        basis = sh_basis(dirs)[0, :, 0]  # (9, n)
        gram = basis @ basis.T * (4 * math.pi / n)
        assert torch.allclose(gram, torch.eye(9, dtype=torch.float64), atol=2e-5)

    def test_exception(self):
        with pytest.raises(ValueError, match="normals"):
            sh_basis(torch.zeros(1, 2, 4, 4))
        with pytest.raises(ValueError, match=r"^n must have shape \(\*, 3\), got \(5, 4\)$"):
            sh_basis_vectors(torch.zeros(5, 4))
        with pytest.raises(TypeError, match=r"^n must be a torch.Tensor"):
            sh_basis_vectors([0.0, 0.0, 1.0])


class TestRenderSH:
    def test_cardinality(self, device, dtype):
        n = random_normals(2, 5, 6, dtype).to(device)
        out = render_sh(n, random_sh(2, dtype).to(device))
        assert out.shape == (2, 3, 5, 6) and out.dtype == dtype and out.device.type == device.type

    def test_constant_light(self, device, dtype):
        sh = torch.zeros(1, 3, 9, dtype=dtype, device=device)
        sh[0, :, 0] = torch.tensor([0.2, 0.5, 0.9]) / 0.282095
        out = render_sh(random_normals(1, 4, 4, dtype).to(device), sh)
        assert torch.allclose(out[0, :, 0, 0], torch.tensor([0.2, 0.5, 0.9], dtype=dtype, device=device), atol=1e-6)

    def test_equals_basis_sum(self, device, dtype):
        """The polynomial form == the 9-term basis sum (unit, zero and non-unit normals)."""
        n = random_normals(3, 5, 4, dtype).to(device)
        n[0, :, 0, :3] = 0.0  # background
        n[1] *= 1.7  # not unit: the polynomial must not assume |n| = 1
        sh = random_sh(3, dtype).to(device)
        tol = dict(atol=2e-6, rtol=1e-6) if dtype == torch.float32 else dict(atol=1e-12, rtol=0)
        ref = torch.einsum("bck,bkhw->bchw", sh, sh_basis(n))
        torch.testing.assert_close(render_sh(n, sh), ref, **tol)
        torch.testing.assert_close(render_sh(n, sh[0]), torch.einsum("ck,bkhw->bchw", sh[0], sh_basis(n)), **tol)
        zero = render_sh(torch.zeros(1, 3, 1, 1, dtype=dtype, device=device), sh[:1])[0, :, 0, 0]
        torch.testing.assert_close(zero, 0.282095 * sh[0, :, 0] - 0.315392 * sh[0, :, 6], **tol)

    def test_blocks(self, monkeypatch):
        """A batch larger than one block gives what one pass gives, values and gradients."""
        n = random_normals(7, 2, 3).requires_grad_()
        sh = random_sh(7).requires_grad_()
        whole, shared = render_sh(n, sh), render_sh(n, sh[0])
        monkeypatch.setattr(_blocks, "BLOCK_VALUES", 2 * 18)  # blocks of 2, 2, 2, 1 maps
        torch.testing.assert_close(render_sh(n, sh), whole, atol=1e-14, rtol=0)
        torch.testing.assert_close(render_sh(n, sh[0]), shared, atol=1e-14, rtol=0)
        assert torch.autograd.gradcheck(render_sh, (n, sh), fast_mode=True)
        one = sh[0].detach().requires_grad_()  # shared lighting: the gradient sums over the batch
        assert torch.autograd.gradcheck(render_sh, (n, one), fast_mode=True)
        with torch.no_grad():
            torch.testing.assert_close(render_sh(n, sh), whole, atol=1e-14, rtol=0)

    def test_shared_lighting_broadcasts(self):
        n = random_normals(3, 4, 4)
        sh = random_sh(1)
        assert torch.allclose(render_sh(n, sh[0]), render_sh(n, sh.expand(3, -1, -1)))

    def test_exception(self):
        with pytest.raises(ValueError, match="sh"):
            render_sh(random_normals(1, 4, 4), torch.zeros(1, 3, 4))
        with pytest.raises(ValueError, match="batch size"):
            render_sh(random_normals(2, 4, 4), torch.zeros(3, 3, 9))

    def test_gradcheck(self):
        n = random_normals(1, 3, 3).requires_grad_()
        sh = random_sh(1).requires_grad_()
        assert torch.autograd.gradcheck(render_sh, (n, sh))

    def test_module(self):
        sh = random_sh(2)
        n = random_normals(2, 4, 4)
        assert torch.equal(SHRenderer(sh)(n), render_sh(n, sh))


class TestFitSH:
    def test_round_trip(self, device):
        sh = random_sh(2, torch.float32).to(device)
        n = random_normals(2, 32, 32, torch.float32).to(device)
        mask = torch.ones(2, 1, 32, 32, dtype=torch.bool, device=device)
        fitted = fit_sh(n, render_sh(n, sh), mask)
        assert (fitted - sh).abs().max() < 1e-5

    def test_nonnegative_constraint(self):
        # a lighting that is negative on part of the hemisphere, observed on all of it
        n = random_normals(1, 16, 16, torch.float64)
        n[:, 2] = n[:, 2].abs()
        sh = torch.zeros(1, 3, 9, dtype=torch.float64)
        sh[:, :, 0], sh[:, :, 3] = 1.0, 2.0  # 0.28 + 0.98 x: negative for x < -0.29
        mask = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        image = render_sh(n, sh)
        directions = n.flatten(2)[0].T
        assert torch.allclose(fit_sh(n, image, mask), sh, atol=1e-6)
        fitted = fit_sh(n, image, mask, nonnegative=directions)
        shading = render_sh(n, fitted)
        assert float(shading.min()) > -1e-3 and float(image.min()) < -0.5
        # where the true shading is comfortably positive the constrained fit stays close to it
        assert float((shading - image)[image > 0.5].abs().median()) < 0.2
        # the solver's transpose is copied: callers that view the result flat (L-BFGS) need it
        assert fitted.is_contiguous()

    def test_nonnegative_leaves_valid_fits_alone(self):
        n = random_normals(1, 16, 16, torch.float64)
        sh = natural_lightings()["st_peters_basilica"].double()[None]
        mask = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        image = render_sh(n, sh)
        directions = n.flatten(2)[0].T[n.flatten(2)[0, 2] > 0]
        assert torch.allclose(fit_sh(n, image, mask, nonnegative=directions), fit_sh(n, image, mask))

    def test_hemisphere_round_trip(self):
        # The visible hemisphere alone determines all 9 coefficients.
        sphere = sphere_normals(64)
        sh = random_sh(1, torch.float32)
        image = render_sh(sphere.normals, sh)
        assert (fit_sh(sphere.normals, image, sphere.mask) - sh).abs().max() < 1e-4

    def test_mask_excludes_outliers(self):
        sh = random_sh(1)
        n = random_normals(1, 16, 16)
        image = render_sh(n, sh)
        mask = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        image[..., :2, :] = 100.0
        mask[..., :2, :] = False
        assert (fit_sh(n, image, mask) - sh).abs().max() < 1e-8

    def test_weights_are_least_squares(self):
        n = random_normals(1, 8, 8)
        colours = torch.rand(1, 3, 8, 8, dtype=torch.float64)
        weights = torch.rand(1, 1, 8, 8, dtype=torch.float64)
        mask = torch.ones(1, 1, 8, 8, dtype=torch.bool)
        fitted = fit_sh(n, colours, mask, weights)
        a = sh_basis(n)[0].flatten(1).T  # (64, 9)
        w = weights.flatten().sqrt()[:, None]
        ref = torch.linalg.lstsq(a * w, colours[0].flatten(1).T * w).solution.T
        assert torch.allclose(fitted[0], ref, atol=1e-7)

    def test_gradcheck(self):
        n = random_normals(1, 4, 4).requires_grad_()
        colours = torch.rand(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        assert torch.autograd.gradcheck(lambda a, b: fit_sh(a, b, mask), (n, colours))

    def test_exception(self):
        n = random_normals(1, 4, 4)
        with pytest.raises(ValueError, match="mask"):
            fit_sh(n, n, torch.ones(1, 1, 5, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask is empty"):
            fit_sh(n, n, torch.zeros(1, 1, 4, 4, dtype=torch.bool))
        bad = n.clone()
        bad[0, 0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="colours contains 1 NaN"):
            fit_sh(n, bad, torch.ones(1, 1, 4, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="weights"):
            fit_sh(n, n, torch.ones(1, 1, 4, 4, dtype=torch.bool), -torch.ones(1, 1, 4, 4, dtype=torch.float64))

    def test_weights_are_checked(self):
        # NaN weights, or weights zero on the whole mask, gave an all-NaN lighting
        n = random_normals(2, 4, 4)
        mask = torch.zeros(2, 1, 4, 4, dtype=torch.bool)
        mask[:, :, :2] = True
        weights = torch.ones(2, 1, 4, 4, dtype=torch.float64)
        weights[0, 0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match=r"^weights contains 1 NaN or infinite values$"):
            fit_sh(n, n, mask, weights)
        weights = (~mask).double()  # positive only off the mask
        weights[0, 0, 0, 0] = 1.0
        with pytest.raises(ValueError, match=r"^weights are zero on the whole mask in batch element\(s\) \[1\]$"):
            fit_sh(n, n, mask, weights)

    def test_fit_sh_vectors_exception(self):
        # unbatched samples raised an IndexError, a wrong weight shape a bmm error
        n = random_normals(2, 5, 10).flatten(2).transpose(1, 2)  # (2, 50, 3)
        with pytest.raises(ValueError, match=r"^normals must have shape \(B, N, 3\), got \(50, 3\)$"):
            fit_sh_vectors(n[0], n[0])
        with pytest.raises(ValueError, match=r"^normals and colours must have the same shape \(B, N, 3\), got "
                                             r"\(2, 50, 3\) and \(2, 49, 3\)$"):
            fit_sh_vectors(n, n[:, :49])
        with pytest.raises(ValueError, match=r"^weights must have shape \(B, N\) = \(2, 50\), got \(2, 49\)$"):
            fit_sh_vectors(n, n, torch.ones(2, 49, dtype=torch.float64))
        with pytest.raises(ValueError, match=r"^colours must be a floating-point tensor, got torch.int64$"):
            fit_sh_vectors(n, n.long())


class TestConversions:
    def test_ramamoorthi_hanrahan_formula(self):
        c1, c2, c3, c4, c5 = 0.429043, 0.511664, 0.743125, 0.886227, 0.247708
        g = torch.Generator().manual_seed(3)
        lm = torch.randn(3, 9, generator=g, dtype=torch.float64)
        n = random_normals(1, 10, 10)[0].flatten(1)  # (3, 100)
        x, y, z = n
        L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = lm.unbind(-1)
        expected = torch.stack(
            [
                c1 * L22[c] * (x * x - y * y) + c3 * L20[c] * z * z + c4 * L00[c] - c5 * L20[c]
                + 2 * c1 * (L2m2[c] * x * y + L21[c] * x * z + L2m1[c] * y * z)
                + 2 * c2 * (L11[c] * x + L1m1[c] * y + L10[c] * z)
                for c in range(3)
            ]
        )  # irradiance E(n)
        rendered = render_sh(n.view(1, 3, 10, 10), irradiance_to_sh(lm)[None])[0].flatten(1)
        assert torch.allclose(rendered * math.pi, expected, atol=1e-5)

    def test_matrix_form_equals_basis_form(self):
        sh = random_sh(2)
        n = random_normals(2, 6, 6)
        m = sh_to_matrix(sh)  # (2, 3, 4, 4)
        nh = torch.cat([n, torch.ones(2, 1, 6, 6, dtype=n.dtype)], 1)
        quad = torch.einsum("bihw,bcij,bjhw->bchw", nh, m, nh)
        assert torch.allclose(quad, render_sh(n, sh), atol=1e-12)
        assert torch.allclose(m, m.transpose(-1, -2))

    def test_matrix_round_trip(self):
        sh = random_sh(4)
        assert torch.allclose(matrix_to_sh(sh_to_matrix(sh)), sh, atol=1e-12)

    def test_matrix_to_sh_accepts_any_equivalent_matrix(self):
        # Adding t * diag(1, 1, 1, -1) changes nothing on unit normals.
        sh = random_sh(1)
        m = sh_to_matrix(sh) + 0.7 * torch.diag(torch.tensor([1.0, 1, 1, -1], dtype=torch.float64))
        assert torch.allclose(matrix_to_sh(m), sh, atol=1e-12)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"^coefficients must have shape \(\*, 3, 9\), got \(9, 3\)$"):
            irradiance_to_sh(torch.ones(9, 3))
        # integer coefficients truncated the factors A_l / pi to 0
        with pytest.raises(ValueError, match=r"^coefficients must be a floating-point tensor, got torch.int64$"):
            irradiance_to_sh(torch.ones(3, 9, dtype=torch.long))
        with pytest.raises(ValueError, match=r"^sh must have shape \(\*, 3, 9\), got \(9,\)$"):
            sh_to_matrix(torch.ones(9))
        with pytest.raises(ValueError, match=r"^matrix must have shape \(\*, 3, 4, 4\), got \(4, 4\)$"):
            matrix_to_sh(torch.ones(4, 4))
        with pytest.raises(TypeError, match=r"^sh must be a torch.Tensor of shape \(\*, 3, 9\), got list$"):
            sh_to_matrix([0.0] * 9)


class TestRotateSH:
    def test_rotated_lighting_on_rotated_normals(self):
        sh = random_sh(1)
        rot = random_rotation()
        n = random_normals(1, 7, 7)
        rotated_n = torch.einsum("ij,bjhw->bihw", rot, n)
        assert torch.allclose(render_sh(rotated_n, rotate_sh(sh, rot)), render_sh(n, sh), atol=1e-12)

    def test_identity_and_inverse(self):
        sh = random_sh(2)
        rot = random_rotation(seed=5)
        assert torch.allclose(rotate_sh(sh, torch.eye(3, dtype=sh.dtype)), sh, atol=1e-12)
        assert torch.allclose(rotate_sh(rotate_sh(sh, rot), rot.T), sh, atol=1e-12)

    def test_exception(self):
        with pytest.raises(ValueError, match="rotation"):
            rotate_sh(random_sh(1), torch.eye(4))
        # a size error from inside the matrix product before
        with pytest.raises(ValueError, match=r"^sh and rotation must have the same batch size \(or one of them 1\), "
                                             r"got \(2, 3, 9\) and \(5, 3, 3\)$"):
            rotate_sh(torch.ones(2, 3, 9), torch.eye(3).expand(5, 3, 3))
        with pytest.raises(ValueError, match=r"^sh must have shape \(3, 9\) or \(B, 3, 9\), got \(1, 2, 3, 9\)$"):
            rotate_sh(torch.ones(1, 2, 3, 9), torch.eye(3))

    def test_batch_of_one_broadcasts(self):
        sh, rot = random_sh(3), random_rotation()
        assert torch.equal(rotate_sh(sh, rot[None]), rotate_sh(sh, rot))
        assert rotate_sh(sh[:1], rot.expand(4, 3, 3)).shape == (4, 3, 9)


class TestSphere:
    def test_sphere_normals_are_unit_and_y_up(self):
        s = sphere_normals(32)
        norms = s.normals.norm(dim=1)[s.mask[:, 0]]
        assert torch.allclose(norms, torch.ones_like(norms), atol=1e-6)
        assert s.normals[0, 1, 2, 16] > 0.8 and s.normals[0, 1, 29, 16] < -0.8  # y up: top rows face up
        assert s.normals[0, 0, 16, 30] > 0.8  # right columns face right

    def test_render_sphere_lit_from_above(self):
        sh = torch.zeros(3, 9)
        sh[:, 0] = 0.5 / 0.282095
        sh[:, 1] = 0.5 / 0.488603  # light from +y
        img = render_sphere(sh, 32)
        assert img.shape == (3, 32, 32)
        # 0.5 + 0.5 y: y = 0.78 three rows from the top, -0.78 three rows from the bottom
        assert img[0, 3, 16] == pytest.approx(0.5 + 0.5 * 0.78125, abs=1e-5)
        assert img[0, 28, 16] == pytest.approx(0.5 - 0.5 * 0.78125, abs=1e-5) and img[0, 0, 0] == 0

    def test_natural_lightings(self):
        lights = natural_lightings()
        assert len(lights) == 7 and lights["grace_cathedral"].shape == (3, 9)
        # R&H: Grace Cathedral L00 red is 0.79, rendered irradiance constant term c4 * L00 / pi.
        assert lights["grace_cathedral"][0, 0] == pytest.approx(0.79)
        assert lights["grace_cathedral"][0, 1] == pytest.approx(0.39 * 2 / 3)

    @pytest.mark.parametrize("albedo", ["0.7", 0, -1.0, math.inf, True])
    def test_natural_lightings_albedo(self, albedo):
        # a string raised a TypeError from inside the product
        with pytest.raises(ValueError, match=rf"^albedo must be a number > 0, got {albedo!r}$"):
            natural_lightings(albedo)


class TestSHRotation:
    def test_smoke(self, device, dtype):
        rot = random_rotation(dtype=dtype).to(device)
        module = SHRotation(rot)
        out = module(random_sh(2, dtype).to(device))
        assert out.shape == (2, 3, 9) and out.dtype == dtype and out.device.type == device.type
        # the rotation is a buffer: it is in the state_dict and moves with the module
        assert torch.equal(module.state_dict()["rotation"], rot)
        assert module.to(torch.float32).rotation.dtype == torch.float32

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        sh = random_sh(batch).to(device)
        assert SHRotation(random_rotation().to(device))(sh).shape == (batch, 3, 9)
        per_item = torch.stack([random_rotation(seed=s) for s in range(batch)]).to(device)
        out = SHRotation(per_item)(sh)
        assert out.shape == (batch, 3, 9)
        for b in range(batch):
            torch.testing.assert_close(out[b], rotate_sh(sh[b], per_item[b]))
        assert SHRotation(per_item)(sh[0]).shape == (batch, 3, 9)  # one lighting, B rotations

    def test_rotated_lighting_on_rotated_normals(self):
        rot = random_rotation(seed=7)
        sh = random_sh(1)
        n = random_normals(1, 4, 4)
        rotated_n = torch.einsum("ij,bjhw->bihw", rot, n)
        torch.testing.assert_close(render_sh(rotated_n, SHRotation(rot)(sh)), render_sh(n, sh))

    def test_exception(self):
        with pytest.raises(ValueError, match="rotation"):
            SHRotation(torch.eye(4))
        with pytest.raises(ValueError, match="rotation"):
            SHRotation(torch.eye(3, dtype=torch.int64))
        with pytest.raises(TypeError, match="rotation"):
            SHRotation([[1.0, 0.0, 0.0]] * 3)
        with pytest.raises(ValueError, match="sh"):
            SHRotation(torch.eye(3))(torch.zeros(1, 3, 4))

    def test_gradcheck(self):
        sh = random_sh(2).requires_grad_()
        assert torch.autograd.gradcheck(SHRotation(random_rotation()), (sh,), fast_mode=True)
        rot = random_rotation(seed=3).requires_grad_()  # the function is differentiable in the rotation too
        assert torch.autograd.gradcheck(lambda r: rotate_sh(sh, r), (rot,), fast_mode=True)

    def test_module(self, device, dtype):
        rot = random_rotation(dtype=dtype).to(device)
        sh = random_sh(3, dtype).to(device)
        torch.testing.assert_close(SHRotation(rot)(sh), rotate_sh(sh, rot))

    def test_dynamo(self):
        rot, sh = random_rotation(), random_sh(2)
        compiled = torch.compile(SHRotation(rot), backend="eager")
        torch.testing.assert_close(compiled(sh), rotate_sh(sh, rot))


class TestSHFit:
    def test_smoke(self, device, dtype):
        sh = random_sh(1, dtype).to(device)
        n = random_normals(1, 8, 8, dtype).to(device)
        mask = torch.ones(1, 1, 8, 8, dtype=torch.bool, device=device)
        out = SHFit()(n, render_sh(n, sh), mask)
        assert out.shape == (1, 3, 9) and out.dtype == dtype and out.device.type == device.type
        torch.testing.assert_close(out, sh, atol=1e-4, rtol=0)
        assert SHFit().nonnegative is None and list(SHFit().buffers()) == []

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        n = random_normals(batch, 6, 6).to(device)
        colours = torch.rand(batch, 3, 6, 6, dtype=torch.float64, device=device)
        mask = torch.ones(batch, 1, 6, 6, dtype=torch.bool, device=device)
        weights = torch.rand(batch, 1, 6, 6, dtype=torch.float64, device=device)
        assert SHFit()(n, colours, mask).shape == (batch, 3, 9)
        assert SHFit()(n, colours, mask, weights).shape == (batch, 3, 9)

    def test_nonnegative_buffer(self):
        # the constrained fit of TestFitSH.test_nonnegative_constraint, through the module
        n = random_normals(1, 16, 16, torch.float64)
        n[:, 2] = n[:, 2].abs()
        sh = torch.zeros(1, 3, 9, dtype=torch.float64)
        sh[:, :, 0], sh[:, :, 3] = 1.0, 2.0
        mask = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        directions = n.flatten(2)[0].T.contiguous()
        module = SHFit(directions)
        assert "nonnegative" in module.state_dict()
        fitted = module(n, render_sh(n, sh), mask)
        assert float(render_sh(n, fitted).min()) > -1e-3
        torch.testing.assert_close(fitted, fit_sh(n, render_sh(n, sh), mask, nonnegative=directions))

    def test_exception(self):
        n = random_normals(1, 4, 4)
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        with pytest.raises(ValueError, match="nonnegative"):
            SHFit(torch.zeros(5, 2))
        with pytest.raises(ValueError, match="nonnegative"):
            fit_sh(n, n, mask, nonnegative=torch.zeros(5, 2))
        with pytest.raises(ValueError, match="mask"):
            SHFit()(n, n, torch.ones(1, 1, 5, 4, dtype=torch.bool))
        with pytest.raises(ValueError, match="colours"):
            SHFit()(n, n[:, :2], mask)
        with pytest.raises(ValueError, match="weights"):
            SHFit()(n, n, mask, -torch.ones(1, 1, 4, 4, dtype=torch.float64))

    def test_gradcheck(self):
        n = random_normals(1, 4, 4).requires_grad_()
        colours = torch.rand(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
        weights = (0.5 + torch.rand(1, 1, 4, 4, dtype=torch.float64)).requires_grad_()
        mask = torch.ones(1, 1, 4, 4, dtype=torch.bool)
        module = SHFit()
        assert torch.autograd.gradcheck(lambda a, b, w: module(a, b, mask, w), (n, colours, weights), fast_mode=True)

    def test_module(self, device, dtype):
        n = random_normals(2, 6, 5, dtype).to(device)
        colours = torch.rand(2, 3, 6, 5, dtype=dtype, device=device)
        mask = torch.rand(2, 1, 6, 5, device=device) < 0.8
        torch.testing.assert_close(SHFit()(n, colours, mask), fit_sh(n, colours, mask))

    def test_dynamo(self):
        n = random_normals(2, 6, 6)
        colours = torch.rand(2, 3, 6, 6, dtype=torch.float64)
        mask = torch.ones(2, 1, 6, 6, dtype=torch.bool)
        compiled = torch.compile(SHFit(), backend="eager")
        torch.testing.assert_close(compiled(n, colours, mask), fit_sh(n, colours, mask))
