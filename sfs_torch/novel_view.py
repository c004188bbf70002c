"""The recovered surface seen from a new viewpoint, shaded with the estimated lighting
(the paper's Fig. 1, right).

The depth map's mesh is centred, scaled to the unit bounding sphere and drawn from a
camera turned by ``azimuth`` about the vertical axis and tilted by ``elevation``, then
shaded with the lighting expressed in that camera's frame
(:func:`sfs_torch.preview.render_shaded`): by pyrender's OpenGL rasteriser where an
offscreen context exists, else by the Embree ray caster (``renderer``; ``docs/rendering.md``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from .preview import _check_mesh_and_lighting, render_shaded

__all__ = ["NovelViewConfig", "view_rotation", "render_novel_view"]


@dataclass
class NovelViewConfig:
    """The command's ``novel_view.png`` (written with a depth map, ``integrate=...``).

    Attributes:
        renderer: ``auto`` (pyrender where an offscreen OpenGL context exists, else the
            Embree ray caster), ``pyrender`` or ``embree`` (:func:`sfs_torch.preview.choose_renderer`).
        azimuth_deg: the viewpoint's turn about the vertical axis, degrees.
        elevation_deg: its tilt, degrees (positive looks from above).
        resolution: image size in pixels.
    """

    renderer: str = "auto"
    azimuth_deg: float = 35.0
    elevation_deg: float = 20.0
    resolution: int = 256


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
    renderer: str = "auto",
) -> Tensor:
    """Shade a camera-frame surface mesh from a novel viewpoint.

    Args:
        mesh: surface in the original camera frame (e.g. :func:`sfs_torch.integrability.depth_to_mesh`).
        lighting: :math:`(3, 9)` SH lighting in the original camera frame.
        azimuth_deg: the new viewpoint's azimuth in degrees.
        elevation_deg: the new viewpoint's elevation in degrees.
        resolution: output size in pixels.
        background: grey level of pixels that miss the surface.
        renderer: ``"auto"``, ``"pyrender"`` or ``"embree"`` (:func:`sfs_torch.preview.choose_renderer`).

    Returns:
        :math:`(3, R, R)` linear RGB in [0, 1].

    Raises:
        TypeError: ``mesh`` is not a ``trimesh.Trimesh``: a ``trimesh.Scene`` (what
            ``trimesh.load`` returns for a ``.glb``) is refused, ``scene.to_mesh()`` is one.
        ValueError: a bad lighting (NaN or inf included), an empty mesh, an unknown
            renderer, or ``"pyrender"`` where no OpenGL context can be made.
    """
    _check_mesh_and_lighting(mesh, lighting)
    unit = mesh.copy()
    lo, hi = unit.bounds
    unit.apply_translation(-(lo + hi) / 2)
    unit.apply_scale(1.0 / max(float(np.linalg.norm(unit.vertices, axis=1).max()), 1e-12))
    rotation = view_rotation(azimuth_deg, elevation_deg)
    return render_shaded(unit, lighting, rotation, resolution, renderer=renderer, background=background).image
