"""Loaders for evaluation datasets already on disk: MIT-Berkeley, DiLiGenT and a plain folder.

Each loader turns a dataset a researcher has downloaded into :class:`~sfs_torch.datasets.Scene`
objects, so that the benchmarks score real cases exactly as they score synthetic ones. Nothing
here downloads anything. Every loader checks its root before reading any image and raises one
``FileNotFoundError`` naming the missing file or folder, or one ``ValueError`` naming the bad
file and value.

- :func:`load_mit_berkeley`: the MIT-Berkeley Intrinsic Images in the layout of Barron &
  Malik's SIRFS release; ground-truth normals from the height maps (:func:`height_to_normals`),
  the known lighting fitted to the image over them.
- :func:`load_diligent`: DiLiGenT's photometric-stereo objects, one case per object and light;
  the known lighting is that light's SH (:func:`directional_light_sh`); perspective camera.
- :func:`load_folder`: our own layout, one folder per case (``docs/dataset_loaders.md``).

The layouts, frame conversions and the definition of each known lighting are documented in
``docs/dataset_loaders.md``.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from ._checks import check_finite, check_mask, check_same_size, check_shape, from_batch, is_number, to_batch
from .datasets import Scene
from .integrability import depth_to_normals
from .io import read_image, read_lighting, read_mask, read_normals_npy, read_normals_png
from .lighting import fit_sh, irradiance_to_sh, sh_basis_vectors

__all__ = [
    "Intrinsics",
    "DILIGENT_INTRINSICS",
    "height_to_normals",
    "directional_light_sh",
    "read_intrinsics",
    "load_mit_berkeley",
    "load_diligent",
    "load_folder",
]

PathLike = Union[str, os.PathLike]

MIT_NATURAL = "MIT-Berkeley-Natural"
MIT_LABORATORY = "MIT-Berkeley-Laboratory"
DILIGENT_FILES = ("filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png", "Normal_gt.mat")
FOLDER_CAMERA_KEYS = ("focal", "principal_point")
# A ground-truth normal inside the mask must be this close to unit length (load_folder).
_UNIT_TOLERANCE = 0.05


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera in SPEC's conventions.

    Attributes:
        focal: focal length in pixels (the mean of ``fx`` and ``fy``).
        principal_point: ``(cx, cy)`` in pixels, measured from the image's top-left corner
            with pixel ``(i, j)`` centred at ``(j + 0.5, i + 0.5)`` (SPEC, :mod:`sfs_torch.camera`).
    """

    focal: float
    principal_point: Tuple[float, float]

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, name: str = "K") -> "Intrinsics":
        """From a 3x3 intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.

        The matrix follows OpenCV's convention (x along columns, pixel centres at integer
        coordinates from 0), so SPEC's principal point is ``(cx + 0.5, cy + 0.5)``.

        Raises:
            ValueError: not 3x3, NaN/inf, a non-positive focal length, ``fx`` and ``fy``
                more than 1% apart (the method assumes square pixels), a skew above
                ``1e-3 fx``, or a last row other than ``(0, 0, 1)``.
        """
        k = np.asarray(matrix, dtype=np.float64)
        if k.shape != (3, 3):
            raise ValueError(f"{name} must be a 3x3 intrinsic matrix, got shape {k.shape}")
        if not np.isfinite(k).all():
            raise ValueError(f"{name} holds NaN or infinite values: {k.tolist()}")
        fx, fy = float(k[0, 0]), float(k[1, 1])
        if not (fx > 0 and fy > 0):
            raise ValueError(f"{name} must have positive focal lengths, got fx={fx:g}, fy={fy:g}")
        if abs(fx - fy) > 0.01 * max(fx, fy):
            raise ValueError(f"{name} has fx={fx:g} and fy={fy:g} more than 1% apart; the method needs square pixels")
        if abs(k[0, 1]) > 1e-3 * fx or abs(k[1, 0]) > 1e-6 * fx:
            raise ValueError(f"{name} has a skew of {k[0, 1]:g} (or a non-zero K[1, 0]); the method needs none")
        if not np.allclose(k[2], (0.0, 0.0, 1.0)):
            raise ValueError(f"{name} must end in the row (0, 0, 1), got {k[2].tolist()}")
        return cls(0.5 * (fx + fy), (float(k[0, 2]) + 0.5, float(k[1, 2]) + 0.5))


# DiLiGenT's calibration as published with Bilateral Normal Integration (Cao et al., ECCV 2022,
# co-authored by DiLiGenT's author) for its 612x512 images: fx along columns, fy along rows,
# the principal point in OpenCV's convention (pot2's K.txt; pot1's differs by 0.75 px in cy).
_DILIGENT_K = np.array([[3772.077471010730, 0.0, 305.875], [0.0, 3759.005431071330, 255.125], [0.0, 0.0, 1.0]])
DILIGENT_INTRINSICS = Intrinsics.from_matrix(_DILIGENT_K, "DiLiGenT's published K")
# (H, W) of the images DILIGENT_INTRINSICS belongs to
_DILIGENT_SIZE = (512, 612)


def height_to_normals(height: Tensor, mask: Optional[Tensor] = None) -> Tensor:
    r"""Orthographic ground-truth normals of a height map, by finite differences.

    ``n = normalize(-dz/du, -dz/dv, 1)`` in SPEC's camera frame (x right, y up, z towards the
    viewer) with ``u`` along columns and ``v`` up, so ``dz/dv = -dz/d(row)``. The differences
    are those of :func:`sfs_torch.integrability.depth_to_normals` (central inside the object,
    second-order one-sided at its edge), so integrating the normals gives the height back.

    Args:
        height: :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)` height towards the
            viewer in pixels (larger is nearer); NaN or infinite outside the object.
        mask: optional object mask of the same size; the object is ``mask`` and finite height.

    Returns:
        :math:`(B, 3, H, W)` (no batch axis for unbatched input) unit normals, ``n_z > 0``,
        exactly 0 outside the object.

    Example:
        >>> j = torch.arange(4.0)
        >>> n = height_to_normals((0.5 * j).expand(3, 4))  # rises to the right
        >>> n[:, 1, 1].tolist()  # (-0.5, 0, 1) / |.|
        [-0.4472135901451111, 0.0, 0.8944271802902222]
    """
    h, single = to_batch(height, "height", 1)
    check_shape(h, "height", "B 1 H W")
    inside = torch.isfinite(h)
    if mask is not None:
        m, _ = to_batch(mask, "mask", 1)
        m = check_mask(m, "mask", allow_full=True, allow_empty=True)
        check_same_size(h, "height", m, "mask")
        inside = inside & m
    normals = depth_to_normals(torch.where(inside, h, torch.zeros_like(h)), inside)
    return from_batch(normals, single)


def directional_light_sh(
    direction: Union[Tensor, Sequence[float]], colour: Union[Tensor, Sequence[float], float] = 1.0
) -> Tensor:
    r"""SPEC SH lighting of one distant light: the 9-term approximation of ``colour * max(0, n . l)``.

    The clamped cosine ``max(0, n . l)`` has the SH coefficients ``A_l Y_k(l)`` (Funk-Hecke,
    with Ramamoorthi & Hanrahan's ``A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4``), so
    ``L[c, k] = colour_c A_l Y_k(l)``: :func:`~sfs_torch.lighting.irradiance_to_sh` of the
    radiance coefficients ``pi colour_c Y_k(l)``. Truncating to 9 terms costs a few percent:
    the shading peaks at ``1.0625 colour`` where ``n = l`` and is off by up to ~0.1 colour
    around the terminator (and slightly negative behind it).

    Args:
        direction: :math:`(*, 3)` direction towards the light in the camera frame (any
            length but 0; normalised here).
        colour: :math:`(*, 3)` RGB intensity, or a scalar for white light.

    Returns:
        :math:`(*, 3, 9)` SH coefficients in SPEC order (float32 unless ``direction`` is float64).

    Raises:
        ValueError: wrong shapes, NaN/inf, or a zero direction.

    Example:
        >>> from sfs_torch.lighting import render_sh
        >>> sh = directional_light_sh([0.0, 0.0, 1.0], [1.0, 1.0, 1.0])
        >>> n = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> round(float(render_sh(n, sh)[0, 0]), 4)
        1.0625
    """
    d = direction if isinstance(direction, Tensor) else torch.tensor(direction, dtype=torch.float32)
    if not d.is_floating_point():
        d = d.float()
    if d.ndim < 1 or d.shape[-1] != 3:
        raise ValueError(f"direction must have shape (*, 3), got {tuple(d.shape)}")
    check_finite(d, "direction")
    length = d.norm(dim=-1, keepdim=True)
    if bool((length <= 0).any()):
        raise ValueError("direction must not be the zero vector")
    c = colour if isinstance(colour, Tensor) else torch.tensor(colour, dtype=d.dtype)
    c = c.to(device=d.device, dtype=d.dtype)
    if c.ndim == 0:
        c = c.expand(3)
    if c.shape[-1] != 3:
        raise ValueError(f"colour must be a scalar or have shape (*, 3), got {tuple(c.shape)}")
    check_finite(c, "colour")
    radiance = math.pi * c[..., :, None] * sh_basis_vectors(d / length)[..., None, :]  # (*, 3, 9)
    return irradiance_to_sh(radiance)


def read_intrinsics(path: PathLike) -> Intrinsics:
    """Read a 3x3 intrinsic matrix from a text file (three rows of three numbers, e.g. ``K.txt``).

    See :meth:`Intrinsics.from_matrix` for the conventions and checks.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file does not hold a valid 3x3 matrix.
    """
    p = _existing(Path(path), "intrinsics file")
    try:
        matrix = np.loadtxt(p, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise ValueError(f"'{p}': expected a 3x3 matrix of numbers, got text NumPy cannot parse ({err})") from None
    return Intrinsics.from_matrix(matrix, f"the intrinsic matrix in '{p}'")


# ------------------------------------------------------------------------------------------
# MIT-Berkeley Intrinsic Images (SIRFS release)


def load_mit_berkeley(root: PathLike, *, objects: Optional[Sequence[str]] = None) -> List[Scene]:
    """The MIT-Berkeley Intrinsic Images under natural light, one case per object.

    Layout (Barron & Malik's SIRFS release; ``root`` may also be the release's top folder,
    which holds them under ``data/``)::

        root/MIT-Berkeley-Laboratory/<obj>/Z.mat          # 'depth': height, NaN off the object
        root/MIT-Berkeley-Laboratory/<obj>/mask.png       # used when Natural has none
        root/MIT-Berkeley-Natural/<obj>/shading_color.png # 16-bit, linear
        root/MIT-Berkeley-Natural/<obj>/mask.png          # optional

    - image: ``shading_color.png`` (uniform albedo under the object's natural light). 16-bit
      PNGs are taken as linear (as SIRFS reads them), 8-bit ones as sRGB; 0 off the mask.
    - mask: ``mask.png`` (Natural's, else Laboratory's) and finite ``depth``.
    - normals: :func:`height_to_normals` of ``depth`` (orthographic).
    - lighting and source_lighting: the known lighting, the least-squares SH fit
      (:func:`~sfs_torch.lighting.fit_sh`) of the image over the ground-truth normals on the
      mask. The release's own ``L.mat`` (SIRFS's SH convention) is not read.
    - focal: ``None``; name ``<obj>|natural``, lighting_name ``natural``.

    Args:
        root: the folder holding ``MIT-Berkeley-Laboratory`` and ``MIT-Berkeley-Natural``.
        objects: object names to load; default every folder in ``MIT-Berkeley-Natural``.

    Returns:
        one :class:`~sfs_torch.datasets.Scene` per object, in the order asked (default: sorted).

    Raises:
        FileNotFoundError: ``root``, a dataset folder, an object or one of its files is missing.
        ValueError: a file cannot be read (e.g. a MATLAB v7.3 ``Z.mat``), has no ``depth``, or
            its size disagrees with the image's; an object's mask is empty.
    """
    base = _existing_dir(Path(root), "MIT-Berkeley root")
    if not (base / MIT_NATURAL).is_dir() and (base / "data" / MIT_NATURAL).is_dir():
        base = base / "data"
    natural = _existing_dir(base / MIT_NATURAL, f"the {MIT_NATURAL} folder of the SIRFS release layout")
    laboratory = _existing_dir(base / MIT_LABORATORY, f"the {MIT_LABORATORY} folder of the SIRFS release layout")
    names = _choose(objects, _subfolders(natural), natural, "objects")
    cases = []
    for name in names:
        mask_path = natural / name / "mask.png"
        if not mask_path.is_file():
            mask_path = laboratory / name / "mask.png"
        if not mask_path.is_file():
            raise FileNotFoundError(
                f"MIT-Berkeley object '{name}' has no mask: neither '{natural / name / 'mask.png'}' nor '{mask_path}' exists"
            )
        cases.append((name, _existing(laboratory / name / "Z.mat", f"MIT-Berkeley object '{name}'"),
                      _existing(natural / name / "shading_color.png", f"MIT-Berkeley object '{name}'"), mask_path))
    return [_mit_scene(*case) for case in cases]


def _mit_scene(name: str, depth_path: Path, image_path: Path, mask_path: Path) -> Scene:
    depth = _mat_variable(depth_path, "depth")
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
        raise ValueError(
            f"'{depth_path}': 'depth' must be a numeric (H, W) height map, got {depth.dtype} of shape {depth.shape}"
        )
    image = read_image(image_path, srgb=_png_bit_depth(image_path) != 16)
    mask = read_mask(mask_path)
    _same_size(image_path, image, mask_path, mask)
    _same_size(image_path, image, depth_path, depth)
    height = torch.from_numpy(depth.astype(np.float64))[None, None]
    mask = mask[None] & torch.isfinite(height)
    if not bool(mask.any()):
        raise ValueError(
            f"MIT-Berkeley object '{name}': no pixel is inside '{mask_path}' with a finite depth in '{depth_path}'"
        )
    normals = height_to_normals(height, mask).float()
    image = image[None] * mask
    lighting = fit_sh(normals, image, mask)
    return Scene(f"{name}|natural", name, "natural", image, mask, normals, lighting, lighting.clone(), None)


# ------------------------------------------------------------------------------------------
# DiLiGenT


@dataclass(frozen=True)
class _DiligentObject:
    name: str
    folder: Path
    photographs: List[Path]
    directions: np.ndarray  # (N, 3)
    intensities: np.ndarray  # (N, 3)
    lights: List[int]
    camera: Optional[Intrinsics]


def load_diligent(
    root: PathLike,
    *,
    objects: Optional[Sequence[str]] = None,
    lights: Optional[Sequence[int]] = None,
    perspective: bool = True,
) -> Iterator[Scene]:
    """DiLiGenT's photometric-stereo objects, one case per object and light.

    Layout (the DiLiGenT release; ``root`` may also be ``pmsData`` itself)::

        root/pmsData/<obj>PNG/filenames.txt          # one photograph per light
        root/pmsData/<obj>PNG/light_directions.txt   # one "x y z" row per light
        root/pmsData/<obj>PNG/light_intensities.txt  # one "r g b" row per light
        root/pmsData/<obj>PNG/mask.png
        root/pmsData/<obj>PNG/Normal_gt.mat          # 'Normal_gt', (H, W, 3)
        root/pmsData/<obj>PNG/001.png ...            # 16-bit linear photographs
        root/pmsData/<obj>PNG/K.txt or root/pmsData/K.txt   # optional 3x3 intrinsics

    DiLiGenT's normals and light directions are in SPEC's frame already (x right, y up, z
    towards the camera), so they are used as they are.

    - image: the photograph (linear) divided by its light's RGB intensity, then by its
      maximum on the mask so that the case spans [0, 1]; 0 off the mask.
    - mask: ``mask.png`` where the ground-truth normal is finite and non-zero.
    - normals: ``Normal_gt`` normalised, 0 off the mask.
    - lighting and source_lighting: the known lighting, :func:`directional_light_sh` of the
      light's direction with the RGB colour that best fits (least squares over the mask) the
      image as ``colour * max(0, n . l)``: the direction and relative intensity come from the
      calibration, the scale (albedo over the normalisation) from the image.
    - focal and principal_point: from ``K.txt`` (:func:`read_intrinsics`) in the object's
      folder, else beside it in ``pmsData``, else :data:`DILIGENT_INTRINSICS` (the camera of
      the release's 612x512 images: an object of another size needs its ``K.txt``); ``None``
      with ``perspective=False``.
    - name ``<obj>|<photograph stem>``, shape ``<obj>``, lighting_name the photograph's stem.

    Args:
        root: the folder holding ``pmsData``.
        objects: object names (``"ball"`` or ``"ballPNG"``); default every ``*PNG`` folder.
        lights: 0-based light indices (rows of the light files); default all of them.
        perspective: use the camera's intrinsics; ``False`` loads orthographic cases.

    Returns:
        an iterator over the cases, object by object and light by light; files are
        checked before it is returned and each photograph is read when its case is reached.

    Raises:
        FileNotFoundError: ``root``, ``pmsData``, an object or one of its files is missing.
        ValueError: a light file is malformed or its row count disagrees with
            ``filenames.txt``, a light index is out of range, a light or object is given
            twice, an intrinsics file is bad, or an object without ``K.txt`` is not 612x512
            (with ``perspective=True``).
            Unreadable ``Normal_gt.mat`` files and size mismatches are reported (as
            ``ValueError``) when their object is reached.
    """
    base = _existing_dir(Path(root), "DiLiGenT root")
    data = base / "pmsData"
    if not data.is_dir() and any(base.glob("*PNG/filenames.txt")):
        data = base
    data = _existing_dir(data, "DiLiGenT's pmsData folder")
    available = [p.name[: -len("PNG")] for p in sorted(data.iterdir()) if p.is_dir() and p.name.endswith("PNG")]
    wanted = None
    if objects is not None:
        wanted = [o[: -len("PNG")] if isinstance(o, str) and o.endswith("PNG") else o for o in _as_list(objects, "objects")]
    names = _choose(wanted, available, data, "objects", suffix="PNG")
    plan = [_diligent_object(name, data, lights, perspective) for name in names]
    return _diligent_scenes(plan)


def _diligent_object(name: str, data: Path, lights: Optional[Sequence[int]], perspective: bool) -> _DiligentObject:
    folder = data / f"{name}PNG"
    what = f"DiLiGenT object '{name}'"
    for file in DILIGENT_FILES:
        _existing(folder / file, what)
    filenames = [line.strip() for line in (folder / "filenames.txt").read_text(encoding="utf-8").splitlines() if line.strip()]
    if not filenames:
        raise ValueError(f"'{folder / 'filenames.txt'}' lists no photograph")
    directions = _light_table(folder / "light_directions.txt", len(filenames))
    intensities = _light_table(folder / "light_intensities.txt", len(filenames))
    lengths = np.linalg.norm(directions, axis=1)
    if bool((lengths == 0).any()):
        raise ValueError(f"'{folder / 'light_directions.txt'}' holds a zero direction (row {int(np.argmin(lengths)) + 1})")
    if bool((intensities <= 0).any()):
        row = int(np.argwhere(intensities <= 0)[0, 0]) + 1
        raise ValueError(
            f"'{folder / 'light_intensities.txt'}' must hold positive intensities, row {row} is {intensities[row - 1].tolist()}"
        )
    chosen = list(range(len(filenames))) if lights is None else _light_indices(lights, len(filenames), folder)
    photographs = [folder / f for f in filenames]
    for index in chosen:
        _existing(photographs[index], f"{what}, light {index} (line {index + 1} of filenames.txt)")
    camera = None
    if perspective:
        k_path = next((p for p in (folder / "K.txt", data / "K.txt") if p.is_file()), None)
        camera = DILIGENT_INTRINSICS if k_path is None else read_intrinsics(k_path)
        if k_path is None:
            # the published camera is that of the release's images: on any other size its
            # principal point lies off centre or outside the image, silently
            size = tuple(read_mask(folder / "mask.png").shape[-2:])
            if size != _DILIGENT_SIZE:
                raise ValueError(
                    f"{what}: '{folder}' holds {size[1]}x{size[0]} images but has no K.txt, and DILIGENT_INTRINSICS "
                    f"are for DiLiGenT's {_DILIGENT_SIZE[1]}x{_DILIGENT_SIZE[0]} images: put this copy's K.txt in "
                    "the object's folder (or pmsData), or pass perspective=False"
                )
    return _DiligentObject(name, folder, photographs, directions, intensities, chosen, camera)


def _diligent_scenes(plan: List[_DiligentObject]) -> Iterator[Scene]:
    for obj in plan:
        mask_path, normals_path = obj.folder / "mask.png", obj.folder / "Normal_gt.mat"
        mask = read_mask(mask_path)
        gt = _mat_variable(normals_path, "Normal_gt")
        if gt.ndim != 3 or gt.shape[2] != 3 or not np.issubdtype(gt.dtype, np.floating):
            raise ValueError(
                f"'{normals_path}': 'Normal_gt' must be a float (H, W, 3) normal map, got {gt.dtype} of shape {gt.shape}"
            )
        _same_size(mask_path, mask, normals_path, gt)
        normals = torch.from_numpy(np.ascontiguousarray(gt.transpose(2, 0, 1), dtype=np.float64))[None]
        length = normals.norm(dim=1, keepdim=True)
        mask = mask[None] & torch.isfinite(length) & (length > 0.5)
        if not bool(mask.any()):
            raise ValueError(f"DiLiGenT object '{obj.name}': no pixel of '{mask_path}' has a valid normal in '{normals_path}'")
        normals = torch.where(mask, normals / torch.where(mask, length, torch.ones_like(length)), 0.0)
        n = normals[0].permute(1, 2, 0)[mask[0, 0]]  # (N, 3)
        normals = normals.float()
        focal = None if obj.camera is None else obj.camera.focal
        principal_point = None if obj.camera is None else obj.camera.principal_point
        for index in obj.lights:
            photo_path = obj.photographs[index]
            photo = read_image(photo_path, srgb=False).double()[None]
            _same_size(photo_path, photo, mask_path, mask)
            image = photo / torch.from_numpy(obj.intensities[index]).view(1, 3, 1, 1) * mask
            peak = float(image.max())
            image = image / (peak if peak > 0 else 1.0)
            direction = torch.from_numpy(obj.directions[index] / np.linalg.norm(obj.directions[index]))
            cosine = (n @ direction).clamp_min(0)  # (N,)
            colours = image[0].permute(1, 2, 0)[mask[0, 0]]  # (N, 3)
            denominator = float((cosine * cosine).sum())
            colour = (cosine @ colours) / denominator if denominator > 0 else torch.zeros(3, dtype=torch.float64)
            lighting = directional_light_sh(direction, colour).float()[None]
            stem = photo_path.stem
            yield Scene(f"{obj.name}|{stem}", obj.name, stem, image.float(), mask, normals, lighting,
                        lighting.clone(), focal, principal_point)


def _light_table(path: Path, rows: int) -> np.ndarray:
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise ValueError(f"'{path}': expected one row of 3 numbers per light, got text NumPy cannot parse ({err})") from None
    if table.shape != (rows, 3):
        raise ValueError(
            f"'{path}' must hold {rows} rows of 3 numbers (one per photograph in filenames.txt), got shape {table.shape}"
        )
    if not np.isfinite(table).all():
        raise ValueError(f"'{path}' holds NaN or infinite values")
    return table


def _light_indices(lights: Sequence[int], count: int, folder: Path) -> List[int]:
    chosen = []
    for i, index in enumerate(_as_list(lights, "lights")):
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise ValueError(f"lights[{i}] must be an integer light index, got {index!r}")
        if not 0 <= int(index) < count:
            raise ValueError(f"lights[{i}] = {index} is out of range: '{folder}' has {count} lights (indices 0 to {count - 1})")
        if int(index) in chosen:  # one case per light: a repeat would give two cases of one name
            raise ValueError(f"lights[{i}] = {index} repeats lights[{chosen.index(int(index))}]: give each light once")
        chosen.append(int(index))
    return chosen


# ------------------------------------------------------------------------------------------
# Plain folder layout


def load_folder(root: PathLike) -> List[Scene]:
    """Cases in our own plain layout, one folder per case (sorted by name)::

        root/<case>/image.png | image.npy   # PNG: sRGB (8 or 16 bit); .npy: float (H, W, 3) linear
        root/<case>/mask.png | mask.npy     # non-zero = object
        root/<case>/normals.npy | normals.png   # optional ground truth, SPEC frame
        root/<case>/lighting.json           # optional {"sh": [[9] x 3]} (SPEC basis)
        root/<case>/camera.json             # optional {"focal": f, "principal_point": [cx, cy]}

    - image: 0 off the mask. normals: as stored (unit to within 5%) and normalised, 0 off
      the mask.
    - lighting and source_lighting: ``lighting.json``; without it, the least-squares SH fit of
      the image over the ground-truth normals (as for MIT-Berkeley); without either, ``None``.
      lighting_name is ``given``, ``fitted`` or ``unknown`` accordingly.
    - focal and principal_point: from ``camera.json`` (either may be ``null`` or left out;
      the principal point in SPEC's convention, as :func:`sfs_torch.estimate` takes it);
      default orthographic, image centre.
    - name and shape: the folder's name. Cases without normals have ``normals=None``.

    Folders whose name starts with ``.`` or ``_`` are ignored.

    Raises:
        FileNotFoundError: ``root`` is missing, or a case has no image or mask.
        ValueError: ``root`` holds no case; a case holds both forms of a file, a file is
            malformed, sizes disagree, the mask is empty or a normal off unit length.
    """
    base = _existing_dir(Path(root), "dataset folder")
    folders = [p for p in sorted(base.iterdir()) if p.is_dir() and not p.name.startswith((".", "_"))]
    if not folders:
        raise ValueError(f"dataset folder '{base}' holds no case folder (expected '{base}/<case>/image.png' and mask.png)")
    plan = []
    for folder in folders:
        image = _one_of(folder, ("image.png", "image.npy"), required=True)
        mask = _one_of(folder, ("mask.png", "mask.npy"), required=True)
        normals = _one_of(folder, ("normals.npy", "normals.png"), required=False)
        lighting, camera = folder / "lighting.json", folder / "camera.json"
        plan.append((folder, image, mask, normals, lighting if lighting.is_file() else None,
                     camera if camera.is_file() else None))
    return [_folder_scene(*case) for case in plan]


def _folder_scene(folder: Path, image_path: Path, mask_path: Path, normals_path: Optional[Path],
                  lighting_path: Optional[Path], camera_path: Optional[Path]) -> Scene:
    image = read_image(image_path)  # PNG as sRGB, .npy as linear
    mask = read_mask(mask_path)
    _same_size(image_path, image, mask_path, mask)
    if not bool(mask.any()):
        raise ValueError(f"'{mask_path}' is empty: no object pixel")
    mask = mask[None]
    image = image[None] * mask
    normals = None
    if normals_path is not None:
        n = read_normals_npy(normals_path) if normals_path.suffix == ".npy" else read_normals_png(normals_path)
        _same_size(normals_path, n, image_path, image)
        length = n.norm(dim=0)[mask[0, 0]]
        off = int(((length - 1).abs() > _UNIT_TOLERANCE).sum())
        if off:
            raise ValueError(
                f"'{normals_path}': {off} object pixels of '{mask_path}' have a normal off unit length by more "
                f"than {_UNIT_TOLERANCE}"
            )
        normals = torch.where(mask, n[None] / n.norm(dim=0).clamp_min(1e-12), 0.0).float()
    if lighting_path is not None:
        lighting, lighting_name = read_lighting(lighting_path)[None], "given"
    elif normals is not None:
        lighting, lighting_name = fit_sh(normals, image, mask), "fitted"
    else:
        lighting, lighting_name = None, "unknown"
    focal, principal_point = _read_camera_json(camera_path) if camera_path is not None else (None, None)
    source = None if lighting is None else lighting.clone()
    return Scene(folder.name, folder.name, lighting_name, image, mask, normals, lighting, source, focal, principal_point)


def _read_camera_json(path: Path) -> Tuple[Optional[float], Optional[Tuple[float, float]]]:
    expected = 'JSON {"focal": <pixels> or null, "principal_point": [cx, cy] or null}'
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"'{path}': expected {expected}, got a file that is not valid JSON ({err})") from None
    if not isinstance(content, dict):
        raise ValueError(f"'{path}': expected {expected}, got a {type(content).__name__}")
    unknown = sorted(set(content) - set(FOLDER_CAMERA_KEYS))
    if unknown:
        raise ValueError(f"'{path}': unknown keys {unknown}; expected {expected}")
    focal = content.get("focal")
    if focal is not None:
        if not is_number(focal, 0, strict=True):
            raise ValueError(f"'{path}': focal must be a positive number of pixels or null, got {focal!r}")
        focal = float(focal)
    point = content.get("principal_point")
    if point is not None:
        if not isinstance(point, list) or len(point) != 2 or not all(is_number(v) for v in point):
            raise ValueError(f"'{path}': principal_point must be [cx, cy] (two numbers, pixels) or null, got {point!r}")
        point = (float(point[0]), float(point[1]))
    return focal, point


# ------------------------------------------------------------------------------------------
# Shared helpers


def _existing(path: Path, what: str) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{what}: missing file '{path}'")
    return path


def _existing_dir(path: Path, what: str) -> Path:
    if not path.exists():
        raise FileNotFoundError(f"{what}: no such folder '{path}'")
    if not path.is_dir():
        raise ValueError(f"{what} must be a folder, got the file '{path}'")
    return path


def _subfolders(path: Path) -> List[str]:
    return [p.name for p in sorted(path.iterdir()) if p.is_dir() and not p.name.startswith(".")]


def _as_list(values, name: str) -> list:
    if isinstance(values, (str, bytes)):
        return [values]
    try:
        return list(values)
    except TypeError:
        raise ValueError(f"{name} must be a list, got {type(values).__name__}") from None


def _choose(wanted: Optional[Sequence[str]], available: List[str], folder: Path, name: str, suffix: str = "") -> List[str]:
    if wanted is None:
        if not available:
            raise ValueError(f"'{folder}' holds no object folder")
        return available
    chosen = _as_list(wanted, name)
    for i, item in enumerate(chosen):
        if item not in available:
            raise FileNotFoundError(
                f"{name}: no object '{item}' (folder '{folder / (str(item) + suffix)}'); "
                f"available: {', '.join(available) or 'none'}"
            )
        if item in chosen[:i]:  # one object's cases twice, under the same names
            raise ValueError(f"{name}[{i}] names the object '{item}' again ({name}[{chosen.index(item)}]): give each once")
    return chosen


def _one_of(folder: Path, names: Sequence[str], required: bool) -> Optional[Path]:
    found = [folder / n for n in names if (folder / n).is_file()]
    if len(found) > 1:
        raise ValueError(f"case '{folder}' holds both {found[0].name} and {found[1].name}: keep one")
    if not found and required:
        raise FileNotFoundError(f"case '{folder}': missing file '{folder / names[0]}' (or {', '.join(names[1:])})")
    return found[0] if found else None


def _same_size(a_path: Path, a, b_path: Path, b) -> None:
    # tensors are (..., H, W); arrays (H, W, ...)
    size_a = tuple(a.shape[-2:]) if isinstance(a, Tensor) else tuple(a.shape[:2])
    size_b = tuple(b.shape[-2:]) if isinstance(b, Tensor) else tuple(b.shape[:2])
    if size_a != size_b:
        raise ValueError(f"'{a_path}' is {size_a} (H, W) but '{b_path}' is {size_b}: they must have the same size")


def _mat_variable(path: Path, variable: str) -> np.ndarray:
    """One variable of a MATLAB (v4 to v7) .mat file, via scipy."""
    from scipy.io import loadmat, whosmat

    try:
        content = loadmat(path, variable_names=[variable])
    except NotImplementedError:
        raise ValueError(
            f"'{path}' is a MATLAB v7.3 (HDF5) .mat file, which scipy cannot read: re-save it in an older "
            f"format (in MATLAB: s = load(file); save(file, '-struct', 's', '-v7'))"
        ) from None
    except Exception as err:  # scipy raises many types on malformed files
        raise ValueError(f"'{path}': not a MATLAB .mat file scipy can read ({type(err).__name__}: {err})") from None
    if variable not in content:
        held = [entry[0] for entry in whosmat(path)]
        raise ValueError(f"'{path}' holds no variable '{variable}' (it holds: {', '.join(held) or 'nothing'})")
    return np.asarray(content[variable])


def _png_bit_depth(path: Path) -> Optional[int]:
    """The bit depth in a PNG's header, ``None`` for other files."""
    with open(path, "rb") as f:
        head = f.read(25)
    if len(head) < 25 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24]
