"""Shaded previews of meshes (the novel view), by pyrender's OpenGL rasteriser or the Embree ray caster.

The training database's normals are always ray cast (:func:`sfs_torch.rendering.render_normals`:
float normals, binary masks, exact depth). A preview only has to look right, so it may be
drawn by `pyrender <https://pyrender.readthedocs.io>`_ instead, where an offscreen OpenGL
context can be made (EGL, or OSMesa): the renderer ``"auto"`` takes pyrender then and falls
back to the ray caster otherwise (pyrender not installed, no EGL/OSMesa library, a context
that fails to start or to draw a test triangle). Both draw the same camera (framing as in
:mod:`sfs_torch.rendering`) and shade the normals with the same SH code
(:func:`sfs_torch.lighting.render_sh`); they differ in how a pixel's normal is found:

- ``"embree"``: one ray through the pixel centre, the barycentric interpolation of the vertex
  normals at the hit (float64).
- ``"pyrender"``: the same interpolation per fragment (:file:`sfs_torch/data/normals.frag`),
  4x multisampled and stored in an 8-bit colour buffer; a pixel is in the mask when at least
  2 of its 4 samples hit. Normals are thus quantised (~0.2 deg) and the rim follows coverage
  rather than the centre sample. Measured against the ray caster: ``benchmarks/renderers.py``,
  ``docs/rendering.md``.

pyrender needs ``PYOPENGL_PLATFORM`` before OpenGL is first imported: when it is unset, the
first use sets it to ``egl`` (or ``osmesa`` where only libOSMesa exists). The context is made
once per process and reused.
"""
from __future__ import annotations

import ctypes.util
import importlib.util
import os
import sys
import threading
from dataclasses import dataclass
from importlib import resources
from typing import Any, Dict, List, Optional, Union

import numpy as np
import torch
import trimesh
from torch import Tensor

from ._checks import check_finite
from .lighting import render_sh, rotate_sh
from .rendering import _check_mesh, _check_view, render_normals

__all__ = [
    "RENDERERS",
    "GLContext",
    "RendererChoice",
    "RasterNormals",
    "ShadedView",
    "gl_context",
    "renderer_name",
    "choose_renderer",
    "rasterize_normals",
    "render_shaded",
]

RENDERERS = ("auto", "pyrender", "embree")
_INSTALL = "pip install 'sfs-torch[render]'"


@dataclass(frozen=True)
class GLContext:
    """Whether pyrender can draw offscreen in this process.

    Attributes:
        available: a context was made and drew the test triangle correctly.
        platform: ``PYOPENGL_PLATFORM`` (``"egl"``, ``"osmesa"``), ``None`` if none was tried.
        device: the OpenGL renderer string (e.g. ``"llvmpipe (LLVM 15.0.6, 256 bits)"``, Mesa's
            software rasteriser), ``None`` when unavailable.
        reason: why no context is available, in one line; ``""`` when available.
    """

    available: bool
    platform: Optional[str] = None
    device: Optional[str] = None
    reason: str = ""


@dataclass(frozen=True)
class RendererChoice:
    """The renderer a request resolves to.

    Attributes:
        name: ``"pyrender"`` or ``"embree"``.
        requested: what was asked for (one of :data:`RENDERERS`).
        reason: one line saying what was chosen and why (e.g. the missing context of a fallback).
    """

    name: str
    requested: str
    reason: str


@dataclass(frozen=True)
class RasterNormals:
    """One view rasterised by pyrender.

    Attributes:
        normals: :math:`(3, H, W)` float32 camera-frame unit normals, 0 outside the mask.
        mask: :math:`(1, H, W)` bool, pixels at least half covered (2 of 4 samples).
        coverage: :math:`(1, H, W)` float32 in [0, 1], the covered fraction of each pixel.
    """

    normals: Tensor
    mask: Tensor
    coverage: Tensor


@dataclass(frozen=True)
class ShadedView:
    """A shaded preview.

    Attributes:
        image: :math:`(3, H, W)` float32 linear RGB in [0, 1], ``background`` outside the mask.
        normals: :math:`(3, H, W)` float32 camera-frame unit normals, 0 outside the mask.
        mask: :math:`(1, H, W)` bool.
        renderer: ``"pyrender"`` or ``"embree"``, the one that drew it.
    """

    image: Tensor
    normals: Tensor
    mask: Tensor
    renderer: str


# One offscreen context per process, made on first use (a forked child of a process that
# made one gets none).
_LOCK = threading.RLock()
_STATE: Dict[str, Any] = {}
_INHERITED: List[Any] = []


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split()) or "no message"
    return f"{type(err).__name__}: {text}"[:300]


def _platform() -> Optional[str]:
    """``PYOPENGL_PLATFORM``, set to ``egl`` or ``osmesa`` when unset and a library is found."""
    chosen = os.environ.get("PYOPENGL_PLATFORM")
    if chosen or "OpenGL" in sys.modules:
        return chosen or None  # too late to choose: PyOpenGL fixed its platform on import
    for name, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            os.environ["PYOPENGL_PLATFORM"] = name
            return name
    return None


def _probe() -> GLContext:
    """Make the offscreen context and check it on one triangle; never raises."""
    if importlib.util.find_spec("pyrender") is None:
        return GLContext(False, reason=f"pyrender is not installed ({_INSTALL})")
    platform = _platform()
    if platform is None:
        if "OpenGL" in sys.modules:
            return GLContext(False, reason="PyOpenGL was imported before PYOPENGL_PLATFORM was set (set it to egl first)")
        return GLContext(False, reason="no libEGL or libOSMesa found (e.g. apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)")
    if platform not in ("egl", "osmesa"):
        return GLContext(False, platform, reason=f"PYOPENGL_PLATFORM={platform!r}: offscreen rendering needs egl or osmesa")
    try:
        import pyrender
        from OpenGL import GL
        from pyrender.shader_program import ShaderProgramCache

        class NormalShaders(ShaderProgramCache):
            """Every program pyrender asks for (only FLAT renders are made) is ours."""

            def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
                return super().get_program("normals.vert", "normals.frag", None, defines)

        renderer = pyrender.OffscreenRenderer(8, 8)
        renderer._renderer._program_cache = NormalShaders(str(resources.files("sfs_torch") / "data"))
        renderer._platform.make_current()
        device = GL.glGetString(GL.GL_RENDERER)
        device = device.decode(errors="replace") if isinstance(device, bytes) else str(device)
        _STATE["renderer"] = renderer
        triangle = trimesh.Trimesh([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]], [[0, 1, 2]], process=False)
        test = _rasterize(triangle, np.eye(3), 8, focal=None, distance=3.0, scale=0.9)
    except Exception as err:  # any failure of a driver, a library or pyrender means: no context
        _STATE.pop("renderer", None)
        return GLContext(False, platform, reason=f"no OpenGL context on {platform}: {_one_line(err)}")
    centre = test.normals[:, 4, 4]
    if not (bool(test.mask[0, 4, 4]) and not bool(test.mask[0, 0, 0]) and float(centre[2]) > 0.99):
        _STATE.pop("renderer", None)
        return GLContext(False, platform, device, reason=f"the OpenGL context on {platform} ({device}) drew the test triangle wrongly")
    return GLContext(True, platform, device)


def gl_context() -> GLContext:
    """Whether pyrender can render here: made (and checked) once per process, then cached.

    Returns:
        :class:`GLContext`; ``reason`` says why not. Never raises.
    """
    with _LOCK:
        if _STATE.get("pid") != os.getpid():  # first call, or a forked child: a context is per process
            inherited = _STATE.pop("renderer", None)
            parent = _STATE.get("context")
            _STATE.clear()
            _STATE["pid"] = os.getpid()
            if inherited is None:
                _STATE["context"] = _probe()
            else:
                # A forked child of a process holding a context can neither use it nor make
                # one (Mesa's EGL deadlocks): the ray caster draws here. Never delete the
                # parent's context from the child either.
                _INHERITED.append(inherited)
                _STATE["context"] = GLContext(
                    False, parent.platform, None,
                    reason="this process was forked from one holding an OpenGL context, which a child cannot use or remake",
                )
        return _STATE["context"]


def renderer_name(requested: Any, key: str = "renderer") -> str:
    """``requested`` as one of :data:`RENDERERS`, or a ``ValueError`` naming ``key`` (the option it came from)."""
    if not isinstance(requested, str) or requested.lower() not in RENDERERS:
        raise ValueError(f"{key} must be one of {', '.join(RENDERERS)}, got {requested!r}")
    return requested.lower()


def choose_renderer(requested: str = "auto", context: Optional[GLContext] = None, *,
                    key: str = "renderer") -> RendererChoice:
    """Resolve a renderer request.

    ``"embree"`` is always available; ``"pyrender"`` needs a context; ``"auto"`` takes pyrender
    where a context exists and the ray caster otherwise.

    Args:
        requested: one of :data:`RENDERERS` (case-insensitive).
        context: the OpenGL status to decide on; ``None`` asks :func:`gl_context` (only for
            ``"auto"`` and ``"pyrender"``: it makes the context, ~1 s the first time).
        key: the option ``requested`` came from, named in the errors (``novel_view.renderer``
            in the CLI).

    Returns:
        :class:`RendererChoice`.

    Raises:
        ValueError: an unknown name, or ``"pyrender"`` where no context can be made.

    Example:
        >>> choose_renderer("auto", GLContext(False, reason="pyrender is not installed")).name
        'embree'
    """
    name = renderer_name(requested, key)
    if name == "embree":
        return RendererChoice("embree", name, "embree: the Embree ray caster, as requested")
    context = gl_context() if context is None else context
    if context.available:
        return RendererChoice("pyrender", name, f"pyrender: OpenGL on {context.platform} ({context.device})")
    if name == "pyrender":
        raise ValueError(
            f"{key}=pyrender needs an offscreen OpenGL context, but {context.reason}; use {key}=auto "
            "(falls back to the Embree ray caster) or embree (docs/rendering.md)"
        )
    return RendererChoice("embree", name, f"embree: the Embree ray caster; pyrender unavailable ({context.reason})")


def _rasterize(mesh: trimesh.Trimesh, rot: np.ndarray, resolution: int, *, focal: Optional[float],
               distance: float, scale: float) -> RasterNormals:
    """Draw with the process's renderer (held by the caller's lock, or during the probe)."""
    import pyrender

    renderer = _STATE["renderer"]
    vertices = np.asarray(mesh.vertices, np.float64)
    radius = float(np.linalg.norm(vertices, axis=1).max()) if len(vertices) else 1.0
    primitive = pyrender.Primitive(
        positions=vertices.astype(np.float32), normals=np.asarray(mesh.vertex_normals, np.float32),
        indices=np.asarray(mesh.faces, np.uint32), mode=pyrender.constants.GLTF.TRIANGLES,
        material=pyrender.MetallicRoughnessMaterial(),
    )
    scene = pyrender.Scene(bg_color=[0.5, 0.5, 0.5, 0.0], ambient_light=[0.0, 0.0, 0.0])
    pose = np.eye(4)
    pose[:3, :3] = rot  # the mesh node turns world into camera coordinates
    scene.add(pyrender.Mesh([primitive]), pose=pose)
    # what the rays see: in front of the camera (z < distance), out to the far side of the mesh
    far = distance + radius + 1e-3 * max(distance, radius) + 1e-6
    near = max(0.5 * (distance - radius), 1e-4 * far) if focal is not None else 1e-6 * far
    if focal is None:
        camera = pyrender.OrthographicCamera(xmag=1.0 / scale, ymag=1.0 / scale, znear=near, zfar=far)
    else:
        camera = pyrender.IntrinsicsCamera(focal, focal, resolution / 2.0, resolution / 2.0, znear=near, zfar=far)
    camera_pose = np.eye(4)
    camera_pose[2, 3] = distance
    scene.add(camera, pose=camera_pose)
    renderer.viewport_width = renderer.viewport_height = int(resolution)
    flags = pyrender.RenderFlags.FLAT | pyrender.RenderFlags.RGBA | pyrender.RenderFlags.SKIP_CULL_FACES
    color, _ = renderer.render(scene, flags=flags)
    rgba = np.asarray(color, np.float32) / 255.0
    coverage = rgba[..., 3]
    mask = coverage >= 0.5
    normals = 2.0 * rgba[..., :3] - 1.0  # the mean of the covered samples' normals, times the coverage
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    mask &= length[..., 0] > 1e-6
    normals = np.where(mask[..., None], normals / np.maximum(length, 1e-12), 0.0)
    return RasterNormals(
        normals=torch.from_numpy(np.ascontiguousarray(normals.transpose(2, 0, 1), dtype=np.float32)),
        mask=torch.from_numpy(np.ascontiguousarray(mask[None])),
        coverage=torch.from_numpy(np.ascontiguousarray(coverage[None])),
    )


def rasterize_normals(
    mesh: trimesh.Trimesh,
    rotation: Union[Tensor, np.ndarray],
    resolution: int,
    *,
    focal: Optional[float] = None,
    distance: Optional[float] = None,
    scale: float = 0.9,
) -> RasterNormals:
    r"""Rasterise the camera-frame normal map of a mesh with pyrender (OpenGL).

    The camera, framing and normal convention are those of
    :func:`sfs_torch.rendering.render_normals`; the normals are 8-bit quantised and the
    mask follows 4x multisampled coverage (module docstring).

    Args:
        mesh: triangle mesh; its ``vertex_normals`` are interpolated.
        rotation: :math:`(3, 3)` world-to-camera rotation.
        resolution: image height and width in pixels.
        focal: focal length in pixels for a perspective camera; ``None`` for orthographic.
        distance: camera-centre distance from the world origin (default as ``render_normals``).
        scale: radius of the unit sphere in the image, as a fraction of ``resolution / 2``.

    Returns:
        :class:`RasterNormals` with ``(3, R, R)`` normals, ``(1, R, R)`` mask and coverage.

    Raises:
        ValueError: a bad rotation, resolution, focal, distance or scale; a mesh without faces;
            no OpenGL context (:func:`gl_context` says why).
    """
    _check_mesh(mesh)
    rot, distance = _check_view(rotation, resolution, focal, distance, scale)
    with _LOCK:
        context = gl_context()
        if not context.available:
            raise ValueError(f"rasterize_normals needs an offscreen OpenGL context, but {context.reason}")
        return _rasterize(mesh, rot, resolution, focal=focal, distance=distance, scale=scale)


def _check_mesh_and_lighting(mesh: trimesh.Trimesh, lighting: Tensor) -> None:
    """The ``mesh`` and ``lighting`` arguments of :func:`render_shaded` and
    :func:`sfs_torch.novel_view.render_novel_view`."""
    if not isinstance(lighting, Tensor) or tuple(lighting.shape) != (3, 9):
        got = tuple(lighting.shape) if isinstance(lighting, Tensor) else type(lighting).__name__
        raise ValueError(f"lighting must be a (3, 9) tensor, got {got}")
    # NaN or inf would shade every pixel NaN
    check_finite(lighting, "lighting")
    _check_mesh(mesh)


def render_shaded(
    mesh: trimesh.Trimesh,
    lighting: Tensor,
    rotation: Union[Tensor, np.ndarray],
    resolution: int,
    *,
    renderer: str = "auto",
    focal: Optional[float] = None,
    distance: Optional[float] = None,
    scale: float = 0.9,
    background: float = 1.0,
) -> ShadedView:
    r"""A shaded preview of a mesh: its normals from a viewpoint, shaded with an SH lighting.

    Args:
        mesh: triangle mesh, normally within the unit sphere (:func:`sfs_torch.shapes.normalize_mesh`).
        lighting: :math:`(3, 9)` SH lighting in the mesh's (world) frame; it is turned into the
            camera frame with the view (:func:`sfs_torch.lighting.rotate_sh`).
        rotation: :math:`(3, 3)` world-to-camera rotation.
        resolution: image height and width in pixels.
        renderer: ``"auto"``, ``"pyrender"`` or ``"embree"`` (:func:`choose_renderer`).
        focal: focal length in pixels for a perspective camera; ``None`` for orthographic.
        distance: camera-centre distance from the world origin (default as ``render_normals``).
        scale: radius of the unit sphere in the image, as a fraction of ``resolution / 2``.
        background: grey level of pixels that miss the surface.

    Returns:
        :class:`ShadedView`; ``renderer`` names the renderer that drew it.

    Raises:
        TypeError: ``mesh`` is not a ``trimesh.Trimesh`` (a ``trimesh.Scene`` included).
        ValueError: bad arguments (NaN or inf in ``lighting`` included), an unknown
            renderer, or ``"pyrender"`` without a context.

    Example:
        >>> from sfs_torch.lighting import natural_lightings
        >>> sphere = trimesh.creation.icosphere(subdivisions=3)
        >>> view = render_shaded(sphere, natural_lightings()["uffizi_gallery"], torch.eye(3), 32, renderer="embree")
        >>> view.image.shape, view.renderer, bool(view.mask[0, 16, 16])
        (torch.Size([3, 32, 32]), 'embree', True)
    """
    _check_mesh_and_lighting(mesh, lighting)
    rot, distance = _check_view(rotation, resolution, focal, distance, scale)
    name = choose_renderer(renderer).name
    if name == "pyrender":
        view = rasterize_normals(mesh, rot, resolution, focal=focal, distance=distance, scale=scale)
    else:
        view = render_normals(mesh, rot, resolution, focal=focal, distance=distance, scale=scale)
    # A normal n in the world frame appears as R n in the camera's: light it alike.
    sh = rotate_sh(lighting.detach().cpu().to(torch.float64), torch.from_numpy(rot)).float()
    shaded = render_sh(view.normals[None], sh[None])[0].clamp(0, 1)
    image = torch.where(view.mask, shaded, torch.full_like(shaded, float(background)))
    return ShadedView(image=image, normals=view.normals, mask=view.mask, renderer=name)
