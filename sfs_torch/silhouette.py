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

import torch
import torch.nn.functional as F
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
    """

    prune_distance: float = 3.0
    prune_angle: float = 60.0


def _mask_argument(mask: Tensor, name: str, allow_empty: bool) -> Tuple[Tensor, bool]:
    mask, single = to_batch(mask, name, 1)
    if allow_empty:
        if mask.ndim != 4 or mask.shape[1] != 1:
            raise ValueError(f"{name} must have shape (B, 1, H, W), got {tuple(mask.shape)}")
        if mask.dtype != torch.bool:
            if mask.is_complex() or not bool(((mask == 0) | (mask == 1)).all()):
                raise ValueError(f"{name} must be boolean or hold only 0 and 1 (dtype {mask.dtype})")
            mask = mask != 0
        return mask, single
    return check_mask(mask, name), single


def _edt_squared(foreground: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Squared EDT and feature transform of ``(B, H, W)`` bool ``foreground``.

    Two exact 1-D passes: along columns the nearest background row (running max / min of
    background indices), then along rows ``d^2(j) = min_k g(k)^2 + (j - k)^2``. The row
    pass visits offsets ``o = 1, 2, ...`` only for the pixels whose current best still
    exceeds ``o^2``, so its work is the sum of the distances, not ``W`` per pixel.

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
    above = torch.where(background, rows, torch.full_like(rows, -big)).cummax(1).values
    below = torch.where(background, rows, torch.full_like(rows, 2 * big)).flip(1).cummin(1).values.flip(1)
    take_above = (rows - above) <= (below - rows)
    feat_row = torch.where(take_above, above, below)
    g = (feat_row - rows).abs()
    no_background = g >= big
    g2 = torch.where(no_background, torch.full(g.shape, math.inf, device=device), g.float().square())

    g2 = g2.reshape(-1)
    best = g2.clone()
    best_col = torch.arange(w, device=device).repeat(b * h)
    idx = torch.nonzero(best > 1.0).flatten()
    col = idx % w
    offset = 1
    while idx.numel() > 0:
        cur = best[idx]
        cur_col = best_col[idx]
        o2 = float(offset * offset)
        for sign in (-1, 1):
            k = col + sign * offset
            valid = (k >= 0) & (k < w)
            cand = torch.where(valid, g2[(idx + sign * offset).clamp(0, g2.numel() - 1)] + o2, math.inf)
            better = cand < cur
            cur = torch.where(better, cand, cur)
            cur_col = torch.where(better, k, cur_col)
        best[idx] = cur
        best_col[idx] = cur_col
        offset += 1
        keep = cur > float(offset * offset)
        idx, col = idx[keep], col[keep]

    best = best.view(b, h, w)
    best_col = best_col.view(b, h, w)
    row_base = (torch.arange(b * h, device=device) * w).view(b, h, 1)
    feat_row = feat_row.reshape(-1)[(row_base + best_col).reshape(-1)].view(b, h, w)
    return best, feat_row, best_col


def euclidean_distance_transform(mask: Tensor) -> Tensor:
    r"""Exact Euclidean distance of every True pixel to the nearest False pixel.

    Matches ``scipy.ndimage.distance_transform_edt``: distances between pixel centres,
    0 on False pixels, and pixels beyond the image border are *not* background. A batch
    element without any False pixel gets ``inf`` everywhere.

    Args:
        mask: :math:`(B, 1, H, W)` (or :math:`(H, W)`, :math:`(1, H, W)`) bool or 0/1.

    Returns:
        :math:`(B, 1, H, W)` float32 distances in pixels (same leading shape as ``mask``).

    Example:
        >>> m = torch.zeros(1, 1, 5, 5, dtype=torch.bool); m[..., 1:4, 1:4] = True
        >>> euclidean_distance_transform(m)[0, 0, 2]
        tensor([0., 1., 2., 1., 0.])
    """
    batch, single = _mask_argument(mask, "mask", allow_empty=True)
    dist2, _, _ = _edt_squared(batch[:, 0])
    return from_batch(dist2.sqrt()[:, None], single)


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
    # every object keeps at least its deepest point, so d_M stays finite after pruning
    deepest = torch.where(foreground, dist2, -1.0).flatten(1).argmax(1)
    axis.view(b, -1)[torch.arange(b, device=device), deepest] = True
    return axis


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
    foreground: Tensor, d_rel: Tensor, depth: Tensor, feat_row: Tensor, feat_col: Tensor
) -> Tensor:
    """``beta`` of Eq. 7 for ``(B, H, W)`` maps, with the feature transform as fallback."""
    b, h, w = foreground.shape
    x = d_rel[:, None]
    # Sobel in image axes; rows grow downwards, y grows upwards
    kernel = torch.tensor([1.0, 2.0, 1.0], device=x.device, dtype=x.dtype)
    diff = torch.tensor([-1.0, 0.0, 1.0], device=x.device, dtype=x.dtype)
    kx = (kernel[:, None] * diff[None, :] / 8.0).view(1, 1, 3, 3)
    padded = F.pad(x, (1, 1, 1, 1), mode="replicate")
    grad_col = F.conv2d(padded, kx)[:, 0]
    grad_row = F.conv2d(padded, kx.transpose(-1, -2))[:, 0]
    gx, gy = -grad_col, grad_row  # -grad(d_rel) in (x right, y up)
    # d_rel falls by about 1 / depth per pixel; much less means the stencil straddles
    # the medial axis, where the gradient is undefined: point at the nearest contour pixel
    weak = (gx * gx + gy * gy) * depth * depth < 0.25
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
            :math:`(1, H, W)` or :math:`(H, W)` mask gives fields without ``B``.
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
    d_medial = torch.where(fg, _edt_squared(~axis)[0].sqrt(), 0.0)
    depth = d_boundary + d_medial
    d_rel = torch.where(fg, d_boundary / depth.clamp_min(1e-6), 0.0)
    beta = _direction_to_contour(fg, d_rel, depth, feat_row, feat_col)
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
