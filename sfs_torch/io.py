"""Reading and writing images, masks, normal maps and SH lighting files.

Everything that touches the file system or NumPy lives here, so that the operations
stay pure tensor functions. Files follow SPEC: images are PNG (8 or 16 bit, sRGB
unless told otherwise), JPEG, or ``.npy`` float ``(H, W, 3)`` linear RGB; masks are
PNG (non-zero = object), the alpha channel of an RGBA PNG, or ``.npy``; normals are
``.npy`` ``(H, W, 3)`` float32 or a 16-bit PNG; lighting is JSON ``{"sh": [[9] x 3]}``;
depth maps are a 16-bit PNG plus the scale and offset that decode it; meshes are PLY, OBJ
or glTF binary (GLB) with per-vertex normals, written through trimesh.

PNG and JPEG go through OpenCV, which keeps 16-bit samples (PIL and imageio's defaults
drop them to 8 bits); its BGR(A) channel order is turned into RGB(A) here.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

import cv2
import numpy as np
import torch
from torch import Tensor

from ._checks import check_finite, check_mask, check_shape

__all__ = [
    "ImageAndMask",
    "srgb_to_linear",
    "linear_to_srgb",
    "read_image",
    "read_mask",
    "read_image_and_mask",
    "write_image",
    "write_normals_png",
    "read_normals_png",
    "write_normals_npy",
    "read_normals_npy",
    "read_lighting",
    "write_lighting",
    "DepthAndMask",
    "write_depth_png",
    "read_depth_png",
    "MESH_FORMATS",
    "write_mesh",
]

PathLike = Union[str, os.PathLike]

_IMAGE_FORMATS = "an 8- or 16-bit PNG, a JPEG, or a float .npy of shape (H, W, 3) or (H, W)"
_MASK_FORMATS = (
    "a PNG (non-zero = object, RGBA: alpha > 0), a JPEG (brighter than mid-grey = object) or a .npy of shape (H, W) or (1, H, W)"
)
# 16-bit normal-map code of a component n in [-1, 1]: round(32767 n + 32768), so that
# n = 0 (the background) is the exact code 32768 and decodes to exactly 0.
_NORMAL_ZERO = 32768.0
_NORMAL_STEP = 32767.0
# 16-bit depth PNG: code 0 is the background, codes 1..65535 span [min, max] of the depth
# over the mask, so that depth = scale * code + offset on the mask.
_DEPTH_CODES = 65534.0
# mesh file formats of write_mesh, by file suffix
MESH_FORMATS = ("ply", "obj", "glb")


@dataclass(frozen=True)
class DepthAndMask:
    """A depth map and the mask it is defined on, as read by :func:`read_depth_png`.

    Attributes:
        depth: :math:`(1, H, W)` float32, 0 outside the mask.
        mask: :math:`(1, H, W)` bool, True where the file holds a depth (code > 0).
    """

    depth: Tensor
    mask: Tensor


@dataclass(frozen=True)
class ImageAndMask:
    """An image and its object mask, as read from disk.

    Attributes:
        image: :math:`(3, H, W)` float32 linear RGB in [0, 1].
        mask: :math:`(1, H, W)` bool, True on the object.
    """

    image: Tensor
    mask: Tensor


_SCALE_CODES = "divide 8-bit codes by 255 (16-bit ones by 65535) first"


def _check_floating(x: Tensor, what: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"x must be a torch.Tensor of {what}, got {type(x).__name__}")
    # integer codes would run through the curve unscaled (code 255 decodes to 5e5)
    if not x.is_floating_point():
        raise ValueError(f"x must be a floating-point tensor of {what}, got {x.dtype}: {_SCALE_CODES}")


def srgb_to_linear(x: Tensor) -> Tensor:
    """Decode sRGB values (IEC 61966-2-1) to linear RGB, elementwise, any shape.

    Args:
        x: floating-point sRGB values in [0, 1] (a file's codes divided by their maximum).

    Returns:
        linear values in [0, 1], shape and dtype of ``x``.

    Raises:
        TypeError: ``x`` is not a tensor.
        ValueError: ``x`` is not floating point, or holds values outside [0, 1].

    Example:
        >>> srgb_to_linear(torch.tensor([0.0, 0.5, 1.0]))
        tensor([0.0000, 0.2140, 1.0000])
    """
    _check_floating(x, "sRGB values in [0, 1]")
    if x.numel():
        low, high = float(x.min()), float(x.max())
        # codes converted to float but not scaled, the usual mistake, lie far above 1
        if low < 0 or high > 1:
            raise ValueError(f"x must hold sRGB values in [0, 1], got values in [{low:g}, {high:g}]: {_SCALE_CODES}")
    # Elementwise (unlike kornia.color's (*, 3, H, W) versions) so grey maps work too;
    # the clamp keeps the unused branch of torch.where free of NaN.
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Tensor) -> Tensor:
    """Encode linear RGB values as sRGB (IEC 61966-2-1), elementwise, any shape.

    Args:
        x: floating-point linear values; [0, 1] encodes to [0, 1], values outside it
            follow the curve's extension (clamp first to write a file).

    Returns:
        sRGB values, shape and dtype of ``x``.

    Raises:
        TypeError: ``x`` is not a tensor.
        ValueError: ``x`` is not floating point.

    Example:
        >>> linear_to_srgb(torch.tensor([0.0, 0.214041, 1.0]))
        tensor([0.0000, 0.5000, 1.0000])
    """
    _check_floating(x, "linear values")
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def _existing_file(path: PathLike, name: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{name}: no such file: '{p}'")
    if not p.is_file():
        raise ValueError(f"{name} must be a file, got the directory '{p}'")
    return p


def _bad(name: str, path: Path, expected: str, got: str) -> ValueError:
    return ValueError(f"{name} '{path}': expected {expected}, got {got}")


def _decode_raster(path: Path, name: str, expected: str) -> np.ndarray:
    """Decode a PNG/JPEG into ``(H, W)`` grey or ``(H, W, 3|4)`` RGB(A), uint8 or uint16."""
    # imdecode on the bytes (rather than imread) also handles non-ASCII paths.
    data = np.fromfile(path, dtype=np.uint8)
    # IMREAD_UNCHANGED keeps 16-bit PNG samples but ignores a JPEG's EXIF orientation;
    # JPEGs are 8-bit, so they are decoded upright as viewers show them (and masks drawn on them).
    flags = cv2.IMREAD_ANYCOLOR if path.suffix.lower() in (".jpg", ".jpeg") else cv2.IMREAD_UNCHANGED
    array = cv2.imdecode(data, flags) if data.size else None
    if array is None:
        raise _bad(name, path, expected, "a file OpenCV cannot decode as an image")
    if array.dtype not in (np.uint8, np.uint16):
        raise _bad(name, path, expected, f"{array.dtype} samples")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    elif array.ndim == 3 and array.shape[2] == 3:
        array = array[..., ::-1]
    elif array.ndim == 3 and array.shape[2] == 4:
        array = array[..., [2, 1, 0, 3]]
    elif array.ndim != 2:
        raise _bad(name, path, expected, f"an image of shape {array.shape}")
    return np.ascontiguousarray(array)


def _load_npy(path: Path, name: str, expected: str) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise _bad(name, path, expected, f"a file NumPy cannot load ({err})") from None


def _check_float_array(array: np.ndarray, name: str, path: Path, expected: str, unit_range: bool) -> None:
    if not np.issubdtype(array.dtype, np.floating):
        raise _bad(name, path, expected, f"dtype {array.dtype}")
    bad = int((~np.isfinite(array)).sum())
    if bad:
        raise _bad(name, path, expected, f"{bad} NaN or infinite values")
    if unit_range and array.size and (array.min() < 0 or array.max() > 1):
        raise _bad(name, path, "values in [0, 1]", f"values in [{array.min():g}, {array.max():g}]")


def _load_image(path: PathLike, name: str, srgb: bool) -> Tuple[Tensor, Optional[Tensor]]:
    """Return the ``(3, H, W)`` linear image and, for RGBA files, the ``(1, H, W)`` alpha > 0."""
    p = _existing_file(path, name)
    if p.suffix.lower() == ".npy":
        array = _load_npy(p, name, _IMAGE_FORMATS)
        if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3))):
            raise _bad(name, p, _IMAGE_FORMATS, f"an array of shape {array.shape}")
        _check_float_array(array, name, p, _IMAGE_FORMATS, unit_range=True)
        image = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
        image = image[None] if image.ndim == 2 else image.permute(2, 0, 1)
        return image.expand(3, -1, -1).contiguous(), None

    array = _decode_raster(p, name, _IMAGE_FORMATS)
    alpha = None
    if array.ndim == 3 and array.shape[2] == 4:
        alpha = torch.from_numpy(array[..., 3] > 0)[None]
        array = array[..., :3]
    # Decode in float64 so that every 16-bit code survives a decode/encode round trip.
    values = torch.from_numpy(array.astype(np.float64) / np.iinfo(array.dtype).max)
    if srgb:
        values = srgb_to_linear(values)
    image = values[None] if values.ndim == 2 else values.permute(2, 0, 1)
    return image.expand(3, -1, -1).to(torch.float32).contiguous(), alpha


def _load_mask(path: PathLike, name: str) -> Tensor:
    p = _existing_file(path, name)
    if p.suffix.lower() == ".npy":
        array = _load_npy(p, name, _MASK_FORMATS)
        if array.ndim == 3 and 1 in (array.shape[0], array.shape[2]):
            array = array[0] if array.shape[0] == 1 else array[..., 0]
        if array.ndim != 2:
            raise _bad(name, p, _MASK_FORMATS, f"an array of shape {array.shape}")
        if array.dtype != np.bool_ and not np.issubdtype(array.dtype, np.number):
            raise _bad(name, p, _MASK_FORMATS, f"dtype {array.dtype}")
        if np.issubdtype(array.dtype, np.inexact) and not np.isfinite(array).all():
            raise _bad(name, p, _MASK_FORMATS, "NaN or infinite values")
        return torch.from_numpy(np.ascontiguousarray(array != 0))[None]
    array = _decode_raster(p, name, _MASK_FORMATS)
    # JPEG's lossy compression rings around the object's edge and leaves faint non-zero
    # pixels in the background, so there the object is what is brighter than mid-grey.
    threshold = np.iinfo(array.dtype).max // 2 if p.suffix.lower() in (".jpg", ".jpeg") else 0
    if array.ndim == 3 and array.shape[2] == 4:
        return torch.from_numpy(np.ascontiguousarray(array[..., 3] > threshold))[None]
    if array.ndim == 3:
        return torch.from_numpy(np.ascontiguousarray((array > threshold).any(2)))[None]
    return torch.from_numpy(array > threshold)[None]


def read_image(path: PathLike, *, srgb: bool = True) -> Tensor:
    """Read an image as linear RGB.

    Args:
        path: an 8- or 16-bit PNG (grey, RGB or RGBA; alpha is dropped), a JPEG, or a
            ``.npy`` float array ``(H, W, 3)`` / ``(H, W)`` of linear values in [0, 1].
        srgb: decode PNG/JPEG samples from sRGB; ``False`` for files holding linear
            values. ``.npy`` files are always taken as linear.

    Returns:
        :math:`(3, H, W)` float32 linear RGB in [0, 1]; grey images repeat the channel.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file cannot be decoded, or holds the wrong shape or dtype,
            NaN/inf, or (``.npy``) values outside [0, 1].
    """
    return _load_image(path, "path", srgb)[0]


def read_mask(path: PathLike) -> Tensor:
    """Read an object mask.

    Args:
        path: a PNG where non-zero pixels (in any channel) are the object, an RGBA
            PNG whose alpha > 0 is the object, a JPEG where pixels brighter than
            mid-grey (> 127 in any channel) are the object (its compression leaves faint
            non-zero noise in the background), or a ``.npy`` array ``(H, W)`` /
            ``(1, H, W)`` (bool or numeric; non-zero = object).

    Returns:
        :math:`(1, H, W)` bool.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file cannot be decoded or holds the wrong shape, dtype or NaN.
    """
    return _load_mask(path, "path")


def read_image_and_mask(
    image_path: PathLike, mask_path: Optional[PathLike] = None, *, srgb: bool = True
) -> ImageAndMask:
    """Read an image and its mask; an RGBA image without ``mask_path`` supplies its alpha.

    Args:
        image_path: as ``path`` of :func:`read_image`.
        mask_path: as ``path`` of :func:`read_mask`; ``None`` to use the alpha channel of
            an RGBA ``image_path``.
        srgb: as in :func:`read_image`.

    Returns:
        :class:`ImageAndMask` with ``image`` :math:`(3, H, W)` and ``mask`` :math:`(1, H, W)`.

    Raises:
        FileNotFoundError: a path does not exist.
        ValueError: as the readers, when ``mask_path`` is ``None`` and the image has no
            alpha channel, or when image and mask sizes differ.
    """
    image, alpha = _load_image(image_path, "image_path", srgb)
    if mask_path is not None:
        mask = _load_mask(mask_path, "mask_path")
    elif alpha is not None:
        mask = alpha
    else:
        raise ValueError(
            f"mask_path is required: image_path '{image_path}' has no alpha channel to use as the mask"
        )
    if mask.shape[-2:] != image.shape[-2:]:
        raise ValueError(
            f"mask_path '{mask_path}' is {tuple(mask.shape[-2:])} (H, W) but image_path '{image_path}' "
            f"is {tuple(image.shape[-2:])}: they must have the same size"
        )
    return ImageAndMask(image, mask)


def _writable(path: PathLike, name: str, suffix: str) -> Path:
    p = Path(path)
    if p.suffix.lower() != suffix:
        raise ValueError(f"{name} must end in '{suffix}', got '{p}'")
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def _write_png(path: Path, array: np.ndarray) -> None:
    """Write ``(H, W)`` grey or ``(H, W, 3)`` RGB integer samples as a PNG."""
    if array.ndim == 3:
        array = np.ascontiguousarray(array[..., ::-1])
    ok, buffer = cv2.imencode(".png", array)
    if not ok:
        raise ValueError(f"OpenCV could not encode a PNG of shape {array.shape} and dtype {array.dtype}")
    buffer.tofile(path)


def _map_for_file(x: Tensor, name: str, channels: str) -> Tensor:
    """Validate a single ``(C, H, W)`` map and return it as float64 on the CPU."""
    check_shape(x, name, f"{channels} H W")
    check_finite(x, name)
    return x.detach().to("cpu", torch.float64)


def write_image(path: PathLike, image: Tensor, *, srgb: bool = True, bits: int = 8) -> None:
    """Write a linear image as a PNG.

    Args:
        path: output file, ending in ``.png``; missing parent folders are created.
        image: :math:`(3, H, W)` RGB, or :math:`(1, H, W)` / :math:`(H, W)` grey, float
            values in [0, 1] (clamp first: out-of-range values are an error, not clipped).
        srgb: encode as sRGB (for viewing); ``False`` stores the linear values.
        bits: 8 or 16 bits per sample.

    Raises:
        ValueError: ``bits`` is not 8 or 16, ``path`` does not end in ``.png``, or
            ``image`` has the wrong shape, NaN/inf or values outside [0, 1].
    """
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    if isinstance(image, Tensor) and image.ndim == 2:
        image = image[None]
    if isinstance(image, Tensor) and image.ndim == 3 and image.shape[0] not in (1, 3):
        raise ValueError(f"image must have shape (3, H, W), (1, H, W) or (H, W), got {tuple(image.shape)}")
    values = _map_for_file(image, "image", "C")
    low, high = float(values.min()), float(values.max())
    if low < 0 or high > 1:
        raise ValueError(f"image values must lie in [0, 1], got values in [{low:g}, {high:g}]; clamp first")
    p = _writable(path, "path", ".png")
    if srgb:
        values = linear_to_srgb(values)
    dtype = np.uint8 if bits == 8 else np.uint16
    codes = torch.round(values * np.iinfo(dtype).max).numpy().astype(dtype)
    _write_png(p, codes[0] if codes.shape[0] == 1 else codes.transpose(1, 2, 0))


def write_normals_png(path: PathLike, normals: Tensor) -> None:
    """Write a normal map as a 16-bit RGB PNG with colour ~ ``(n + 1) / 2``.

    Component ``n`` in [-1, 1] is stored as the code ``round(32767 n + 32768)``; the
    colour is ``(n + 1) / 2`` to within one code, and zero normals (the background) are
    exactly mid-grey ``32768`` and read back as exactly 0. R, G, B hold x (right),
    y (up), z (towards the viewer). The angular quantisation error is below 0.002 deg.

    Args:
        path: output file ending in ``.png``; missing parent folders are created.
        normals: :math:`(3, H, W)` camera-frame normals, components in [-1, 1] (an
            overshoot up to 1e-4 from rounding is clipped).

    Raises:
        ValueError: wrong shape, NaN/inf, components outside [-1, 1], or a path not
            ending in ``.png``.
    """
    values = _map_for_file(normals, "normals", "3")
    # Unit normals normalised in float32 may overshoot 1 by an ulp or two.
    if bool((values.abs() > 1 + 1e-4).any()):
        largest = float(values.abs().max())
        raise ValueError(f"normals components must lie in [-1, 1], got a largest magnitude of {largest:g}")
    p = _writable(path, "path", ".png")
    codes = torch.round(values * _NORMAL_STEP + _NORMAL_ZERO).clamp(0, 65535).numpy().astype(np.uint16)
    _write_png(p, codes.transpose(1, 2, 0))


def read_normals_png(path: PathLike) -> Tensor:
    """Read a normal map written by :func:`write_normals_png`.

    Returns the decoded components as stored (unit length to within 5e-5, not
    renormalised), so that reading and writing again reproduces the file exactly.

    Returns:
        :math:`(3, H, W)` float32; mid-grey pixels are exactly 0.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a 16-bit RGB PNG.
    """
    expected = "a 16-bit RGB PNG written by write_normals_png"
    p = _existing_file(path, "path")
    array = _decode_raster(p, "path", expected)
    if array.dtype != np.uint16 or array.ndim != 3 or array.shape[2] != 3:
        raise _bad("path", p, expected, f"{array.dtype} samples of shape {array.shape}")
    values = (array.astype(np.float64) - _NORMAL_ZERO) / _NORMAL_STEP
    return torch.from_numpy(values.transpose(2, 0, 1)).to(torch.float32).contiguous()


def write_normals_npy(path: PathLike, normals: Tensor) -> None:
    """Write a normal map as ``.npy``, float32 ``(H, W, 3)`` (the SPEC file layout).

    Args:
        path: output file ending in ``.npy``; missing parent folders are created.
        normals: :math:`(3, H, W)` camera-frame normals.

    Raises:
        ValueError: wrong shape, NaN/inf, or a path not ending in ``.npy``.
    """
    check_shape(normals, "normals", "3 H W")
    check_finite(normals, "normals")
    p = _writable(path, "path", ".npy")
    np.save(p, np.ascontiguousarray(normals.detach().to("cpu", torch.float32).permute(1, 2, 0).numpy()))


def read_normals_npy(path: PathLike) -> Tensor:
    """Read a ``.npy`` normal map of shape ``(H, W, 3)`` (float).

    Returns:
        :math:`(3, H, W)` float32.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: wrong shape, a non-float dtype, or NaN/inf values.
    """
    expected = "a float .npy normal map of shape (H, W, 3)"
    p = _existing_file(path, "path")
    array = _load_npy(p, "path", expected)
    if array.ndim != 3 or array.shape[2] != 3:
        raise _bad("path", p, expected, f"an array of shape {array.shape}")
    _check_float_array(array, "path", p, expected, unit_range=False)
    return torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32))


def read_lighting(path: PathLike) -> Tensor:
    """Read SH lighting from JSON ``{"sh": [[9 floats], [9 floats], [9 floats]]}`` (R, G, B).

    Returns:
        :math:`(3, 9)` float32.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: invalid JSON, no ``"sh"`` key, not 3 rows of 9 numbers, or NaN/inf.
    """
    expected = 'JSON {"sh": [[9 numbers] x 3]} (R, G, B rows)'
    p = _existing_file(path, "path")
    try:
        content = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _bad("path", p, expected, f"a file that is not valid JSON ({err})") from None
    if not isinstance(content, dict) or "sh" not in content:
        raise _bad("path", p, expected, f"no 'sh' key in {type(content).__name__}")
    try:
        sh = np.asarray(content["sh"], dtype=np.float64)
    except (TypeError, ValueError):
        raise _bad("path", p, expected, "'sh' rows that are not lists of numbers") from None
    if sh.shape != (3, 9):
        raise _bad("path", p, expected, f"'sh' of shape {sh.shape}")
    sh = torch.from_numpy(sh).to(torch.float32)
    # after the conversion: coefficients beyond float32's range (1e300) become inf there
    if not bool(torch.isfinite(sh).all()):
        raise _bad("path", p, expected, "NaN or infinite coefficients (or beyond float32's range)")
    return sh


def write_lighting(path: PathLike, sh: Tensor) -> None:
    """Write SH lighting as JSON ``{"sh": [[9 floats] x 3]}``, one colour channel a line.

    Values are written with the shortest decimals that read back to the same float32
    (float64 input keeps all its digits), so a round trip is exact.

    Args:
        path: output file ending in ``.json``; missing parent folders are created.
        sh: :math:`(3, 9)` SH coefficients (SPEC basis order).

    Raises:
        ValueError: wrong shape, NaN/inf, or a path not ending in ``.json``.
    """
    check_shape(sh, "sh", "3 9")
    check_finite(sh, "sh")
    p = _writable(path, "path", ".json")
    values = sh.detach().cpu()
    if values.dtype == torch.float64:
        rows = [[repr(v) for v in row] for row in values.tolist()]
    else:
        rows = [[str(v) for v in row] for row in values.to(torch.float32).numpy()]
    lines = ",\n".join("    [" + ", ".join(row) + "]" for row in rows)
    p.write_text('{\n  "sh": [\n' + lines + "\n  ]\n}\n", encoding="utf-8")


def _single_map(x: Tensor, name: str) -> Tensor:
    """Accept ``(H, W)``, ``(1, H, W)`` or ``(1, 1, H, W)`` and return ``(H, W)``."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (1, H, W) or (H, W), got {type(x).__name__}")
    if x.ndim < 2 or x.ndim > 4 or any(n != 1 for n in x.shape[:-2]):
        raise ValueError(f"{name} must have shape (1, H, W) or (H, W), got {tuple(x.shape)}")
    return x.reshape(x.shape[-2:])


def write_depth_png(path: PathLike, depth: Tensor, mask: Tensor) -> dict:
    """Write a depth map as a 16-bit grey PNG and return what decodes it.

    On the mask, the depth is mapped linearly onto the codes 1 (its minimum) to 65535
    (its maximum); code 0 marks the background. The depth on the mask is then
    ``scale * code + offset``, to within half a quantisation step ``scale``
    (``(max - min) / 65534``). A constant depth is stored as code 1 with ``scale = 0``.
    The depth keeps its meaning and units (:func:`sfs_torch.integrability.depth_to_mesh`):
    the file is a lossy copy of ``depth.npy`` meant for viewers and image tools.

    Args:
        path: output file ending in ``.png``; missing parent folders are created.
        depth: :math:`(1, H, W)` or :math:`(H, W)` float; values outside the mask are ignored.
        mask: same size, bool or 0/1, not empty.

    Returns:
        ``{"scale": float, "offset": float, "depth_min": float, "depth_max": float}``
        (plain floats, ready for JSON).

    Raises:
        ValueError: wrong shapes, an empty mask, NaN/inf depth on the mask, or a path not
            ending in ``.png``.

    Example:
        >>> import tempfile, pathlib
        >>> d = torch.tensor([[9.0, 1.0], [2.0, 4.0]])
        >>> m = torch.tensor([[False, True], [True, True]])
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     info = write_depth_png(pathlib.Path(tmp) / "depth.png", d, m)
        ...     back = read_depth_png(pathlib.Path(tmp) / "depth.png", scale=info["scale"], offset=info["offset"])
        >>> info["depth_min"], info["depth_max"]
        (1.0, 4.0)
        >>> back.depth  # within scale / 2 of the depth on the mask, 0 outside
        tensor([[[0.0000, 1.0000],
                 [2.0000, 4.0000]]])
    """
    d = _single_map(depth, "depth")
    if not d.is_floating_point():
        raise ValueError(f"depth must be a floating-point tensor, got {d.dtype}")
    m = _single_map(mask, "mask")
    if m.shape != d.shape:
        raise ValueError(f"mask is {tuple(m.shape)} (H, W) but depth is {tuple(d.shape)}: they must have the same size")
    m = check_mask(m[None, None], "mask", allow_full=True)[0, 0].cpu()
    d = d.detach().to("cpu", torch.float64)
    check_finite(d[m], "depth on the mask")
    p = _writable(path, "path", ".png")
    low, high = float(d[m].min()), float(d[m].max())
    scale = (high - low) / _DEPTH_CODES
    codes = torch.zeros(d.shape, dtype=torch.float64)
    if scale > 0:
        codes[m] = 1 + torch.round((d[m] - low) / scale).clamp(0, _DEPTH_CODES)
    else:
        codes[m] = 1
    _write_png(p, codes.numpy().astype(np.uint16))
    return {"scale": scale, "offset": low - scale, "depth_min": low, "depth_max": high}


def read_depth_png(path: PathLike, *, scale: float, offset: float) -> DepthAndMask:
    """Read a depth map written by :func:`write_depth_png`.

    Args:
        path: a 16-bit grey PNG.
        scale: as returned by :func:`write_depth_png` (the CLI writes it into ``depth.json``).
        offset: as returned by :func:`write_depth_png` (likewise).

    Returns:
        :class:`DepthAndMask`: ``depth`` :math:`(1, H, W)` float32 ``scale * code + offset``
        on the mask, 0 elsewhere; ``mask`` :math:`(1, H, W)` bool, code > 0.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a 16-bit grey PNG.
    """
    expected = "a 16-bit grey PNG written by write_depth_png"
    p = _existing_file(path, "path")
    array = _decode_raster(p, "path", expected)
    if array.dtype != np.uint16 or array.ndim != 2:
        raise _bad("path", p, expected, f"{array.dtype} samples of shape {array.shape}")
    codes = torch.from_numpy(array.astype(np.float64))
    mask = codes > 0
    depth = torch.where(mask, float(scale) * codes + float(offset), 0.0)
    return DepthAndMask(depth=depth.to(torch.float32)[None].contiguous(), mask=mask[None].contiguous())


def write_mesh(path: PathLike, mesh, *, vertex_normals: Optional[Union[Tensor, np.ndarray]] = None) -> None:
    """Write a triangle mesh with per-vertex normals; the file suffix chooses the format.

    ``.ply`` (binary PLY), ``.obj`` (Wavefront OBJ, one ``vn`` line a vertex, faces
    ``f a//a b//b c//c``) or ``.glb`` (binary glTF 2.0: one mesh, no material). All three
    store the vertices in their order (unreferenced ones included), the faces, and the
    normals, read back by ``trimesh.load`` as ``vertex_normals`` (trimesh's OBJ reader
    drops vertices no face uses, and then the normals too). Vertices, faces and normals
    are written as they are: the camera frame (x right, y up, z towards the viewer) is
    also glTF's axis convention. PLY and GLB store vertices and normals as float32;
    GLB normals are unit length (glTF requires it).

    Args:
        path: output file ending in ``.ply``, ``.obj`` or ``.glb``; missing parent folders
            are created.
        mesh: a ``trimesh.Trimesh`` (e.g. :func:`sfs_torch.integrability.depth_to_mesh`);
            it is not modified.
        vertex_normals: :math:`(V, 3)` normals, one per vertex (e.g. the estimated normals
            at the mask pixels); ``None`` writes ``mesh.vertex_normals`` (given or
            computed by trimesh from the faces).

    Raises:
        TypeError: ``mesh`` is not a ``trimesh.Trimesh``.
        ValueError: an unknown suffix, a mesh without vertices, ``vertex_normals`` of the
            wrong shape or with NaN/inf, or (``.glb``) a zero-length normal, as trimesh
            computes for a vertex no face uses.
    """
    import trimesh

    p = Path(path)
    kind = p.suffix.lower().lstrip(".")
    if kind not in MESH_FORMATS:
        raise ValueError(f"path must end in {', '.join('.' + f for f in MESH_FORMATS)}, got '{p}'")
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if len(vertices) == 0:
        raise ValueError("mesh has no vertices: there is nothing to write")
    normals = mesh.vertex_normals if vertex_normals is None else vertex_normals
    if isinstance(normals, Tensor):
        normals = normals.detach().cpu().numpy()
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != vertices.shape:
        raise ValueError(f"vertex_normals must have shape {vertices.shape} (one per vertex), got {normals.shape}")
    if not np.isfinite(normals).all():
        raise ValueError(f"vertex_normals contains {int((~np.isfinite(normals)).sum())} NaN or infinite values")
    # glTF requires unit normals: the exporter scales the others to unit length, but a
    # zero normal has no direction to scale
    zero = int((~normals.any(1)).sum())
    if kind == "glb" and zero:
        raise ValueError(f"vertex_normals holds {zero} zero-length normals, which glTF (.glb) cannot store: "
                         "give every vertex a direction")
    # a copy holding the normals: trimesh keeps given normals only until its data change
    copy = trimesh.Trimesh(vertices=vertices, faces=np.asarray(mesh.faces, dtype=np.int64), process=False)
    copy.vertex_normals = normals
    if kind == "ply":
        data = copy.export(file_type="ply", encoding="binary", vertex_normal=True, include_attributes=False)
    elif kind == "obj":
        data = copy.export(file_type="obj", include_normals=True, include_color=False, include_texture=False)
    else:
        data = copy.export(file_type="glb", include_normals=True)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
