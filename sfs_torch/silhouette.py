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

from ._checks import check_mask, from_batch, to_batch
from .camera import rotate_normals_to_camera

__all__ = [
    "SilhouetteConfig",
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


def _mask_argument(mask: Tensor, name: str, allow_empty: bool) -> Tuple[Tensor, bool]:
    mask, single = to_batch(mask, name, 1)
    # a distance transform is defined for empty and full masks alike
    return check_mask(mask, name, allow_full=allow_empty, allow_empty=allow_empty), single


def _lower_envelope(f: Tensor) -> Tuple[Tensor, Tensor]:
    """``min_k f[r, k] + (j - k)^2`` and its argmin for every row ``r`` and column ``j``.

    Felzenszwalb & Huttenlocher's lower envelope of parabolas, run for all rows at once:
    the loop goes over the ``n`` columns, each step is a few vector operations over the
    rows, and only the rows that pop a parabola off their stack take part in the pops.
    Stacks are stored column-major, ``(n + 1, rows)``, so that reading one stack level
    for all rows is contiguous. ``f`` is ``(rows, n)`` with ``inf`` for "no site".
    """
    r, n = f.shape
    dev, dt = f.device, f.dtype
    ft = f.t().contiguous()
    stack_v = torch.zeros(n + 1, r, dtype=dt, device=dev)  # parabola apex column
    stack_h = torch.full((n + 1, r), math.inf, dtype=dt, device=dev)  # f + apex^2
    stack_z = torch.full((n + 1, r), math.inf, dtype=dt, device=dev)  # left end of its interval
    top = torch.full((r,), -1, dtype=torch.long, device=dev)
    v_top = torch.zeros(r, dtype=dt, device=dev)
    # an empty stack never pops: its (h, z) make the intersection +inf and the bound -inf
    h_top = torch.full((r,), -math.inf, dtype=dt, device=dev)
    z_top = torch.full((r,), -math.inf, dtype=dt, device=dev)
    finite = torch.isfinite(ft)
    for q in range(n):
        hq = ft[q] + q * q
        act = finite[q]
        # abscissa where parabola q starts beating the top one
        s = (hq - h_top) / (2 * (q - v_top)).clamp_min(1)
        pop = act & (s <= z_top)
        while bool(pop.any()):
            rows = torch.nonzero(pop).flatten()
            k = top[rows] - 1
            top[rows] = k
            v_top[rows] = stack_v[k, rows]
            h_top[rows] = stack_h[k, rows]
            z_top[rows] = stack_z[k, rows]
            s_rows = (hq[rows] - h_top[rows]) / (2 * (q - v_top[rows])).clamp_min(1)
            s[rows] = s_rows
            pop = torch.zeros_like(pop)
            pop[rows] = s_rows <= z_top[rows]
        s = torch.where(top < 0, -math.inf, s)
        top = top + act.long()
        v_top = torch.where(act, float(q), v_top)
        h_top = torch.where(act, hq, h_top)
        z_top = torch.where(act, s, z_top)
        at = torch.where(act, top, n).view(1, r)  # inactive rows write to the spare level n
        stack_v.scatter_(0, at, v_top.view(1, r))
        stack_h.scatter_(0, at, h_top.view(1, r))
        stack_z.scatter_(0, at, z_top.view(1, r))
    level = torch.arange(n + 1, device=dev).view(-1, 1)
    stack_z = torch.where(level > top, math.inf, stack_z)
    j = torch.arange(n, device=dev, dtype=dt).expand(r, n).contiguous()
    which = torch.searchsorted(stack_z[1:].t().contiguous(), j, right=True)
    arg = stack_v.t().gather(1, which)
    return (j - arg).square() + stack_h.t().gather(1, which) - arg.square(), arg.long()


def _edt_squared(foreground: Tensor, region: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
    """Squared EDT and feature transform of ``(B, H, W)`` bool ``foreground``.

    On the CPU, SciPy's C implementation of the same exact algorithm is 5-7x faster
    than the vectorised torch one, so CPU tensors go there; every other device runs
    :func:`_edt_squared_torch`. Both return the same distances (exact integers when
    squared); ties between equally near background pixels may resolve differently.
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
    from the background skip the second pass.

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
        d2_rows, col_rows = _lower_envelope(g2[needed])
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
        config: pruning knobs; default :class:`SilhouetteConfig`.

    Returns:
        :math:`(B, 1, H, W)` bool, a subset of ``mask``.
    """
    config = SilhouetteConfig() if config is None else config
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
        config: :class:`SilhouetteConfig`.

    Returns:
        :class:`SilhouetteDistances`, float32 fields :math:`(B, 1, H, W)`.
    """
    config = SilhouetteConfig() if config is None else config
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
