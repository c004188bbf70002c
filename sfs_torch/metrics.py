"""Evaluation metrics of the paper's tables (SPEC "Metrics"): MAE, nMSE and lMSE.

All metrics are computed over the object pixels of each batch element separately, in
the dtype of the estimate, and without Python loops over pixels or batch elements.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict, List, Union

import torch
from torch import Tensor

from ._checks import check_finite, check_mask, check_same_size, check_shape, from_batch, is_integer, to_batch
from .lighting import render_sphere, sphere_normals

__all__ = ["angular_error", "NormalMetrics", "normal_metrics", "lmse"]

# Thresholds of the "share of pixels under t degrees" columns.
_THRESHOLDS = (11.25, 22.5, 30.0)


def _normal_pair(est: Tensor, gt: Tensor, mask: Tensor):
    """Validate ``est``, ``gt``, ``mask``; return them batched, the mask as bool, and ``was_single``."""
    est_b, single = to_batch(est, "est", 3)
    gt_b, _ = to_batch(gt, "gt", 3)
    mask_b, _ = to_batch(mask, "mask", 1)
    check_shape(est_b, "est", "B 3 H W")
    check_shape(gt_b, "gt", "B 3 H W")
    check_same_size(est_b, "est", gt_b, "gt")
    # A metric compares maps that may cover the whole frame, so a full mask is fine.
    mask_b = check_mask(mask_b, "mask", allow_full=True)
    if mask_b.shape[0] == 1:
        mask_b = mask_b.expand(est_b.shape[0], -1, -1, -1)
    check_same_size(est_b, "est", mask_b, "mask")
    check_finite(est_b, "est")
    check_finite(gt_b, "gt")
    dtype = torch.promote_types(est_b.dtype, gt_b.dtype)
    est_b, gt_b = est_b.to(dtype), gt_b.to(est_b.device, dtype)
    mask_b = mask_b.to(est_b.device)
    for x, name in ((est_b, "est"), (gt_b, "gt")):
        # A zero vector has no direction: its angle to anything would silently read as 0.
        zero = (x.abs().amax(1, keepdim=True) == 0) & mask_b
        if bool(zero.any()):
            raise ValueError(f"{name} has {int(zero.sum())} zero-length normal(s) inside the mask")
    return est_b, gt_b, mask_b, single


def _angle_deg(est: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    # Kahan's form 2 atan2(|a |b| - b |a||, |a |b| + b |a||) is accurate to a few ulps at
    # every angle, exactly 0 for equal directions and needs no normalisation, where acos
    # of the clamped dot product loses half the digits near 0 and 180 degrees.
    a = est * gt.norm(dim=1, keepdim=True)
    b = gt * est.norm(dim=1, keepdim=True)
    angle = 2 * torch.atan2((a - b).norm(dim=1, keepdim=True), (a + b).norm(dim=1, keepdim=True))
    return torch.where(mask, torch.rad2deg(angle), torch.zeros_like(angle))


def angular_error(est: Tensor, gt: Tensor, mask: Tensor) -> Tensor:
    r"""Angle between estimated and true normals, per pixel, in degrees.

    Args:
        est: estimated normals, :math:`(B, 3, H, W)` or :math:`(3, H, W)`; need not be unit
            length, but must be non-zero inside the mask.
        gt: true normals, same shape as ``est``.
        mask: object pixels, :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`, bool or
            {0, 1}; a single mask is shared by all batch elements.

    Returns:
        :math:`(B, 1, H, W)` (or :math:`(1, H, W)`) angles in :math:`[0, 180]` degrees, exactly 0
        outside the mask.

    Raises:
        ValueError: wrong shapes, sizes that differ, an empty mask, NaN/inf values, or a
            zero-length normal inside the mask.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
        >>> m = torch.tensor([0.0, 1.0, 1.0]).view(3, 1, 1)
        >>> angular_error(m, n, torch.ones(1, 1, 1, dtype=torch.bool)).flatten()
        tensor([45.])
    """
    est_b, gt_b, mask_b, single = _normal_pair(est, gt, mask)
    return from_batch(_angle_deg(est_b, gt_b, mask_b), single)


@dataclass(frozen=True)
class NormalMetrics:
    """Per-image normal accuracy, as in the paper's tables.

    Every field is a :math:`(B,)` tensor (a 0-dim tensor for unbatched input).

    Attributes:
        median: median angular error in degrees over object pixels (the paper's "MAE").
        mean: mean angular error in degrees.
        under_11_25: share of object pixels with an error below 11.25 degrees, in [0, 1].
        under_22_5: share below 22.5 degrees.
        under_30: share below 30 degrees.
        nmse: mean over object pixels of ``|n_est - n_gt|^2`` for unit normals
            (``= 2 - 2 cos(angle)``).
    """

    median: Tensor
    mean: Tensor
    under_11_25: Tensor
    under_22_5: Tensor
    under_30: Tensor
    nmse: Tensor

    def as_dict(self) -> Dict[str, Union[float, List[float]]]:
        """Plain Python numbers for JSON and tables: floats for one image, lists for a batch."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return {name: float(v) if v.numel() == 1 else v.tolist() for name, v in values.items()}


def normal_metrics(est: Tensor, gt: Tensor, mask: Tensor) -> NormalMetrics:
    r"""Angular-error statistics and nMSE of estimated normals over object pixels.

    The median of an even number of errors is the mean of the two middle values (as
    ``numpy.median``). Shares count errors strictly below each threshold. For nMSE both
    fields are first scaled to unit length, so it depends on the angle alone. Sums over
    half-precision maps are accumulated in float32; the fields keep the input's dtype.

    Args:
        est: estimated normals, :math:`(B, 3, H, W)` or :math:`(3, H, W)`.
        gt: true normals, same shape.
        mask: object pixels, :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`.

    Returns:
        :class:`NormalMetrics` with :math:`(B,)` fields (0-dim for unbatched input).

    Raises:
        ValueError: as :func:`angular_error`.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 2, 2)
        >>> normal_metrics(n, n, torch.ones(2, 2, dtype=torch.bool)).as_dict()["median"]
        0.0
    """
    est_b, gt_b, mask_b, single = _normal_pair(est, gt, mask)
    err = _angle_deg(est_b, gt_b, mask_b).flatten(1)
    inside = mask_b.flatten(1)
    count = inside.sum(1)
    # a float16 sum of errors overflows past 65504 degrees (a few thousand object pixels),
    # and bfloat16 rounds counts above 256: half precision is summed in float32
    acc = torch.promote_types(err.dtype, torch.float32)
    n = count.to(acc)

    # Background sorts last, so the object errors fill the first `count` slots.
    ranked = torch.where(inside, err, torch.full_like(err, float("inf"))).sort(1).values
    lower = ranked.gather(1, ((count - 1) // 2)[:, None])[:, 0]
    upper = ranked.gather(1, (count // 2)[:, None])[:, 0]
    shares = [((err < t) & inside).sum(1).to(acc) / n for t in _THRESHOLDS]

    unit_est = est_b / est_b.norm(dim=1, keepdim=True).clamp_min(torch.finfo(est_b.dtype).tiny)
    unit_gt = gt_b / gt_b.norm(dim=1, keepdim=True).clamp_min(torch.finfo(gt_b.dtype).tiny)
    sq = ((unit_est - unit_gt) ** 2).sum(1).flatten(1)
    nmse = torch.where(inside, sq, torch.zeros_like(sq)).sum(1, dtype=acc) / n

    values = [(lower + upper) / 2, err.sum(1, dtype=acc) / n, *shares, nmse]
    return NormalMetrics(*(from_batch(v.to(err.dtype), single) for v in values))


def lmse(est_sh: Tensor, gt_sh: Tensor, resolution: int = 64) -> Tensor:
    r"""Scale-invariant MSE between two SH lightings rendered on the visible hemisphere.

    Both lightings are rendered on an orthographic ``resolution x resolution`` image of a
    unit sphere (:func:`sfs_torch.lighting.render_sphere`); the estimate is multiplied by
    the single factor ``s`` (per batch element, shared by the three channels) minimising
    ``|s * est - gt|^2``, in closed form ``s = <est, gt> / <est, est>`` (0 when the estimate
    renders black); the result is the mean squared error over sphere pixels and channels.

    Args:
        est_sh: estimated lighting, :math:`(B, 3, 9)` or :math:`(3, 9)`.
        gt_sh: true lighting, same shape.
        resolution: side of the sphere image in pixels.

    Returns:
        :math:`(B,)` (0-dim for unbatched input), in squared intensity units.

    Raises:
        ValueError: wrong shapes, batch sizes that differ, NaN/inf values, or a
            resolution below 2.

    Example:
        >>> sh = torch.zeros(3, 9); sh[:, 0] = 1.0; sh[0, 2] = 0.5
        >>> float(lmse(2.0 * sh, sh))
        0.0
    """
    single = isinstance(est_sh, Tensor) and est_sh.ndim == 2
    est_b = est_sh[None] if single else est_sh
    gt_b = gt_sh[None] if isinstance(gt_sh, Tensor) and gt_sh.ndim == 2 else gt_sh
    check_shape(est_b, "est_sh", "B 3 9")
    check_shape(gt_b, "gt_sh", "B 3 9")
    if est_b.shape[0] != gt_b.shape[0]:
        raise ValueError(
            f"est_sh and gt_sh must have the same batch size, got {tuple(est_sh.shape)} and {tuple(gt_sh.shape)}"
        )
    check_finite(est_b, "est_sh")
    check_finite(gt_b, "gt_sh")
    if not is_integer(resolution, 2):
        raise ValueError(f"resolution must be an integer >= 2, got {resolution!r}")
    dtype = torch.promote_types(est_b.dtype, gt_b.dtype)
    est_b, gt_b = est_b.to(dtype), gt_b.to(est_b.device, dtype)

    # render_sphere is 0 outside the disk, so sums over the image are sums over the sphere.
    est_img = render_sphere(est_b, resolution)
    gt_img = render_sphere(gt_b, resolution)
    pixels = sphere_normals(resolution, device=est_b.device).mask.sum().to(dtype)

    num = (est_img * gt_img).sum((1, 2, 3))
    den = (est_img * est_img).sum((1, 2, 3))
    scale = torch.where(den > 0, num / den.clamp_min(torch.finfo(dtype).tiny), torch.zeros_like(den))
    sq = ((scale[:, None, None, None] * est_img - gt_img) ** 2).sum((1, 2, 3))
    err = sq / (3 * pixels)
    return err[0] if single else err
