"""Silhouette features (paper Sec. 6.1): distances to the contour and the medial axis.

Everything here is a function of the object mask alone, batched ``(B, 1, H, W)``, and
runs on any device.

* :func:`euclidean_distance_transform`: exact Euclidean distance transform (EDT), the
  same numbers as ``scipy.ndimage.distance_transform_edt``.
* :func:`medial_axis`: the pruned integer medial axis (Hesselink & Roerdink 2008), read
  off the feature transform that the EDT yields for free.
* :func:`silhouette_distances`: ``d_B``, ``d_M``, ``d_rel = d_B / (d_B + d_M)`` (Eq. 6)
  and the direction ``beta`` to the contour (Eq. 7).
* :func:`silhouette_features`: ``[d_rel, cos beta, sin beta]``, the forest's input.
* :func:`coarse_normals`: the silhouette-only normal estimate of Eq. 10.

Frames: pixel row ``i``, column ``j`` sits at ``u = j + 0.5 - cx``, ``v = cy - (i + 0.5)``
(x right, **y up**); ``beta`` is an angle in that frame.

Image border: as in scipy, pixels beyond the border are *not* background. A silhouette
cut by the image border therefore has no contour along the cut (the cut is not an
occluding contour), and ``d_B`` there measures the distance to the visible contour.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import Tensor

from ._checks import check_mask, from_batch, is_number, to_batch
from .camera import rotate_normals_to_camera

__all__ = [
    "SilhouetteConfig",
    "check_silhouette_config",
    "SilhouetteDistances",
    "euclidean_distance_transform",
    "medial_axis",
    "silhouette_distances",
    "silhouette_features",
    "coarse_normals",
]


@dataclass
class SilhouetteConfig:
    """Knobs of the silhouette features.

    Attributes:
        prune_distance: a pair of neighbouring object pixels adds a medial-axis point
            only when their nearest contour points lie more than this many pixels
            apart; branches caused by contour bumps narrower than this vanish.
        prune_angle: ... and only when the directions from the two pixels to their
            nearest contour points differ by more than this angle (degrees). This is
            the scale-invariant object-angle test: where the nearest contour point just
            slides along a smooth contour the directions differ by about
            ``1 / radius`` radians, so a disk keeps only the pixels within
            ``1 / radians(prune_angle)`` pixels of its centre, while true axis points
            (spokes to both sides of the shape) differ by far more. Rectangle corner
            branches have 90 degrees; the ends of elongated axes get trimmed where
            the shape narrows below this angle.
        prune_depth_ratio, prune_window: an axis point must be at least
            ``prune_depth_ratio`` as far from the contour as the deepest pixel within
            ``prune_window`` times its own depth. Contour bumps and notches make
            axis points near the contour, right beside much deeper interior; a single
            one would cap ``d_M`` by about ``d_B`` over the whole object, so this
            non-local test is what makes ``d_rel`` robust to noisy silhouettes
            (``prune_depth_ratio=0`` disables it). It also trims the shallow ends of
            corner branches.
        depth_layer_ratio: ``d_M`` of a pixel at depth ``d`` only looks at axis points
            deeper than about ``d / depth_layer_ratio`` (see Eq. 5: the axis point on
            the ray through the pixel is deeper than the pixel); ``inf`` gives the
            plain distance to the axis. Costs one extra row pass per factor of this
            ratio in depth.
        gradient_sigma: Gaussian smoothing (pixels) of ``d_rel`` before its Sobel
            gradient gives ``beta``; the distance transform is quantised to the pixel
            grid, and on a disk of radius 100 px this takes the median ``beta`` error
            from 1.2 to 0.55 degrees (``0`` disables it).
    """

    prune_distance: float = 3.0
    prune_angle: float = 60.0
    prune_depth_ratio: float = 0.5
    prune_window: float = 2.0
    depth_layer_ratio: float = 2.0
    gradient_sigma: float = 1.5


def check_silhouette_config(cfg: SilhouetteConfig, prefix: str = "") -> None:
    """``ValueError`` naming the first bad option of ``cfg`` as ``prefix`` + its field name
    (``"silhouette."`` in the pipeline, ``"config."`` in the functions here).

    Example:
        >>> check_silhouette_config(SilhouetteConfig(prune_angle=200.0), prefix="silhouette.")
        Traceback (most recent call last):
        ...
        ValueError: silhouette.prune_angle must be in [0, 180] degrees, got 200.0
    """
    for name in ("prune_distance", "prune_angle", "prune_depth_ratio", "prune_window", "gradient_sigma"):
        value = getattr(cfg, name)
        if not is_number(value, 0):
            raise ValueError(f"{prefix}{name} must be a finite number >= 0, got {value!r}")
    if cfg.prune_angle > 180:
        raise ValueError(f"{prefix}prune_angle must be in [0, 180] degrees, got {cfg.prune_angle!r}")
    if not cfg.depth_layer_ratio > 1:  # inf allowed: the plain distance to the axis
        raise ValueError(f"{prefix}depth_layer_ratio must be > 1 (inf for none), got {cfg.depth_layer_ratio!r}")


def _checked_config(config: Optional[SilhouetteConfig]) -> SilhouetteConfig:
    """A function's ``config`` argument, checked; the defaults for ``None``."""
    if config is None:
        return SilhouetteConfig()
    check_silhouette_config(config, prefix="config.")
    return config


def _mask_argument(mask: Tensor, name: str, allow_empty: bool) -> Tuple[Tensor, bool]:
    mask, single = to_batch(mask, name, 1)
    # a distance transform is defined for empty and full masks alike
    mask = check_mask(mask, name, allow_full=allow_empty, allow_empty=allow_empty)
    # the maps built from it keep its strides and are written through flat views, which a
    # transposed or sliced mask would break
    return mask.contiguous(), single


def _lower_envelope(f: Tensor, max_site: int) -> Tuple[Tensor, Tensor]:
    """``min_k f[r, k] + (j - k)^2`` and its argmin for every row ``r`` and column ``j``.

    ``f`` is ``(rows, n)``: integers in ``[0, max_site]`` (as floats), ``inf`` for "no
    site". The matrix ``M[j, k] = f[k] + (j - k)^2`` is Monge (``(j - k)^2`` is, and a
    term per column keeps it so), so the leftmost argmin ``K(j)`` does not decrease with
    ``j``: once ``K`` is known at every ``2s``-th column, ``K`` at the columns half way
    between lies in ``[K(j - s), K(j + s)]``, and these ranges only share their end
    points. For ``j + 1 = s, 3s, 5s, ... <= n`` they hold ``n - 1 + (number of columns)``
    candidates in all, whatever ``K``, so every halving of ``s`` is one fixed-size
    gather and segment minimum per row: ``log2(n) + 1`` rounds of batched ops,
    ``O(n log n)`` per row, no data-dependent loop and no host sync. Exact: integer
    arithmetic (int32 where the values fit, else int64), minimum and argmin taken
    together as ``value * 2^b + k``.

    Returns:
        the minimum, float32 ``(rows, n)`` (``inf`` for a row without sites), and the
        leftmost argmin, long ``(rows, n)`` (0 for a row without sites).
    """
    r, n = f.shape
    dev = f.device
    shift = max(n - 1, 1).bit_length()
    # a column without a site costs more than any real candidate (<= max_site + (n - 1)^2)
    sentinel = max_site + n * n
    fits = ((sentinel + n * n) << shift) + n < torch.iinfo(torch.int32).max
    dt = torch.int32 if fits else torch.int64
    finite = torch.isfinite(f)
    site = torch.where(finite, torch.where(finite, f, 0.0).to(dt), sentinel)
    site = (site << shift) + torch.arange(n, device=dev, dtype=dt)  # f[k] 2^b + k
    big_n = 1 << max(n, 1).bit_length()  # power of two > n: columns j + 1 in [0, big_n]
    arg = torch.zeros(r, big_n + 1, dtype=torch.long, device=dev)  # K at j + 1; K(-1) = 0
    arg[:, n + 1 :] = n - 1  # K beyond the last column: n - 1
    best = torch.zeros(r, big_n + 1, dtype=dt, device=dev)
    stride = big_n // 2
    while stride >= 1:
        count = (n // stride + 1) // 2  # columns of this round: j + 1 = (2m + 1) stride <= n
        bounds = arg[:, 0 : 2 * count * stride + 1 : 2 * stride]  # K(j - stride), K(j + stride)
        size = n - 1 + count
        slot = torch.arange(size, device=dev)
        # segment m (column j) starts at slot K(j - stride) + m and ends at K(j + stride) + m
        starts = torch.zeros(r, size + 1, dtype=torch.long, device=dev)
        starts.scatter_(1, bounds[:, 1:-1] + torch.arange(1, count, device=dev), 1)
        seg = starts[:, :size].cumsum(1)
        k = slot - seg
        jk = (seg * (2 * stride + 1) + (stride - 1 - slot)).to(dt)  # j - k, j = (2 seg + 1) stride - 1
        key = site.gather(1, k) + ((jk * jk) << shift)
        low = torch.full((r, count), torch.iinfo(dt).max, dtype=dt, device=dev)
        low = low.scatter_reduce(1, seg, key, "amin")
        cols = torch.arange(1, 2 * count, 2, device=dev) * stride
        arg[:, cols] = (low & ((1 << shift) - 1)).long()
        best[:, cols] = low >> shift
        stride //= 2
    d2 = best[:, 1 : n + 1]
    out = torch.where(d2 < sentinel, d2.float(), math.inf)
    return out, torch.where(d2 < sentinel, arg[:, 1 : n + 1], 0)


def _edt_squared(foreground: Tensor, region: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
    """Squared EDT and feature transform of ``(B, H, W)`` bool ``foreground``.

    On the CPU, SciPy's C implementation is 1-8x faster than the batched torch one
    (1-2.5x on many small regions, 4-8x on one large disk, ``benchmarks/edt.py``), so
    CPU tensors go there; every other device runs :func:`_edt_squared_torch`. Both
    return the same distances (exact integers when squared); ties between equally near
    background pixels may resolve differently.
    """
    if foreground.device.type == "cpu" and bool((~foreground).flatten(1).any(1).all()):
        return _edt_squared_scipy(foreground)
    return _edt_squared_torch(foreground, region)


def _edt_squared_scipy(foreground: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    dist2, feat_row, feat_col = [], [], []
    for image in foreground.numpy():
        distance, (rows, cols) = ndimage.distance_transform_edt(image, return_indices=True)
        dist2.append(np.rint(distance * distance))
        feat_row.append(rows)
        feat_col.append(cols)
    return (
        torch.from_numpy(np.stack(dist2)).float(),
        torch.from_numpy(np.stack(feat_row)).long(),
        torch.from_numpy(np.stack(feat_col)).long(),
    )


def _edt_squared_torch(foreground: Tensor, region: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
    """Squared EDT and feature transform of ``(B, H, W)`` bool ``foreground``, in torch.

    Two exact 1-D passes: along columns the nearest background row (running max / min of
    background indices), then along rows ``d^2(j) = min_k g(k)^2 + (j - k)^2`` by
    :func:`_lower_envelope`. ``region`` (bool ``(B, H, W)``, default ``foreground``)
    says which pixels are needed: rows without any needed pixel farther than one pixel
    from the background skip the second pass (one host sync, for their count).

    Returns:
        ``dist2`` float32 ``(B, H, W)`` (``inf`` where a batch element has no
        background), and the row and column of the nearest background pixel, long
        ``(B, H, W)``; background pixels are their own nearest background pixel.
    """
    b, h, w = foreground.shape
    device = foreground.device
    rows = torch.arange(h, device=device).view(1, h, 1).expand(b, h, w)
    background = ~foreground
    big = h + w + 1
    above = torch.where(background, rows, -big).cummax(1).values
    below = torch.where(background, rows, 2 * big).flip(1).cummin(1).values.flip(1)
    feat_row = torch.where((rows - above) <= (below - rows), above, below)
    g = (feat_row - rows).abs()
    g2 = torch.where(g >= big, math.inf, g.float().square()).view(b * h, w)

    region = foreground if region is None else region
    # d <= g, and d >= 1 off the background: g <= 1 is already exact
    needed = torch.nonzero((region.reshape(b * h, w) & (g2 > 1.0)).any(1)).flatten()
    dist2 = g2.clone()
    feat_col = torch.arange(w, device=device).expand(b * h, w).clone()
    if needed.numel() > 0:
        d2_rows, col_rows = _lower_envelope(g2[needed], max_site=(h - 1) ** 2)
        dist2[needed] = d2_rows
        feat_col[needed] = col_rows
    feat_row = feat_row.reshape(b * h, w).gather(1, feat_col)
    return dist2.view(b, h, w), feat_row.view(b, h, w), feat_col.view(b, h, w)


def euclidean_distance_transform(mask: Tensor) -> Tensor:
    r"""Exact Euclidean distance of every True pixel to the nearest False pixel.

    Matches ``scipy.ndimage.distance_transform_edt``: distances between pixel centres,
    0 on False pixels, and pixels beyond the image border are *not* background. A batch
    element without any False pixel gets ``inf`` everywhere.

    Args:
        mask: :math:`(B, 1, H, W)` (or :math:`(H, W)`, :math:`(1, H, W)`) bool or 0/1.

    Returns:
        float32 distances in pixels, the shape of ``mask``.

    Example:
        >>> m = torch.zeros(1, 1, 5, 5, dtype=torch.bool); m[..., 1:4, 1:4] = True
        >>> euclidean_distance_transform(m)[0, 0, 2]
        tensor([0., 1., 2., 1., 0.])
    """
    batch, _ = _mask_argument(mask, "mask", allow_empty=True)
    fg = batch[:, 0]
    if fg.device.type == "cpu" and bool((~fg).flatten(1).any(1).all()):
        # distances only: SciPy skips the feature transform
        distance = np.stack([ndimage.distance_transform_edt(image) for image in fg.numpy()])
        return torch.from_numpy(distance).float().view(mask.shape)
    dist2, _, _ = _edt_squared(fg)
    return dist2.sqrt().view(mask.shape)


def _medial_axis_from_features(
    foreground: Tensor, dist2: Tensor, feat_row: Tensor, feat_col: Tensor, config: SilhouetteConfig
) -> Tensor:
    """Pruned integer medial axis of ``(B, H, W)`` ``foreground`` from its feature transform."""
    b, h, w = foreground.shape
    device = foreground.device
    rows = torch.arange(h, device=device).view(1, h, 1)
    cols = torch.arange(w, device=device).view(1, 1, w)
    # spokes: from each pixel to its nearest background pixel, (row, col)
    spoke_r = (feat_row - rows).float()
    spoke_c = (feat_col - cols).float()
    cos_max = math.cos(math.radians(config.prune_angle))
    axis = torch.zeros_like(foreground)
    for dim in (1, 2):  # pairs with the pixel below, then with the pixel to the right
        n = (h if dim == 1 else w) - 1

        def first(x: Tensor) -> Tensor:
            return x.narrow(dim, 0, n)

        def second(x: Tensor) -> Tensor:
            return x.narrow(dim, 1, n)

        step_r, step_c = (1.0, 0.0) if dim == 1 else (0.0, 1.0)
        # difference of the two contour points: F(x) - F(y) = s_x - s_y + (x - y)
        dr = first(spoke_r) - second(spoke_r) - step_r
        dc = first(spoke_c) - second(spoke_c) - step_c
        sep2 = dr * dr + dc * dc
        # crit >= 0: x lies nearer to the bisector of the two contour points than y
        crit = dr * (first(spoke_r) + second(spoke_r)) + dc * (first(spoke_c) + second(spoke_c))
        dot = first(spoke_r) * second(spoke_r) + first(spoke_c) * second(spoke_c)
        norms = (first(dist2) * second(dist2)).sqrt()
        split = (sep2 > config.prune_distance**2) & (dot < cos_max * norms) & first(foreground) & second(foreground)
        first(axis).logical_or_(split & (crit >= 0))
        second(axis).logical_or_(split & (crit <= 0))
    axis &= _locally_deep(dist2.sqrt(), config)
    # every object keeps at least its deepest point, so d_M stays finite after pruning
    deepest = torch.where(foreground, dist2, -1.0).flatten(1).argmax(1)
    axis.view(b, -1)[torch.arange(b, device=device), deepest] = True
    return axis


def _locally_deep(dist: Tensor, config: SilhouetteConfig) -> Tensor:
    """Pixels at least ``prune_depth_ratio`` as deep as the deepest pixel within
    ``prune_window`` times their own depth (a square window, radius rounded up to a power
    of two). Axis points produced by contour noise sit at small depth next to much
    deeper interior and fail this; true axis points are local depth maxima at the scale
    of their own depth. Windows grow by doubling: the max over ``[x - 2r, x + 2r]^2`` is
    the max of the ``r``-windows shifted by ``(+-r, +-r)``.
    """
    if config.prune_depth_ratio <= 0:
        return torch.ones_like(dist, dtype=torch.bool)
    finite = torch.where(torch.isfinite(dist), dist, 0.0)
    need = (config.prune_window * finite).clamp_min(1.0)
    level_needed = torch.ceil(torch.log2(need)).long()
    n_levels = int(level_needed.max()) + 1
    window = finite
    window_max = torch.empty_like(finite)
    for level in range(n_levels):
        r = 1 << level
        if level == 0:
            padded = F.pad(window[:, None], (1, 1, 1, 1), value=-1.0)[:, 0]
            window = F.max_pool2d(padded[:, None], 3, stride=1)[:, 0]
        else:
            half = r // 2
            padded = F.pad(window, (half, half, half, half), value=-1.0)
            h, w = window.shape[-2:]
            window = torch.maximum(
                torch.maximum(padded[:, :h, :w], padded[:, :h, 2 * half :]),
                torch.maximum(padded[:, 2 * half :, :w], padded[:, 2 * half :, 2 * half :]),
            )
        window_max = torch.where(level_needed == level, window, window_max)
    return finite >= config.prune_depth_ratio * window_max


def medial_axis(mask: Tensor, config: Optional[SilhouetteConfig] = None) -> Tensor:
    r"""Pruned medial axis of the object mask.

    The integer medial axis (Hesselink & Roerdink, "Euclidean skeletons of digital image
    and volume data in linear time by the integer medial axis transform", 2008): a pair
    of 4-neighbouring object pixels whose nearest contour points differ by more than
    ``config.prune_distance`` pixels, seen from the two pixels at directions more than
    ``config.prune_angle`` degrees apart, puts the pixel nearer to the bisector of those
    contour points on the axis. Short spurious branches from contour noise have nearby
    contour points and vanish. Each batch
    element keeps at least its deepest pixel.

    Args:
        mask: :math:`(B, 1, H, W)` bool or 0/1, non-empty, not the whole image.
        config: pruning knobs, checked (:func:`check_silhouette_config`); default
            :class:`SilhouetteConfig`.

    Returns:
        :math:`(B, 1, H, W)` bool, a subset of ``mask``.
    """
    config = _checked_config(config)
    batch, single = _mask_argument(mask, "mask", allow_empty=False)
    fg = batch[:, 0]
    dist2, feat_row, feat_col = _edt_squared(fg)
    return from_batch(_medial_axis_from_features(fg, dist2, feat_row, feat_col, config)[:, None], single)


def _distance_to_deeper_axis(foreground: Tensor, axis: Tensor, depth: Tensor, ratio: float) -> Tensor:
    """Distance from each object pixel to the nearest axis point about as deep as itself.

    Eq. 5 measures ``d_M`` along the ray from the nearest contour point through ``p``,
    on which the depth grows up to the axis, so the axis point it meets is deeper than
    ``p``. Pixels are split into depth layers ``[t, ratio * t)`` (``t`` = powers of
    ``ratio``) and each layer only sees axis points of depth ``>= t``: a shallow
    spurious axis point left by contour noise then serves only pixels shallower than
    ``ratio`` times its depth, instead of capping ``d_M`` by about ``d_B`` over the
    whole object. ``ratio = inf`` gives the plain distance to the axis.
    """
    out = torch.zeros_like(depth)
    lower = 0.0
    while True:
        upper = max(1.0, lower * ratio)
        in_layer = foreground & (depth >= lower) & (depth < upper)
        if bool(in_layer.any()):
            targets = axis & (depth >= lower)
            d2 = _edt_squared(~targets, in_layer)[0]
            out = torch.where(in_layer, d2.sqrt(), out)
        if not bool((foreground & (depth >= upper)).any()):
            return out
        lower = upper


@dataclass(frozen=True)
class SilhouetteDistances:
    """Silhouette distances of Sec. 6.1, each :math:`(B, 1, H, W)`, 0 outside the mask.

    Attributes:
        d_boundary: distance to the contour in pixels, ``d_B``. The contour runs half a
            pixel outside the outermost object pixels, so this is the EDT minus 0.5.
        d_medial: distance to the (pruned) medial axis in pixels, ``d_M``.
        d_rel: ``d_B / (d_B + d_M)`` (Eq. 6): near 0 at the contour, 1 on the axis.
        beta: angle (radians, in ``(-pi, pi]``) of the direction to the contour in the
            camera frame (x right, y up), from ``-grad(d_rel)`` (Eq. 7).
        medial: the medial axis, bool.
    """

    d_boundary: Tensor
    d_medial: Tensor
    d_rel: Tensor
    beta: Tensor
    medial: Tensor


def _direction_to_contour(
    foreground: Tensor, d_rel: Tensor, depth: Tensor, feat_row: Tensor, feat_col: Tensor, sigma: float
) -> Tensor:
    """``beta`` of Eq. 7 for ``(B, H, W)`` maps, with the feature transform as fallback."""
    h, w = foreground.shape[-2:]
    x = d_rel[:, None]
    if sigma > 0:
        size = 2 * math.ceil(3 * sigma) + 1
        x = kornia.filters.gaussian_blur2d(x, (size, size), (sigma, sigma), border_type="replicate")
    grad = kornia.filters.spatial_gradient(x, mode="sobel", normalized=True)[:, 0]  # d/dcol, d/drow
    gx, gy = -grad[:, 0], grad[:, 1]  # -grad(d_rel) with x right, y up (rows grow downwards)
    # d_rel falls by about 1 / depth per pixel (half that on the contour, where the
    # blur reaches the flat outside); far less means the stencil straddles the medial
    # axis, where the gradient is undefined: point at the nearest contour pixel instead
    weak = (gx * gx + gy * gy) * depth * depth < 0.04
    rows = torch.arange(h, device=x.device).view(1, h, 1)
    cols = torch.arange(w, device=x.device).view(1, 1, w)
    fx = (feat_col - cols).to(x.dtype)
    fy = (rows - feat_row).to(x.dtype)
    gx = torch.where(weak, fx, gx)
    gy = torch.where(weak, fy, gy)
    beta = torch.atan2(gy, gx)
    return torch.where(foreground, beta, 0.0)


def silhouette_distances(mask: Tensor, config: Optional[SilhouetteConfig] = None) -> SilhouetteDistances:
    r"""Distances to contour and medial axis, ``d_rel`` (Eq. 6) and ``beta`` (Eq. 7).

    Args:
        mask: :math:`(B, 1, H, W)` bool or 0/1 object mask, non-empty, not the whole
            image; several components, holes and border contact are fine. A single
            :math:`(1, H, W)` or :math:`(H, W)` mask gives :math:`(1, H, W)` fields.
        config: :class:`SilhouetteConfig`, checked (:func:`check_silhouette_config`); ``None``
            for the defaults.

    Returns:
        :class:`SilhouetteDistances`, float32 fields :math:`(B, 1, H, W)`.
    """
    config = _checked_config(config)
    batch, single = _mask_argument(mask, "mask", allow_empty=False)
    fg = batch[:, 0]
    dist2, feat_row, feat_col = _edt_squared(fg)
    axis = _medial_axis_from_features(fg, dist2, feat_row, feat_col, config)
    d_boundary = torch.where(fg, dist2.sqrt() - 0.5, 0.0)
    d_medial = _distance_to_deeper_axis(fg, axis, dist2.sqrt(), config.depth_layer_ratio)
    depth = d_boundary + d_medial
    d_rel = torch.where(fg, d_boundary / depth.clamp_min(1e-6), 0.0)
    beta = _direction_to_contour(fg, d_rel, depth, feat_row, feat_col, config.gradient_sigma)
    fields = [d_boundary, d_medial, d_rel, beta, axis]
    return SilhouetteDistances(*(from_batch(f[:, None], single) for f in fields))


def silhouette_features(mask: Tensor, config: Optional[SilhouetteConfig] = None) -> Tensor:
    r"""The forest's silhouette features ``[d_rel, cos beta, sin beta]``.

    Args:
        mask: :math:`(B, 1, H, W)` bool or 0/1 (or a single :math:`(1, H, W)` / :math:`(H, W)`).
        config: :class:`SilhouetteConfig`.

    Returns:
        :math:`(B, 3, H, W)` float32, exactly 0 outside the mask.
    """
    batch, single = _mask_argument(mask, "mask", allow_empty=False)
    dist = silhouette_distances(batch, config)
    inside = batch
    cos_b = torch.where(inside, torch.cos(dist.beta), 0.0)
    sin_b = torch.where(inside, torch.sin(dist.beta), 0.0)
    return from_batch(torch.cat([dist.d_rel, cos_b, sin_b], dim=1), single)


def coarse_normals(
    mask: Tensor,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    config: Optional[SilhouetteConfig] = None,
) -> Tensor:
    r"""Silhouette-only normal estimate (Eq. 10).

    ``c = 1 - d_rel``, ``n = (c cos beta, c sin beta, sqrt(1 - c^2))``: exact for a sphere
    (a disk mask) under orthographic projection. With ``focal`` each normal is rotated by
    its pixel's perspective rotation (Sec. 8).

    Args:
        mask: :math:`(B, 1, H, W)` bool or 0/1 (or single :math:`(1, H, W)` / :math:`(H, W)`).
        focal: focal length in pixels, ``None`` for orthographic.
        principal_point: ``(cx, cy)`` in pixels; default image centre.
        config: :class:`SilhouetteConfig`.

    Returns:
        :math:`(B, 3, H, W)` float32 unit normals in the camera frame, 0 outside.
    """
    batch, single = _mask_argument(mask, "mask", allow_empty=False)
    dist = silhouette_distances(batch, config)
    c = 1.0 - dist.d_rel
    inside = batch
    nx = c * torch.cos(dist.beta)
    ny = c * torch.sin(dist.beta)
    nz = torch.sqrt((1.0 - c * c).clamp_min(0.0))
    normals = torch.where(inside, torch.cat([nx, ny, nz], dim=1), 0.0)
    if focal is not None:
        normals = rotate_normals_to_camera(normals, focal, principal_point)
    return from_batch(normals, single)
