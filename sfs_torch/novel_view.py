"""The recovered surface seen from a new viewpoint, shaded with the estimated lighting
(the paper's Fig. 1, right).

The depth map's mesh is centred, scaled to the unit bounding sphere and ray cast from a
camera turned by ``azimuth`` about the vertical axis and tilted by ``elevation``
(:func:`sfs_torch.rendering.render_normals`), then shaded with the lighting expressed
in that camera's frame.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import trimesh
from torch import Tensor

from .lighting import render_sh, rotate_sh
from .rendering import render_normals

__all__ = ["view_rotation", "render_novel_view"]


def view_rotation(azimuth_deg: float, elevation_deg: float) -> Tensor:
    """World-to-camera rotation of a camera orbiting the original one.

    Returns:
        :math:`(3, 3)` float64: a turn of ``azimuth`` about the y axis, then a tilt of
        ``elevation`` about the x axis (positive looks from above).
    """
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    turn = torch.tensor([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]], dtype=torch.float64)
    tilt = torch.tensor([[1, 0, 0], [0, math.cos(e), -math.sin(e)], [0, math.sin(e), math.cos(e)]], dtype=torch.float64)
    return tilt @ turn


def render_novel_view(
    mesh: trimesh.Trimesh,
    lighting: Tensor,
    *,
    azimuth_deg: float = 35.0,
    elevation_deg: float = 20.0,
    resolution: int = 256,
    background: float = 1.0,
) -> Tensor:
    """Shade a camera-frame surface mesh from a novel viewpoint.

    Args:
        mesh: surface in the original camera frame (e.g. :func:`sfs_torch.integrability.depth_to_mesh`).
        lighting: :math:`(3, 9)` SH lighting in the original camera frame.
        azimuth_deg: the new viewpoint's azimuth in degrees.
        elevation_deg: the new viewpoint's elevation in degrees.
        resolution: output size in pixels.
        background: grey level of pixels that miss the surface.

    Returns:
        :math:`(3, R, R)` linear RGB in [0, 1].
    """
    if lighting.shape != (3, 9):
        raise ValueError(f"lighting must have shape (3, 9), got {tuple(lighting.shape)}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces to render")
    unit = mesh.copy()
    lo, hi = unit.bounds
    unit.apply_translation(-(lo + hi) / 2)
    unit.apply_scale(1.0 / max(float(np.linalg.norm(unit.vertices, axis=1).max()), 1e-12))
    rotation = view_rotation(azimuth_deg, elevation_deg)
    view = render_normals(unit, rotation, resolution)
    # A normal n in the original frame appears as R n in the new one: light it alike.
    sh = rotate_sh(lighting.to(torch.float64), rotation).float()
    shaded = render_sh(view.normals[None], sh[None])[0].clamp(0, 1)
    return torch.where(view.mask, shaded, torch.full_like(shaded, background))
