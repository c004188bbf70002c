import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.color import linear_rgb_to_rgb, rgb_to_lab
from scipy import ndimage
from skimage.color import rgb2lab

from sfs_torch import _blocks
from sfs_torch.texton import (
    N_TEXTON_FILTERS,
    TEXTON_FILTER_NAMES,
    LinearRGBToLab,
    TextonConfig,
    TextonFeatures,
    linear_rgb_to_lab,
    texton_features,
    texton_filter_bank,
)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    return np.where(linear > 0.0031308, 1.055 * np.power(np.clip(linear, 0.0031308, None), 1 / 2.4) - 0.055, 12.92 * linear)


def special_values(dtype, device="cpu"):
    """(1, 3, 1, N) linear RGB: 0, tiny, the sRGB and Lab thresholds, 1, out of range, grey
    and mixed pairs of those, and random colours."""
    v = [0.0, 1e-8, 1e-6, 1e-4, 0.0031308, 0.0031309, 0.008856, 0.0088565, 0.01, 0.2, 0.5, 1.0, -0.01, 1.2]
    v = torch.tensor(v, dtype=torch.float64)
    pairs = torch.stack(torch.meshgrid(v, v, indexing="ij")).flatten(1)[[0, 1, 1]]
    g = torch.Generator().manual_seed(7)
    x = torch.cat([v.expand(3, -1), pairs, torch.rand(3, 300, generator=g, dtype=torch.float64)], 1)
    return x[None, :, None].to(device=device, dtype=dtype)


def scipy_bank(lab: np.ndarray, radius: int) -> np.ndarray:
    """The 17 responses of an (3, H, W) Lab image with scipy.ndimage, zero padded."""
    kw = dict(mode="constant", cval=0.0, radius=radius)
    out = [ndimage.gaussian_filter(lab[c], s, **kw) for c in range(3) for s in (1, 2, 4)]
    out += [ndimage.gaussian_laplace(lab[0], s, **kw) for s in (1, 2, 4, 8)]
    for s in (2, 4):
        out.append(ndimage.gaussian_filter(lab[0], s, order=(0, 1), **kw))  # x right
        out.append(-ndimage.gaussian_filter(lab[0], s, order=(1, 0), **kw))  # y up
    return np.stack(out)


class TestTextonFilterBank:
    @pytest.mark.parametrize("kernel_size", [5, 7])
    def test_equals_scipy(self, kernel_size):
        rng = np.random.default_rng(0)
        lab = rng.normal(size=(3, 13, 16))
        bank = texton_filter_bank(kernel_size, dtype=torch.float64)
        got = F.conv2d(torch.from_numpy(lab)[None], bank, padding=kernel_size // 2)[0].numpy()
        np.testing.assert_allclose(got, scipy_bank(lab, kernel_size // 2), atol=1e-6, rtol=0)

    def test_structure(self):
        bank = texton_filter_bank()
        assert bank.shape == (N_TEXTON_FILTERS, 3, 5, 5) == (17, 3, 5, 5)
        assert len(TEXTON_FILTER_NAMES) == 17 and TEXTON_FILTER_NAMES[13:15] == ("dx_L_s2", "dy_L_s2")
        torch.testing.assert_close(bank[:9].sum((-1, -2)).sum(1), torch.ones(9))  # normalised Gaussians
        assert float(bank[9:, 1:].abs().max()) == 0.0  # LoG and derivatives only on L
        # y is up: the derivative is positive when intensity grows towards row 0
        ramp = torch.arange(5.0, 0.0, -1.0).view(1, 1, 5, 1).expand(1, 3, 5, 5)
        resp = F.conv2d(ramp, bank)[0, :, 0, 0]
        assert float(resp[14]) > 0 and abs(float(resp[13])) < 1e-6

    def test_cached(self, device, dtype):
        a = texton_filter_bank(5, device=device, dtype=dtype)
        assert a is texton_filter_bank(5, device=device, dtype=dtype)
        assert a.device.type == device.type and a.dtype == dtype

    def test_exception(self):
        for bad in (4, 0, 2.5):
            with pytest.raises(ValueError, match="kernel_size"):
                texton_filter_bank(bad)

    @pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.complex64, "float32"])
    def test_dtype_must_be_floating(self, dtype):
        # an integer dtype returned all-zero filters
        with pytest.raises(ValueError, match=rf"^dtype must be a floating-point torch.dtype, got {re.escape(repr(dtype))}$"):
            texton_filter_bank(5, dtype=dtype)


class TestLinearRgbToLab:
    def test_matches_skimage(self, dtype):
        rng = np.random.default_rng(1)
        lin = rng.random((2, 3, 6, 7))
        lin[0, :, 0, 0] = 0.0  # black
        lin[0, :, 0, 1] = 0.002  # linear segment of the sRGB curve
        got = linear_rgb_to_lab(torch.from_numpy(lin).to(dtype)).double().numpy()
        ref = np.stack([rgb2lab(srgb_encode(x).transpose(1, 2, 0)).transpose(2, 0, 1) for x in lin])
        np.testing.assert_allclose(got, ref, atol=1e-3 if dtype == torch.float32 else 1e-8)
        assert np.abs(got[0, :, 0, 0]).max() < 1e-4  # black is Lab 0: zero padding == black border

    def test_equals_kornia_on_srgb(self, device, dtype):
        """The direct linear RGB -> XYZ -> Lab equals kornia's rgb_to_lab of the sRGB encoding."""
        x = special_values(dtype, device)
        ref = rgb_to_lab(linear_rgb_to_rgb(x.double()))  # kornia, in float64
        got = linear_rgb_to_lab(x)
        assert got.dtype == dtype and got.device.type == device.type
        # float32: a = 500 (f_x - f_y) turns rounding of f near the threshold into ~2e-4
        tol = dict(atol=5e-4, rtol=1e-6) if dtype == torch.float32 else dict(atol=1e-10, rtol=0)
        torch.testing.assert_close(got.double(), ref, **tol)
        # and no worse than kornia's own round trip in the same dtype
        own = (rgb_to_lab(linear_rgb_to_rgb(x)).double() - ref).abs().max()
        assert float((got.double() - ref).abs().max()) <= 1.5 * float(own) + 1e-10
        assert float(got[0, :, 0, 0].abs().max()) == 0.0  # black is exactly Lab 0

    def test_gradient_equals_kornia(self):
        g = torch.Generator().manual_seed(8)
        x = (0.02 + 0.96 * torch.rand(1, 3, 4, 6, generator=g, dtype=torch.float64)).requires_grad_()
        w = torch.randn(1, 3, 4, 6, generator=g, dtype=torch.float64)
        ours = torch.autograd.grad((linear_rgb_to_lab(x) * w).sum(), x)[0]
        ref = torch.autograd.grad((rgb_to_lab(linear_rgb_to_rgb(x)) * w).sum(), x)[0]
        torch.testing.assert_close(ours, ref, atol=1e-10, rtol=1e-10)
        # finite at black, tiny values and the thresholds too
        x0 = special_values(torch.float64).requires_grad_()
        assert bool(torch.isfinite(torch.autograd.grad(linear_rgb_to_lab(x0).sum(), x0)[0]).all())

    def test_unbatched_and_exception(self):
        x = torch.rand(3, 4, 5)
        torch.testing.assert_close(linear_rgb_to_lab(x), linear_rgb_to_lab(x[None])[0])
        with pytest.raises(ValueError, match="image"):
            linear_rgb_to_lab(torch.rand(1, 4, 4, 4))


class TestTextonFeatures:
    def test_equals_scipy_pipeline(self):
        rng = np.random.default_rng(2)
        lin = rng.random((3, 12, 10))
        mask = rng.random((12, 10)) < 0.7
        got = texton_features(torch.from_numpy(lin)[None], torch.from_numpy(mask)[None, None])[0].numpy()
        lab = rgb2lab(srgb_encode(lin * mask).transpose(1, 2, 0)).transpose(2, 0, 1)
        np.testing.assert_allclose(got, scipy_bank(lab, 2), atol=1e-5)

    def test_patch_equals_full_image(self):
        """Training side: 5x5 patches, background zeroed, 'valid' == 'same' at the centre."""
        g = torch.Generator().manual_seed(0)
        image = torch.rand(1, 3, 20, 24, generator=g, dtype=torch.float64)
        yy, xx = torch.meshgrid(torch.arange(20), torch.arange(24), indexing="ij")
        mask = ((yy - 9) ** 2 + (xx - 14) ** 2 < 60)[None, None]
        full = texton_features(image, mask)
        # patches around every object pixel, zero outside the mask and the image
        padded = F.pad(image * mask, (2, 2, 2, 2))
        patches = F.unfold(padded, 5).view(3, 5, 5, 20, 24).permute(3, 4, 0, 1, 2)
        rows, cols = torch.nonzero(mask[0, 0], as_tuple=True)
        sel = patches[rows, cols]  # (N, 3, 5, 5)
        got = texton_features(sel, padding="valid")
        assert got.shape == (len(rows), 17, 1, 1)
        torch.testing.assert_close(got[:, :, 0, 0], full[0][:, rows, cols].T, atol=1e-10, rtol=0)

    def test_equals_bank_on_lab(self, device, dtype):
        """The bank folded into the weights == the bank on linear_rgb_to_lab of the masked image."""
        g = torch.Generator().manual_seed(9)
        image = torch.rand(2, 3, 9, 11, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
        image[0, :, 0, :14] = special_values(dtype, device)[0, :, 0, :11]
        mask = (torch.rand(2, 1, 9, 11, generator=g) < 0.7).to(device)
        lab = linear_rgb_to_lab(torch.where(mask, image, torch.zeros((), dtype=dtype, device=device)))
        ref = F.conv2d(lab.double(), texton_filter_bank(dtype=torch.float64, device=device), padding=2)
        tol = dict(atol=2e-4, rtol=1e-6) if dtype == torch.float32 else dict(atol=1e-10, rtol=0)
        torch.testing.assert_close(texton_features(image, mask).double(), ref, **tol)

    def test_blocks(self, monkeypatch):
        """A batch larger than one block gives what one pass gives, values and gradients."""
        g = torch.Generator().manual_seed(10)
        image = (0.05 + 0.9 * torch.rand(7, 3, 5, 6, generator=g, dtype=torch.float64)).requires_grad_()
        mask = torch.rand(7, 1, 5, 6, generator=g) < 0.8
        whole_valid, whole_same = texton_features(image, mask, padding="valid"), texton_features(image, mask)
        monkeypatch.setattr(_blocks, "BLOCK_VALUES", 2 * 90)  # blocks of 2, 2, 2, 1 images
        torch.testing.assert_close(texton_features(image, mask, padding="valid"), whole_valid, atol=1e-12, rtol=0)
        torch.testing.assert_close(texton_features(image, mask), whole_same, atol=1e-12, rtol=0)
        assert texton_features(image, mask, padding="valid").shape == (7, 17, 1, 2)
        assert torch.autograd.gradcheck(lambda x: texton_features(x, mask, padding="valid"), (image,), fast_mode=True)

    def test_background_ignored(self):
        image = torch.rand(1, 3, 9, 9)
        mask = torch.zeros(1, 1, 9, 9, dtype=torch.bool)
        mask[..., 2:7, 2:7] = True
        other = torch.where(mask, image, torch.rand(1, 3, 9, 9))
        torch.testing.assert_close(texton_features(image, mask), texton_features(other, mask))
        assert not torch.allclose(texton_features(image), texton_features(other))

    def test_cardinality(self, device, dtype):
        image = torch.rand(2, 3, 8, 11, device=device, dtype=dtype)
        mask = torch.rand(2, 1, 8, 11, device=device) < 0.8
        out = texton_features(image, mask)
        assert out.shape == (2, 17, 8, 11) and out.dtype == dtype and out.device.type == device.type
        for b in range(2):
            torch.testing.assert_close(out[b], texton_features(image[b], mask[b]))
            torch.testing.assert_close(out[b], texton_features(image[b], mask[b, 0]))
        assert texton_features(image, padding="valid").shape == (2, 17, 4, 7)
        assert texton_features(image, kernel_size=TextonConfig().kernel_size).shape == (2, 17, 8, 11)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(3)
        image = (0.05 + 0.9 * torch.rand(1, 3, 5, 6, generator=g, dtype=torch.float64)).requires_grad_()
        mask = torch.ones(1, 1, 5, 6, dtype=torch.bool)
        mask[..., 0, 0] = False
        assert torch.autograd.gradcheck(lambda x: texton_features(x, mask), (image,))

    def test_exception(self):
        with pytest.raises(ValueError, match="padding"):
            texton_features(torch.rand(1, 3, 5, 5), padding="reflect")
        with pytest.raises(ValueError, match="image"):
            texton_features(torch.rand(1, 4, 5, 5))
        with pytest.raises(ValueError, match="mask"):
            texton_features(torch.rand(1, 3, 5, 5), torch.ones(1, 1, 4, 5, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask"):
            texton_features(torch.rand(1, 3, 5, 5), torch.full((1, 1, 5, 5), 0.5))
        with pytest.raises(ValueError, match="kernel_size"):
            texton_features(torch.rand(1, 3, 3, 3), padding="valid")
        with pytest.raises(ValueError, match="image"):
            texton_features(torch.full((1, 3, 5, 5), float("nan")))
        big = torch.rand(4000, 3, 5, 5)  # more than one block
        big[3999, 1, 2, 2] = float("inf")
        with pytest.raises(ValueError, match="image contains 1 NaN or infinite"):
            texton_features(big, padding="valid")

    def test_huge_finite_values_pass_the_check(self):
        # the sum overflows to inf; the exact check then finds no bad value
        image = torch.full((1, 3, 5, 5), 3e38)
        assert bool(torch.isfinite(texton_features(image, padding="valid")).all())


class TestLinearRGBToLabModule:
    def test_smoke(self, device, dtype):
        out = LinearRGBToLab()(torch.rand(1, 3, 4, 5, device=device, dtype=dtype))
        assert out.shape == (1, 3, 4, 5) and out.dtype == dtype and out.device.type == device.type
        # white is L = 100, a = b = 0
        white = LinearRGBToLab()(torch.ones(1, 3, 1, 1, device=device, dtype=dtype))[0, :, 0, 0].double().cpu()
        torch.testing.assert_close(white, torch.tensor([100.0, 0.0, 0.0], dtype=torch.float64), atol=1e-2, rtol=0)

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        assert LinearRGBToLab()(torch.rand(batch, 3, 4, 6, device=device)).shape == (batch, 3, 4, 6)
        assert LinearRGBToLab()(torch.rand(3, 4, 6, device=device)).shape == (3, 4, 6)

    def test_exception(self):
        with pytest.raises(ValueError, match="image"):
            LinearRGBToLab()(torch.rand(1, 4, 4, 4))
        with pytest.raises(ValueError, match="image"):
            LinearRGBToLab()(torch.rand(4, 4))

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(4)
        # away from the sRGB and Lab linear segments near black
        image = (0.05 + 0.9 * torch.rand(1, 3, 3, 4, generator=g, dtype=torch.float64)).requires_grad_()
        assert torch.autograd.gradcheck(LinearRGBToLab(), (image,), fast_mode=True)

    def test_module(self, device, dtype):
        image = torch.rand(2, 3, 5, 5, device=device, dtype=dtype)
        torch.testing.assert_close(LinearRGBToLab()(image), linear_rgb_to_lab(image))

    def test_dynamo(self):
        image = torch.rand(2, 3, 5, 5)
        compiled = torch.compile(LinearRGBToLab(), backend="eager")
        torch.testing.assert_close(compiled(image), linear_rgb_to_lab(image))


class TestTextonFeaturesModule:
    def test_smoke(self, device, dtype):
        image = torch.rand(1, 3, 7, 9, device=device, dtype=dtype)
        module = TextonFeatures()
        out = module(image)
        assert out.shape == (1, N_TEXTON_FILTERS, 7, 9) and out.dtype == dtype and out.device.type == device.type
        assert module.kernel_size == TextonConfig().kernel_size and module.padding == "same"
        assert "kernel_size=5" in repr(module)
        assert list(module.buffers()) == [] and list(module.parameters()) == []

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        image = torch.rand(batch, 3, 8, 11, device=device)
        mask = torch.rand(batch, 1, 8, 11, device=device) < 0.8
        assert TextonFeatures()(image, mask).shape == (batch, 17, 8, 11)
        assert TextonFeatures(kernel_size=3, padding="valid")(image).shape == (batch, 17, 6, 9)
        assert TextonFeatures()(image[0], mask[0]).shape == (17, 8, 11)

    def test_exception(self):
        with pytest.raises(ValueError, match="padding"):
            TextonFeatures(padding="reflect")
        with pytest.raises(ValueError, match="kernel_size"):
            TextonFeatures(kernel_size=4)
        with pytest.raises(ValueError, match="image"):
            TextonFeatures()(torch.rand(1, 4, 5, 5))
        with pytest.raises(ValueError, match="mask"):
            TextonFeatures()(torch.rand(1, 3, 5, 5), torch.ones(1, 1, 4, 5, dtype=torch.bool))
        with pytest.raises(ValueError, match="kernel_size"):
            TextonFeatures(padding="valid")(torch.rand(1, 3, 3, 3))

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(5)
        image = (0.05 + 0.9 * torch.rand(1, 3, 5, 6, generator=g, dtype=torch.float64)).requires_grad_()
        mask = torch.ones(1, 1, 5, 6, dtype=torch.bool)
        mask[..., 0, 0] = False
        module = TextonFeatures()
        assert torch.autograd.gradcheck(lambda x: module(x, mask), (image,), fast_mode=True)

    def test_module(self, device, dtype):
        image = torch.rand(2, 3, 9, 8, device=device, dtype=dtype)
        mask = torch.rand(2, 1, 9, 8, device=device) < 0.7
        torch.testing.assert_close(TextonFeatures()(image, mask), texton_features(image, mask))
        valid = TextonFeatures(kernel_size=7, padding="valid")
        torch.testing.assert_close(valid(image), texton_features(image, kernel_size=7, padding="valid"))

    # dynamo traces through the lru_cache of the filter bank (it builds the same constant bank)
    @pytest.mark.filterwarnings("ignore:Dynamo detected a call to a `functools.lru_cache`")
    def test_dynamo(self):
        image = torch.rand(2, 3, 8, 8)
        mask = torch.rand(2, 1, 8, 8) < 0.8
        compiled = torch.compile(TextonFeatures(), backend="eager")
        torch.testing.assert_close(compiled(image, mask), texton_features(image, mask))
