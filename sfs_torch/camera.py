"""Camera conventions: the pixel grid and the perspective normal rotation (paper Sec. 8).

Camera frame (SPEC): x to the right, y up, z towards the viewer. Pixel row ``i`` and
column ``j`` sit at ``u = j + 0.5 - cx`` and ``v = cy - (i + 0.5)``; the default
principal point is the image centre ``(W / 2, H / 2)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from ._checks import check_mask, check_shape, from_batch, to_batch

__all__ = [
    "CameraConfig",
    "CameraRotation",
    "pixel_grid",
    "perspective_rotation",
    "rotate_normals_to_camera",
    "centroid_rotation",
]


@dataclass
class CameraConfig:
    """Pinhole camera; ``focal=None`` means orthographic projection.

    Attributes:
        focal: focal length in pixels, or ``None`` for an orthographic camera.
        principal_point: ``(cx, cy)`` in pixels; ``None`` for the image centre.

    How :func:`sfs_torch.estimate` turns the forest's normals into this camera's frame
    is the pipeline's ``normal_rotation`` (:class:`sfs_torch.pipeline.PipelineConfig`).
    """

    focal: Optional[float] = None
    principal_point: Optional[Tuple[float, float]] = None


def _positive_focal(focal) -> float:
    """``focal`` as a float, or ``ValueError`` unless it is a finite positive number."""
    # float() would also read the string "50" (or True): a focal length must be a number
    if isinstance(focal, (str, bytes, bool)):
        raise ValueError(f"focal must be a positive focal length in pixels, got {focal!r}")
    try:
        value = float(focal)
    except (TypeError, ValueError):
        raise ValueError(f"focal must be a positive focal length in pixels, got {focal!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"focal must be a positive focal length in pixels, got {focal!r}")
    return value


def _check_camera(
    focal, principal_point, orthographic: bool = True
) -> Tuple[Optional[float], Optional[Tuple[float, float]]]:
    """The camera arguments of a public function, checked and as floats.

    ``focal``: a finite positive number, or ``None`` (orthographic) where ``orthographic``
    allows it; ``principal_point``: ``None`` or two finite numbers ``(cx, cy)``.

    Raises:
        ValueError: naming ``focal`` or ``principal_point`` and showing what came.
    """
    if focal is not None or not orthographic:
        focal = _positive_focal(focal)
    if principal_point is not None:
        try:
            point = () if isinstance(principal_point, (str, bytes)) else tuple(float(c) for c in principal_point)
        except (TypeError, ValueError):
            point = ()
        if len(point) != 2 or not all(math.isfinite(c) for c in point):
            raise ValueError(f"principal_point must be two finite numbers (cx, cy) in pixels, got {principal_point!r}")
        principal_point = point
    return focal, principal_point


def pixel_grid(
    height: int,
    width: int,
    principal_point: Optional[Sequence[float]] = None,
    *,
    device: Optional[torch.device] = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Image-plane coordinates ``(u, v)`` of every pixel centre.

    Args:
        height: image height in pixels.
        width: image width in pixels.
        principal_point: ``(cx, cy)`` in pixels; default ``(width / 2, height / 2)``.

    Returns:
        :math:`(2, H, W)` tensor: ``u`` (right) and ``v`` (up) in pixels.
    """
    cx, cy = (width / 2.0, height / 2.0) if principal_point is None else (float(principal_point[0]), float(principal_point[1]))
    j = torch.arange(width, device=device, dtype=dtype) + 0.5 - cx
    i = cy - (torch.arange(height, device=device, dtype=dtype) + 0.5)
    v, u = torch.meshgrid(i, j, indexing="ij")
    return torch.stack([u, v])


def perspective_rotation(u: Tensor, v: Tensor, focal: float) -> Tensor:
    r"""Rotation :math:`R_d` of Sec. 8 for image-plane points ``(u, v)``.

    It maps ``(0, 0, 1)`` exactly to the unit direction from the surface point towards
    the camera centre, ``(-u, -v, f) / |(-u, -v, f)|``, and never rolls the image: a
    horizontal vector stays horizontal. It rotates first about the x axis by ``theta``
    and then about the y axis by ``phi = atan(u / f)``. The paper writes
    ``theta = atan(v / f)``; we use the exact ``theta = atan(v / sqrt(u^2 + f^2))``,
    which agrees with it to first order in the field of view and makes the mapping
    exact off the image axes too.

    Args:
        u: image-plane coordinate (right) in pixels, any shape ``(*)``.
        v: image-plane coordinate (up) in pixels, the shape of ``u``.
        focal: focal length in pixels.

    Returns:
        rotation matrices of shape :math:`(*, 3, 3)`.
    """
    focal = _positive_focal(focal)
    phi = torch.atan(u / focal)
    theta = torch.atan(v / torch.sqrt(u * u + focal * focal))
    cp, sp, ct, st = torch.cos(phi), torch.sin(phi), torch.cos(theta), torch.sin(theta)
    zero, one = torch.zeros_like(u), torch.ones_like(u)
    rot_y = torch.stack([cp, zero, -sp, zero, one, zero, sp, zero, cp], -1).unflatten(-1, (3, 3))
    rot_x = torch.stack([one, zero, zero, zero, ct, -st, zero, st, ct], -1).unflatten(-1, (3, 3))
    return rot_y @ rot_x


def rotate_normals_to_camera(
    normals: Tensor, focal: float, principal_point: Optional[Sequence[float]] = None
) -> Tensor:
    """Rotate orthographic-frame normals by each pixel's perspective rotation (Sec. 8).

    Args:
        normals: :math:`(B, 3, H, W)` (or :math:`(3, H, W)`) normals predicted as if the
            camera were orthographic.
        focal: focal length in pixels.
        principal_point: ``(cx, cy)``; default image centre.

    Returns:
        :math:`(B, 3, H, W)` (or :math:`(3, H, W)`) normals in the perspective camera
        frame; zero pixels stay zero.

    Raises:
        ValueError: ``normals`` is not :math:`(B, 3, H, W)` floating point, ``focal`` is
            not a finite positive number or ``principal_point`` not two finite numbers.
    """
    batch, single = to_batch(normals, "normals", 3)
    check_shape(batch, "normals", "B 3 H W")
    focal, principal_point = _check_camera(focal, principal_point, orthographic=False)
    _, _, h, w = batch.shape
    uv = pixel_grid(h, w, principal_point, device=batch.device, dtype=batch.dtype)
    rot = perspective_rotation(uv[0], uv[1], focal)  # (H, W, 3, 3)
    return from_batch(torch.einsum("hwij,bjhw->bihw", rot, batch), single)


def centroid_rotation(mask: Tensor, focal: float, principal_point: Optional[Sequence[float]] = None) -> Tensor:
    """The single rotation of Sec. 8 for each object's centroid on the image plane.

    Args:
        mask: :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`, bool or 0/1, none
            empty.
        focal: focal length in pixels.
        principal_point: ``(cx, cy)``; default image centre.

    Returns:
        :math:`(B, 3, 3)` rotations (:math:`(3, 3)` for an unbatched mask).

    Raises:
        ValueError: a bad mask (shape, values, empty), ``focal`` or ``principal_point``.
    """
    mask, single = to_batch(mask, "mask", 1)
    mask = check_mask(mask, allow_full=True)
    focal, principal_point = _check_camera(focal, principal_point, orthographic=False)
    _, _, h, w = mask.shape
    uv = pixel_grid(h, w, principal_point, device=mask.device, dtype=torch.float32)
    m = mask[:, 0].float()
    count = m.flatten(1).sum(1)
    u = (uv[0] * m).flatten(1).sum(1) / count
    v = (uv[1] * m).flatten(1).sum(1) / count
    return from_batch(perspective_rotation(u, v, focal), single)


class CameraRotation(nn.Module):
    """Rotate orthographic-frame normals into a perspective camera's frame, per pixel
    (module form of :func:`rotate_normals_to_camera`, paper Sec. 8).

    Stores the camera; the per-pixel rotations depend on the input's size, so they are
    built in ``forward`` on the input's device and dtype (no buffer).

    Args:
        focal: focal length in pixels (positive).
        principal_point: ``(cx, cy)`` in pixels; default the image centre.

    ``forward(normals)``: :math:`(B, 3, H, W)` (or :math:`(3, H, W)`) normals; returns the
    same shape.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); n[:, 2] = 1
        >>> CameraRotation(100.0)(n).shape
        torch.Size([1, 3, 2, 2])
    """

    def __init__(self, focal: float, principal_point: Optional[Sequence[float]] = None):
        super().__init__()
        self.focal, self.principal_point = _check_camera(focal, principal_point, orthographic=False)

    def forward(self, normals: Tensor) -> Tensor:
        return rotate_normals_to_camera(normals, self.focal, self.principal_point)

    def extra_repr(self) -> str:
        return f"focal={self.focal}, principal_point={self.principal_point}"
