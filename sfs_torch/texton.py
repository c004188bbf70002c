"""Texton features (paper Sec. 6): CIE L*a*b* and a 17-filter bank in one ``conv2d``.

The bank (Winn et al. 2005, as the paper cites) on the Lab image, every kernel truncated
to ``kernel_size x kernel_size`` (5 x 5, the size of the training patches):

* Gaussians, sigma 1, 2, 4, on each of L, a, b (filters 0-8),
* Laplacians of Gaussian, sigma 1, 2, 4, 8, on L (filters 9-12),
* first derivatives of Gaussian along x and y, sigma 2 and 4, on L (filters 13-16).

Each kernel equals what ``scipy.ndimage`` applies with ``radius = kernel_size // 2``:
``gaussian_filter``, ``gaussian_laplace`` and ``gaussian_filter(order=...)`` (the
truncated 1-D Gaussian normalised to sum 1, its derivatives taken analytically and not
renormalised). Derivatives are in the camera frame: ``x`` to the right (scipy's
``order=(0, 1)``) and ``y`` **up**, i.e. minus scipy's ``order=(1, 0)`` along rows.

Background rule (identical for training patches and test images): pixels outside the
mask are set to black *before* the Lab conversion, and the image is zero-padded. Black is
Lab ``(0, 0, 0)``, so zero padding of the Lab image is the same as a black border, and a
``kernel_size`` patch filtered with ``padding="valid"`` equals the ``"same"`` response at
its centre pixel.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._blocks import in_blocks
from ._checks import check_finite, check_mask, check_same_size, check_shape, from_batch, is_integer, to_batch

__all__ = [
    "N_TEXTON_FILTERS",
    "TEXTON_FILTER_NAMES",
    "TextonConfig",
    "texton_filter_bank",
    "linear_rgb_to_lab",
    "texton_features",
    "LinearRGBToLab",
    "TextonFeatures",
]

PADDINGS = ("same", "valid")

_GAUSS_SIGMAS = (1.0, 2.0, 4.0)
_LOG_SIGMAS = (1.0, 2.0, 4.0, 8.0)
_DERIV_SIGMAS = (2.0, 4.0)

TEXTON_FILTER_NAMES: Tuple[str, ...] = (
    *(f"gauss_{c}_s{s:g}" for c in ("L", "a", "b") for s in _GAUSS_SIGMAS),
    *(f"log_L_s{s:g}" for s in _LOG_SIGMAS),
    *(f"d{axis}_L_s{s:g}" for s in _DERIV_SIGMAS for axis in ("x", "y")),
)
N_TEXTON_FILTERS = len(TEXTON_FILTER_NAMES)  # 17


@dataclass
class TextonConfig:
    """Texton features.

    Attributes:
        kernel_size: odd support of every filter; the paper matches the 5 x 5 patches.
    """

    kernel_size: int = 5


def _gaussian_kernel1d(sigma: float, order: int, radius: int) -> Tensor:
    """scipy.ndimage's truncated 1-D Gaussian (or derivative), as a correlation kernel."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    phi = torch.exp(-0.5 * x * x / sigma**2)
    phi = phi / phi.sum()
    poly = {0: torch.ones_like(x), 1: -x / sigma**2, 2: x * x / sigma**4 - 1.0 / sigma**2}[order]
    # scipy convolves (reverses the kernel); conv2d correlates
    return (poly * phi).flip(0)


@functools.lru_cache(maxsize=None)
def _filter_bank(kernel_size: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    r = kernel_size // 2

    def outer(order_row: int, order_col: int, sigma: float) -> Tensor:
        return _gaussian_kernel1d(sigma, order_row, r)[:, None] * _gaussian_kernel1d(sigma, order_col, r)[None, :]

    bank = torch.zeros(N_TEXTON_FILTERS, 3, kernel_size, kernel_size, dtype=torch.float64)
    i = 0
    for channel in range(3):
        for sigma in _GAUSS_SIGMAS:
            bank[i, channel] = outer(0, 0, sigma)
            i += 1
    for sigma in _LOG_SIGMAS:
        bank[i, 0] = outer(2, 0, sigma) + outer(0, 2, sigma)
        i += 1
    for sigma in _DERIV_SIGMAS:
        bank[i, 0] = outer(0, 1, sigma)  # d/dx, x right = columns
        bank[i + 1, 0] = -outer(1, 0, sigma)  # d/dy, y up = minus d/drow
        i += 2
    return bank.to(device=device, dtype=dtype)


def _check_kernel_size(kernel_size: int) -> None:
    if not is_integer(kernel_size, 1) or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size!r}")


def _check_padding(padding: str) -> None:
    if padding not in PADDINGS:
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")


def texton_filter_bank(
    kernel_size: int = TextonConfig.kernel_size,
    *,
    device: Optional[torch.device] = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    r"""The 17 texton filters as ``conv2d`` weights for a Lab image.

    Built once and cached per ``(kernel_size, device, dtype)``: do not modify the result
    in place. Order and names: :data:`TEXTON_FILTER_NAMES`.

    Args:
        kernel_size: odd filter support (5 in the paper).
        device: of the returned weights.
        dtype: of the returned weights.

    Returns:
        :math:`(17, 3, k, k)` weights; input channels are L, a, b.

    Raises:
        ValueError: ``kernel_size`` is not a positive odd integer, or ``dtype`` is not a
            floating-point dtype (the filters' weights, all below 1, would round to 0).

    Example:
        >>> texton_filter_bank().shape
        torch.Size([17, 3, 5, 5])
    """
    _check_kernel_size(kernel_size)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
    return _filter_bank(kernel_size, torch.device("cpu") if device is None else torch.device(device), dtype)


# kornia.color.rgb_to_xyz (linear sRGB primaries, D65) with the rows divided by kornia's
# rgb_to_lab reference white (0.95047, 1, 1.08883): linear RGB -> X/Xn, Y/Yn, Z/Zn.
_RGB_TO_XYZ = (
    (0.412453, 0.357580, 0.180423),
    (0.212671, 0.715160, 0.072169),
    (0.019334, 0.119193, 0.950227),
)
_XYZ_WHITE = (0.95047, 1.0, 1.08883)
_RGB_TO_XYZ_WHITE = tuple(tuple(k / w for k in row) for row, w in zip(_RGB_TO_XYZ, _XYZ_WHITE))
# L*a*b* from g = f(t) - 4/29 (f of CIE / kornia below): L = 116 g_y, a = 500 (g_x - g_y),
# b = 200 (g_y - g_z); the offsets -16 and 116 * 4/29 cancel, so black (g = 0) is Lab 0.
_G_TO_LAB = ((0.0, 116.0, 0.0), (500.0, -500.0, 0.0), (0.0, 200.0, -200.0))
_LAB_THRESHOLD = 0.008856  # kornia's (6/29)^3
_LAB_SLOPE = 7.787  # kornia's (29/6)^2 / 3


def _mix_channels(image: Tensor, rows: Tuple[Tuple[float, ...], ...]) -> Tensor:
    """``out[:, i] = sum_j rows[i][j] * image[:, j]``: a 3 x 3 colour matrix on (B, 3, H, W).

    Three broadcast multiply-adds into one output (differentiable; the in-place adds
    keep nothing autograd needs), cheaper on CPU than ``einsum``, which copies.
    """
    m = torch.tensor(rows, dtype=image.dtype, device=image.device).view(3, 3, 1, 1)
    out = image[:, 0:1] * m[:, 0]
    out.addcmul_(image[:, 1:2], m[:, 1])
    return out.addcmul_(image[:, 2:3], m[:, 2])


def _lab_g(image: Tensor) -> Tensor:
    """Linear RGB (B, 3, H, W) -> ``f(X/Xn, Y/Yn, Z/Zn) - 4/29`` (B, 3, H, W), 0 at black.

    ``f(t) = t^(1/3)`` above ``(6/29)^3`` and ``7.787 t + 4/29`` below, kornia's
    constants; the cube-root branch is clamped so that its gradient stays finite.
    """
    t = _mix_channels(image, _RGB_TO_XYZ_WHITE)
    cube_root = t.clamp(min=_LAB_THRESHOLD).pow(1.0 / 3.0).sub_(4.0 / 29.0)
    return torch.where(t > _LAB_THRESHOLD, cube_root, t * _LAB_SLOPE)


def _lab(image: Tensor) -> Tensor:
    """Linear RGB (B, 3, H, W) -> L*a*b* (B, 3, H, W), unchecked."""
    return _mix_channels(_lab_g(image), _G_TO_LAB)


def linear_rgb_to_lab(image: Tensor) -> Tensor:
    r"""CIE L*a*b* (D65, 2 degree observer) of a LINEAR RGB image.

    Computed directly, linear RGB -> XYZ -> L*a*b*, with kornia's matrix, white point and
    thresholds: it equals ``kornia.color.rgb_to_lab(kornia.color.linear_rgb_to_rgb(x))``
    (kornia's ``rgb_to_lab`` expects sRGB-encoded input and linearises it again) to
    float rounding, without the two ``pow`` calls of that round trip, and it matches
    ``skimage.color.rgb2lab`` of the sRGB encoding. Differentiable; the gradient is
    finite everywhere (black included).

    Args:
        image: :math:`(B, 3, H, W)` (or :math:`(3, H, W)`) linear RGB, nominally [0, 1].

    Returns:
        :math:`(B, 3, H, W)` L in [0, 100], a and b roughly in [-128, 127]; dtype and
        device of ``image``. Black is exactly ``(0, 0, 0)``.

    Example:
        >>> black_white = torch.tensor([0.0, 1.0]).view(1, 1, 2).expand(3, 1, 2)
        >>> linear_rgb_to_lab(black_white)[0].flatten().tolist()  # L
        [0.0, 100.0]
    """
    batch, single = to_batch(image, "image", 3)
    check_shape(batch, "image", "B 3 H W")
    return from_batch(_lab(batch), single)


def texton_features(
    image: Tensor, mask: Optional[Tensor] = None, *, kernel_size: int = TextonConfig.kernel_size, padding: str = "same"
) -> Tensor:
    r"""Texton filter responses of a linear RGB image.

    Pixels outside ``mask`` are set to black before the Lab conversion, and the image
    border is zero-padded (black). ``padding="valid"`` on ``kernel_size`` patches gives
    exactly the ``"same"`` response at the patch centres. Differentiable in ``image``.

    Equals ``conv2d(linear_rgb_to_lab(masked image), texton_filter_bank(k))``; large
    batches are processed in blocks (of about ``2**18`` values), ``kernel_size`` patches
    with ``padding="valid"`` as one matrix product.

    Args:
        image: :math:`(B, 3, H, W)` (or :math:`(3, H, W)`) linear RGB.
        mask: optional :math:`(B, 1, H, W)` (or :math:`(1, H, W)`, :math:`(H, W)`) bool / 0-1.
        kernel_size: odd filter support.
        padding: ``"same"`` (output :math:`H \times W`) or ``"valid"`` (output
            :math:`(H - k + 1) \times (W - k + 1)`).

    Returns:
        :math:`(B, 17, H', W')` responses (same dtype and device as ``image``).
    """
    _check_padding(padding)
    batch, single = to_batch(image, "image", 3)
    check_shape(batch, "image", "B 3 H W")
    check_finite(batch, "image")
    if padding == "valid" and min(batch.shape[-2:]) < kernel_size:
        raise ValueError(
            f"image of size {tuple(batch.shape[-2:])} is smaller than kernel_size {kernel_size} for padding='valid'"
        )
    weights = texton_filter_bank(kernel_size, device=batch.device, dtype=batch.dtype)
    mask_b = None
    if mask is not None:
        # any coverage is valid here: a training patch may lie wholly inside the object
        mask_b = check_mask(to_batch(mask, "mask", 1)[0], allow_full=True, allow_empty=True)
        check_same_size(batch, "image", mask_b, "mask")
    n, (height, width) = batch.shape[0], batch.shape[-2:]
    if padding == "valid":
        height, width = height - kernel_size + 1, width - kernel_size + 1

    def responses(part: slice) -> Tensor:
        block = batch[part]
        if mask_b is not None:
            block = torch.where(mask_b[part], block, torch.zeros((), dtype=block.dtype, device=block.device))
        lab = _lab(block)
        if height == width == 1 and padding == "valid":  # a patch of the kernel's size: one matrix product
            return F.linear(lab.flatten(1), weights.flatten(1)).view(-1, N_TEXTON_FILTERS, 1, 1)
        return F.conv2d(lab, weights, padding=kernel_size // 2 if padding == "same" else 0)

    # large batches (the training patches) in blocks
    return from_batch(in_blocks(responses, n, batch[0:1].numel(), (n, N_TEXTON_FILTERS, height, width), batch), single)


class LinearRGBToLab(nn.Module):
    r"""CIE L*a*b* of a linear RGB image (module form of :func:`linear_rgb_to_lab`).

    No options and no state; ``forward(image)`` takes :math:`(B, 3, H, W)` (or
    :math:`(3, H, W)`) linear RGB and returns Lab of the same shape, dtype and device.

    Example:
        >>> LinearRGBToLab()(torch.zeros(1, 3, 2, 2)).shape
        torch.Size([1, 3, 2, 2])
    """

    def forward(self, image: Tensor) -> Tensor:
        return linear_rgb_to_lab(image)


class TextonFeatures(nn.Module):
    r"""The 17 texton responses of a linear RGB image (module form of :func:`texton_features`).

    Stores ``kernel_size`` and ``padding`` (checked here, as the function checks them);
    the filter bank is not a buffer: :func:`texton_filter_bank` builds it on the input's
    device and dtype at the first call and caches it there.

    Args:
        kernel_size: odd filter support (:attr:`TextonConfig.kernel_size`, 5 in the paper).
        padding: ``"same"`` or ``"valid"``.

    ``forward(image, mask=None)``: image :math:`(B, 3, H, W)` (or :math:`(3, H, W)`),
    optional mask :math:`(B, 1, H, W)`; returns :math:`(B, 17, H', W')`.

    Example:
        >>> TextonFeatures()(torch.rand(2, 3, 8, 8)).shape
        torch.Size([2, 17, 8, 8])
    """

    def __init__(self, kernel_size: int = TextonConfig.kernel_size, padding: str = "same"):
        super().__init__()
        _check_kernel_size(kernel_size)
        _check_padding(padding)
        self.kernel_size, self.padding = kernel_size, padding

    def forward(self, image: Tensor, mask: Optional[Tensor] = None) -> Tensor:
        return texton_features(image, mask, kernel_size=self.kernel_size, padding=self.padding)

    def extra_repr(self) -> str:
        return f"kernel_size={self.kernel_size}, padding={self.padding!r}"
