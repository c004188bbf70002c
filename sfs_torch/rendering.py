"""Exact normal-map rendering of meshes by ray casting (paper Sec. 4).

Each pixel centre casts one ray (trimesh + Embree); the normal at the hit is the
barycentric interpolation of the mesh's vertex normals (smooth shading), rotated into
the camera frame (SPEC: x right, y up, z towards the viewer) and flipped where it faces
away from the camera (meshes with broken winding, or back faces seen through holes).
Unlike a rasteriser this gives float normals without quantisation, no anti-aliased rim
pixels and exact depth, for orthographic and perspective cameras alike: the training
database is always ray cast. Previews (the novel view) may be rasterised by pyrender
instead, with the same camera (:mod:`sfs_torch.preview`).

Framing: the world origin projects to the image centre. Orthographic: the unit sphere
(the bounding sphere of a normalised mesh) has a radius of ``scale * resolution / 2``
pixels. Perspective: the camera sits at ``distance`` on the view axis, by default at the
distance where the unit sphere's outline has that same radius.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple, Union

import numpy as np
import torch
import trimesh
from torch import Tensor

from ._checks import is_number
from .camera import _positive_focal, pixel_grid

__all__ = ["NormalRender", "render_normals", "random_view_rotations", "camera_distance"]


@dataclass(frozen=True)
class NormalRender:
    """One rendered view.

    Attributes:
        normals: :math:`(3, H, W)` float32 camera-frame unit normals, 0 outside the mask.
        mask: :math:`(1, H, W)` bool, pixels whose ray hits the mesh.
        depth: :math:`(1, H, W)` float32 distance from the camera centre along the view
            axis (``-z``), in mesh units; 0 outside the mask.
        points: :math:`(3, H, W)` float64 hit points in the mesh's own (world) frame, 0
            outside the mask: where :mod:`sfs_torch.image_formation` casts shadow rays from.
    """

    normals: Tensor
    mask: Tensor
    depth: Tensor
    points: Tensor


def camera_distance(resolution: int, focal: float, scale: float) -> float:
    """Distance at which a perspective camera sees the unit sphere with radius ``scale * resolution / 2`` px.

    A sphere of radius 1 at distance ``d`` subtends a cone of half-angle ``asin(1 / d)``;
    its outline has radius ``f tan(asin(1 / d))`` pixels.
    """
    half = scale * resolution / 2.0
    return 1.0 / math.sin(math.atan(half / focal))


def _check_view(
    rotation: Union[Tensor, np.ndarray], resolution: int, focal: Optional[float], distance: Optional[float], scale: float
) -> Tuple[np.ndarray, float]:
    """Validate a view's arguments (shared with :mod:`sfs_torch.preview`); return the rotation and the distance."""
    rot = np.asarray(rotation.detach().cpu() if isinstance(rotation, Tensor) else rotation, dtype=np.float64)
    if rot.shape != (3, 3) or not np.isfinite(rot).all():
        raise ValueError(f"rotation must be a finite (3, 3) matrix, got shape {rot.shape}")
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0:
        raise ValueError("rotation must be a proper rotation matrix (R R^T = I, det R = 1)")
    if not (isinstance(resolution, (int, np.integer)) and resolution > 0):
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    if focal is not None:
        _positive_focal(focal)  # inf would make camera_distance divide by zero
    if not is_number(scale, 0.0, strict=True):
        raise ValueError(f"scale must be a finite positive number, got {scale!r}")
    if distance is None:
        distance = 3.0 if focal is None else camera_distance(resolution, focal, scale)
    # From inside the unit sphere the mesh is normalised into, rays start within the object
    # and hit back faces; from infinitely far, nothing (orthographic rays start at the camera)
    if not is_number(distance, 1.0, strict=True):
        raise ValueError(f"distance must be a finite number > 1 (outside the unit sphere), got {distance!r}")
    return rot, float(distance)


def _check_mesh(mesh: trimesh.Trimesh) -> None:
    """The ``mesh`` argument of a renderer: a ``trimesh.Trimesh`` with faces."""
    if not isinstance(mesh, trimesh.Trimesh):
        # trimesh.load returns a Scene for .glb files, the format write_mesh writes
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__} (for a trimesh.Scene, pass "
                        "scene.to_mesh() or load the file with trimesh.load_mesh)")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces to render")


def render_normals(
    mesh: trimesh.Trimesh,
    rotation: Union[Tensor, np.ndarray],
    resolution: int,
    *,
    focal: Optional[float] = None,
    distance: Optional[float] = None,
    scale: float = 0.9,
) -> NormalRender:
    r"""Render the normal map, mask and depth of a mesh seen from one viewpoint.

    Args:
        mesh: triangle mesh, normally normalised to the unit bounding sphere
            (:func:`sfs_torch.shapes.normalize_mesh`); its ``vertex_normals`` are interpolated.
        rotation: :math:`(3, 3)` world-to-camera rotation: camera coordinates are
            ``x_cam = R x_world`` (+ the camera offset along z).
        resolution: image height and width in pixels.
        focal: focal length in pixels for a perspective camera; ``None`` for orthographic.
        distance: camera-centre distance from the world origin along the view axis, in
            mesh units, finite and > 1 (outside the unit sphere). Default: 3 for
            orthographic (it only offsets the depth), :func:`camera_distance` for perspective.
        scale: radius of the unit sphere in the image, as a fraction of ``resolution / 2``;
            finite and positive.

    Returns:
        :class:`NormalRender` with ``(3, R, R)`` normals, ``(1, R, R)`` mask and depth.

    Raises:
        TypeError: ``mesh`` is not a ``trimesh.Trimesh`` (a ``trimesh.Scene`` included).
        ValueError: a mesh without faces, or a bad rotation, resolution, focal, distance or scale.

    Example:
        >>> sphere = trimesh.creation.icosphere(subdivisions=3)
        >>> r = render_normals(sphere, torch.eye(3), 32)
        >>> r.normals.shape, bool(r.mask[0, 16, 16]), round(float(r.normals[2, 16, 16]), 2)
        (torch.Size([3, 32, 32]), True, 1.0)
    """
    _check_mesh(mesh)
    rot, distance = _check_view(rotation, resolution, focal, distance, scale)
    uv = pixel_grid(resolution, resolution, dtype=torch.float64).flatten(1).T.numpy()  # (R*R, 2)
    n_pix = uv.shape[0]
    if focal is None:
        pixel = scale * resolution / 2.0  # pixels per mesh unit
        origins = np.column_stack([uv / pixel, np.full(n_pix, distance)])
        directions = np.tile([0.0, 0.0, -1.0], (n_pix, 1))
    else:
        origins = np.tile([0.0, 0.0, distance], (n_pix, 1))
        directions = np.column_stack([uv, np.full(n_pix, -float(focal))])
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    # Camera frame -> world frame is R^T (row vectors: x @ R). mesh.ray is Embree when
    # embreex is installed (~20x faster), else trimesh's numpy intersector.
    locations, index_ray, index_tri = mesh.ray.intersects_location(
        origins @ rot, directions @ rot, multiple_hits=False
    )

    normals = np.zeros((n_pix, 3), np.float64)
    depth = np.zeros(n_pix, np.float64)
    points = np.zeros((n_pix, 3), np.float64)
    hit = np.zeros(n_pix, bool)
    if len(index_ray):
        tri = np.asarray(mesh.faces)[index_tri]
        bary = trimesh.triangles.points_to_barycentric(np.asarray(mesh.vertices)[tri], locations)
        world = np.einsum("nk,nkc->nc", bary, np.asarray(mesh.vertex_normals)[tri])
        cam_normal = world @ rot.T
        cam_point = locations @ rot.T
        # Facing the camera: n . (camera centre - point) > 0; for orthographic, n_z > 0.
        view = np.array([0.0, 0.0, 1.0]) if focal is None else np.array([0.0, 0.0, distance]) - cam_point
        facing = np.einsum("nc,nc->n", cam_normal, np.broadcast_to(view, cam_normal.shape))
        cam_normal *= np.where(facing < 0, -1.0, 1.0)[:, None]
        length = np.linalg.norm(cam_normal, axis=1, keepdims=True)
        good = length[:, 0] > 1e-12  # opposite vertex normals can cancel on razor-thin parts
        normals[index_ray[good]] = cam_normal[good] / length[good]
        depth[index_ray[good]] = distance - cam_point[good, 2]
        points[index_ray[good]] = locations[good]
        hit[index_ray[good]] = True
    return NormalRender(
        normals=torch.from_numpy(normals.T.reshape(3, resolution, resolution).astype(np.float32)),
        mask=torch.from_numpy(hit.reshape(1, resolution, resolution)),
        depth=torch.from_numpy(depth.reshape(1, resolution, resolution).astype(np.float32)),
        points=torch.from_numpy(np.ascontiguousarray(points.T.reshape(3, resolution, resolution))),
    )


def random_view_rotations(n: int, generator: torch.Generator) -> Tensor:
    """Uniformly random world-to-camera rotations (uniform viewpoints and roll).

    Normalised 4D Gaussian vectors are uniform unit quaternions, hence Haar-uniform
    rotations; the viewing direction (third row) is then uniform on the sphere.

    Args:
        n: number of rotations.
        generator: the source of randomness.

    Returns:
        :math:`(n, 3, 3)` float64 rotation matrices.
    """
    if n < 0:
        raise ValueError(f"n must be non-negative, got {n}")
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    w, x, y, z = (q / q.norm(dim=1, keepdim=True)).unbind(1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        1,
    ).reshape(n, 3, 3)
