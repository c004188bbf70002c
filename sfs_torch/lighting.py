r"""Second-order spherical-harmonic (SH) lighting: basis, shading, fitting, conversions.

A lighting (the paper's reflectance map) is a tensor ``(B, 3, 9)``: 9 real SH
coefficients per colour channel, defined so that the rendered linear intensity of a
surface with unit normal ``n = (x, y, z)`` in the camera frame is

.. math:: I_c(n) = \sum_k L[c, k] \, Y_k(n),

with albedo and the Lambertian convolution folded into ``L`` (SPEC). Basis order:
``Y0 = 0.282095``, ``Y1 = 0.488603 y``, ``Y2 = 0.488603 z``, ``Y3 = 0.488603 x``,
``Y4 = 1.092548 xy``, ``Y5 = 1.092548 yz``, ``Y6 = 0.315392 (3z^2 - 1)``,
``Y7 = 1.092548 xz``, ``Y8 = 0.546274 (x^2 - y^2)``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor, nn

from ._blocks import in_blocks
from ._checks import check_finite, check_mask, check_same_size, check_shape, is_number

__all__ = [
    "SH_CONSTANTS",
    "SphereNormals",
    "SHRenderer",
    "SHRotation",
    "SHFit",
    "sh_basis",
    "sh_basis_vectors",
    "render_sh",
    "fit_sh",
    "fit_sh_vectors",
    "irradiance_to_sh",
    "sh_to_matrix",
    "matrix_to_sh",
    "rotate_sh",
    "sphere_normals",
    "render_sphere",
    "natural_lightings",
]

SH_CONSTANTS = (0.282095, 0.488603, 1.092548, 0.315392, 0.546274)
_C0, _C1, _C2, _C3, _C4 = SH_CONSTANTS
# Lambertian convolution A_l / pi for bands l = 0, 1, 2 (Ramamoorthi & Hanrahan 2001).
_BAND_OF_COEFFICIENT = (0, 1, 1, 1, 2, 2, 2, 2, 2)
_LAMBERT_OVER_PI = (1.0, 2.0 / 3.0, 0.25)


def sh_basis_vectors(n: Tensor) -> Tensor:
    """The 9 SH basis functions of unit vectors.

    Args:
        n: directions, :math:`(*, 3)`.

    Returns:
        :math:`(*, 9)` basis values in SPEC order.

    Raises:
        TypeError: ``n`` is not a tensor.
        ValueError: its last dimension is not 3.
    """
    if not isinstance(n, Tensor):
        raise TypeError(f"n must be a torch.Tensor of shape (*, 3), got {type(n).__name__}")
    if n.ndim == 0 or n.shape[-1] != 3:
        raise ValueError(f"n must have shape (*, 3), got {tuple(n.shape)}")
    x, y, z = n.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, _C0),
            _C1 * y,
            _C1 * z,
            _C1 * x,
            _C2 * x * y,
            _C2 * y * z,
            _C3 * (3 * z * z - 1),
            _C2 * x * z,
            _C4 * (x * x - y * y),
        ],
        -1,
    )


def sh_basis(normals: Tensor) -> Tensor:
    """The 9 SH basis functions of a normal map.

    Args:
        normals: camera-frame unit normals, :math:`(B, 3, H, W)`.

    Returns:
        :math:`(B, 9, H, W)` basis images.
    """
    check_shape(normals, "normals", "B 3 H W")
    return sh_basis_vectors(normals.movedim(1, -1)).movedim(-1, 1)


def _check_trailing(x: Tensor, name: str, trailing: Tuple[int, ...]) -> None:
    """Check that ``x`` is a floating-point tensor of shape ``(*, *trailing)``, like :func:`check_shape`
    for the functions that take any batch shape."""
    spec = ", ".join(["*", *map(str, trailing)])
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape ({spec}), got {type(x).__name__}")
    if x.shape[x.ndim - len(trailing):] != trailing:
        raise ValueError(f"{name} must have shape ({spec}), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {x.dtype}")


def _sh_polynomial(sh: Tensor) -> Tuple[Tensor, Tensor]:
    """SH coefficients as a quadratic polynomial in the normal.

    Args:
        sh: :math:`(*, 3, 9)` coefficients.

    Returns:
        ``(coefficients, constant)``: :math:`(*, 3, 9)` weights of the monomials
        ``x, y, z, x^2, y^2, z^2, xy, yz, zx`` (the order of :func:`_sh_monomials`) and
        the :math:`(*, 3)` constant term, so that
        ``I_c(n) = constant[c] + sum_k coefficients[c, k] m_k(n)`` equals the SPEC basis
        sum for any ``n`` (unit or not, zero included).
    """
    a = sh.unbind(-1)
    coefficients = torch.stack(
        [
            _C1 * a[3], _C1 * a[1], _C1 * a[2],  # x, y, z
            _C4 * a[8], -_C4 * a[8], 3 * _C3 * a[6],  # x^2, y^2, z^2
            _C2 * a[4], _C2 * a[5], _C2 * a[7],  # xy, yz, zx
        ],
        -1,
    )
    return coefficients, _C0 * a[0] - _C3 * a[6]


def _sh_monomials(n: Tensor) -> Tensor:
    """The 9 monomials ``x, y, z, x^2, y^2, z^2, xy, yz, zx`` of flattened normals.

    Args:
        n: :math:`(B, 3, P)` normals.

    Returns:
        :math:`(B, 9, P)`, contiguous.
    """
    return torch.cat([n, n * n, n[:, 0:2] * n[:, 1:3], n[:, 2:3] * n[:, 0:1]], 1)


def render_sh(normals: Tensor, sh: Tensor) -> Tensor:
    """Shade a normal map with SH lighting.

    Pixels whose normal is zero (outside the object) receive the lighting's constant
    terms; multiply by the mask where a black background is wanted.

    The 9-term basis sum is evaluated as the equal quadratic polynomial in ``n`` (9
    monomials and a constant, a batched matrix product, over blocks of the batch); it
    equals ``einsum("bck,bkhw->bchw", sh, sh_basis(normals))`` up to rounding.

    Args:
        normals: camera-frame unit normals, :math:`(B, 3, H, W)`.
        sh: SH coefficients, :math:`(B, 3, 9)` (or :math:`(3, 9)`, shared by the batch).

    Returns:
        linear RGB, :math:`(B, 3, H, W)`, unclipped, contiguous, dtype and device of
        ``normals``.

    Example:
        >>> n = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
        >>> sh = torch.zeros(1, 3, 9); sh[:, :, 0] = 1 / 0.282095
        >>> render_sh(n, sh).flatten().tolist()
        [1.0, 1.0, 1.0]
    """
    check_shape(normals, "normals", "B 3 H W")
    batch, _, height, width = normals.shape
    if sh.ndim == 2:
        sh = sh.expand(batch, -1, -1)
    check_shape(sh, "sh", "B 3 9")
    if sh.shape[0] != batch:
        raise ValueError(f"sh must have batch size {batch} like normals, got {tuple(sh.shape)}")
    # one lighting broadcast over the batch (stride 0): convert it once, not per element
    shared = batch > 1 and sh.stride(0) == 0
    coefficients, constant = _sh_polynomial((sh[:1] if shared else sh).to(normals.dtype))
    if shared:
        coefficients, constant = coefficients.expand(batch, -1, -1), constant.expand(batch, -1)
    flat, constant = normals.reshape(batch, 3, height * width), constant.unsqueeze(-1)

    def shade(part: slice) -> Tensor:
        return torch.baddbmm(constant[part], coefficients[part], _sh_monomials(flat[part]))

    return in_blocks(shade, batch, 3 * height * width, flat.shape, flat).view(batch, 3, height, width)


def fit_sh_vectors(
    normals: Tensor,
    colours: Tensor,
    weights: Optional[Tensor] = None,
    ridge: float = 1e-9,
    nonnegative: Optional[Tensor] = None,
) -> Tensor:
    """Weighted least-squares SH fit to colour samples, in closed form.

    Args:
        normals: unit directions, :math:`(B, N, 3)`.
        colours: observed linear RGB, :math:`(B, N, 3)`.
        weights: non-negative sample weights, :math:`(B, N)`; 0 drops a sample.
        ridge: Tikhonov term relative to the mean diagonal of the normal equations,
            which keeps the solve finite when the normals do not span all 9 functions.
        nonnegative: optional directions :math:`(M, 3)` on which the fitted shading must
            not be negative (a physically valid lighting there): the constrained least
            squares, per channel, solved through its dual.

    Returns:
        :math:`(B, 3, 9)` coefficients.

    Raises:
        TypeError: an argument is not a tensor.
        ValueError: bad or disagreeing shapes, or non-floating-point ``colours`` (the
            result takes their dtype).
    """
    check_shape(normals, "normals", "B N 3", floating=False)
    check_shape(colours, "colours", "B N 3")
    if colours.shape != normals.shape:
        raise ValueError(
            f"normals and colours must have the same shape (B, N, 3), got {tuple(normals.shape)} and "
            f"{tuple(colours.shape)}"
        )
    if weights is not None:
        check_shape(weights, "weights", "B N", floating=False)
        if weights.shape != normals.shape[:2]:
            raise ValueError(f"weights must have shape (B, N) = {tuple(normals.shape[:2])}, got {tuple(weights.shape)}")
    if nonnegative is not None:
        check_shape(nonnegative, "nonnegative", "M 3")
    # Float64 normal equations: on the visible hemisphere alone the constant, z and z^2
    # terms are nearly collinear, and float32 loses ~1e-3 of the coefficients.
    out_dtype = colours.dtype
    basis = sh_basis_vectors(normals.double())  # (B, N, 9)
    colours = colours.double()
    weighted = basis if weights is None else basis * weights.double().unsqueeze(-1)
    gram = weighted.transpose(1, 2) @ basis  # (B, 9, 9)
    rhs = weighted.transpose(1, 2) @ colours  # (B, 9, 3)
    scale = gram.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(torch.finfo(gram.dtype).tiny)
    eye = torch.eye(9, dtype=gram.dtype, device=gram.device)
    gram = gram + ridge * scale[:, None, None] * eye
    solution = torch.linalg.solve(gram, rhs)  # (B, 9, 3)
    if nonnegative is not None:
        solution = _nonnegative_solution(gram, rhs, solution, sh_basis_vectors(nonnegative.to(gram)))
    # contiguous: the constrained solution's transpose is a strided view, which callers that
    # flatten it (torch.optim's L-BFGS, on the refinement's lighting) cannot view
    return solution.transpose(1, 2).to(out_dtype).contiguous()


def _nonnegative_solution(gram: Tensor, rhs: Tensor, solution: Tensor, basis: Tensor, iterations: int = 500) -> Tensor:
    """Least squares with the shading on ``basis`` (M, 9) kept >= 0, each channel (B, 9, 3).

    Solves the dual of ``min 1/2 x^T G x - b^T x  s.t.  A x >= 0`` (a non-negative
    multiplier per direction) by accelerated projected gradient; the primal is
    ``x = G^-1 (b + A^T lambda)``, its constant term raised by what violation the fixed number
    of steps leaves. Only runs where the unconstrained fit violates.
    """
    if not bool(((basis @ solution) < 0).any()):
        return solution
    inverse = torch.linalg.inv(gram)  # (B, 9, 9), shared by the channels
    coupling = basis @ inverse @ basis.T  # (B, M, M)
    step = 1.0 / torch.linalg.eigvalsh(coupling)[:, -1].clamp_min(torch.finfo(gram.dtype).tiny)
    lam = torch.zeros(gram.shape[0], basis.shape[0], 3, dtype=gram.dtype, device=gram.device)
    y, momentum = lam, 1.0
    for _ in range(iterations):
        shading = basis @ (inverse @ (rhs + basis.T @ y))  # (B, M, 3): the dual gradient
        new = (y - step[:, None, None] * shading).clamp_min(0)
        next_momentum = 0.5 * (1.0 + (1.0 + 4.0 * momentum * momentum) ** 0.5)
        y = new + ((momentum - 1.0) / next_momentum) * (new - lam)
        lam, momentum = new, next_momentum
    solution = inverse @ (rhs + basis.T @ lam)
    # few samples make G nearly singular and the dual converge slowly: lift what violation is
    # left with the constant term (Y0 > 0 everywhere), so the shading on ``basis`` is >= 0
    lift = (-(basis @ solution).amin(1)).clamp_min(0)  # (B, 3)
    solution[:, 0] = solution[:, 0] + lift / _C0
    return solution


def fit_sh(
    normals: Tensor, colours: Tensor, mask: Tensor, weights: Optional[Tensor] = None, nonnegative: Optional[Tensor] = None
) -> Tensor:
    """Fit SH lighting to an image of known normals (closed-form least squares).

    Args:
        normals: camera-frame unit normals, :math:`(B, 3, H, W)`.
        colours: linear RGB, :math:`(B, 3, H, W)`.
        mask: pixels to use, :math:`(B, 1, H, W)` bool.
        weights: optional per-pixel weights, :math:`(B, 1, H, W)`, finite, non-negative
            and positive somewhere on each batch element's mask.
        nonnegative: optional directions :math:`(M, 3)` where the fitted shading must
            not be negative (see :func:`fit_sh_vectors`).

    Returns:
        :math:`(B, 3, 9)` SH coefficients minimising the (weighted) squared shading error.

    Raises:
        ValueError: shapes disagree, inputs hold NaN/inf, or weights are negative or zero
            on a whole mask.
    """
    check_shape(normals, "normals", "B 3 H W")
    check_shape(colours, "colours", "B 3 H W")
    check_same_size(normals, "normals", colours, "colours")
    mask = check_mask(mask, "mask", allow_full=True)
    check_same_size(normals, "normals", mask, "mask")
    check_finite(normals, "normals")
    check_finite(colours, "colours")
    if nonnegative is not None:
        check_shape(nonnegative, "nonnegative", "M 3")
    w = mask.to(normals.dtype)
    if weights is not None:
        check_shape(weights, "weights", "B 1 H W")
        check_same_size(normals, "normals", weights, "weights")
        check_finite(weights, "weights")
        if bool((weights < 0).any()):
            raise ValueError("weights must be non-negative")
        # no weighted sample leaves nothing to fit: the normal equations would be all zero
        empty = ~((weights > 0) & mask).flatten(1).any(1)
        if bool(empty.any()):
            which = torch.nonzero(empty).flatten().tolist()
            raise ValueError(f"weights are zero on the whole mask in batch element(s) {which}")
        w = w * weights.to(normals.dtype)
    return fit_sh_vectors(
        normals.flatten(2).transpose(1, 2), colours.to(normals.dtype).flatten(2).transpose(1, 2), w.flatten(1),
        nonnegative=nonnegative,
    )


def irradiance_to_sh(coefficients: Tensor, albedo: float = 1.0) -> Tensor:
    """Convert Ramamoorthi & Hanrahan's radiance coefficients ``L_lm`` to SPEC lighting.

    ``L[c, k] = albedo * A_l / pi * L_lm`` with ``A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4``,
    so that rendering gives ``albedo * E(n) / pi`` with R&H's irradiance ``E``.

    Args:
        coefficients: :math:`(*, 3, 9)` ``L_lm`` in the order L00, L1-1, L10, L11,
            L2-2, L2-1, L20, L21, L22.

    Returns:
        :math:`(*, 3, 9)` SH lighting.

    Raises:
        TypeError: ``coefficients`` is not a tensor.
        ValueError: its shape is not :math:`(*, 3, 9)`, or it is not floating point (the
            factors ``A_l / pi`` would be truncated to integers).
    """
    _check_trailing(coefficients, "coefficients", (3, 9))
    factors = torch.tensor(
        [_LAMBERT_OVER_PI[band] for band in _BAND_OF_COEFFICIENT], dtype=coefficients.dtype, device=coefficients.device
    )
    return albedo * coefficients * factors


def sh_to_matrix(sh: Tensor) -> Tensor:
    """The 4x4 matrix form ``I_c = n^T M_c n`` of a lighting (``n`` homogeneous).

    Args:
        sh: :math:`(*, 3, 9)`.

    Returns:
        :math:`(*, 3, 4, 4)` symmetric matrices.

    Raises:
        TypeError: ``sh`` is not a tensor.
        ValueError: its shape is not :math:`(*, 3, 9)`, or it is not floating point.
    """
    _check_trailing(sh, "sh", (3, 9))
    s = sh.unbind(-1)
    zero = torch.zeros_like(s[0])
    rows = [
        [_C4 * s[8], _C2 * s[4] / 2, _C2 * s[7] / 2, _C1 * s[3] / 2],
        [_C2 * s[4] / 2, -_C4 * s[8], _C2 * s[5] / 2, _C1 * s[1] / 2],
        [_C2 * s[7] / 2, _C2 * s[5] / 2, 3 * _C3 * s[6] + zero, _C1 * s[2] / 2],
        [_C1 * s[3] / 2, _C1 * s[1] / 2, _C1 * s[2] / 2, _C0 * s[0] - _C3 * s[6]],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def matrix_to_sh(matrix: Tensor) -> Tensor:
    """Inverse of :func:`sh_to_matrix` for any (not necessarily symmetric) 4x4 ``M``.

    On unit normals ``n^T M n`` only depends on the symmetric part of ``M`` and on
    ``M00 + M11 + M22 - M33`` up to the identity ``x^2 + y^2 + z^2 = 1``; every such
    matrix has exactly one SH equivalent.

    Args:
        matrix: :math:`(*, 3, 4, 4)`.

    Returns:
        :math:`(*, 3, 9)`.

    Raises:
        TypeError: ``matrix`` is not a tensor.
        ValueError: its shape is not :math:`(*, 3, 4, 4)`, or it is not floating point.
    """
    _check_trailing(matrix, "matrix", (3, 4, 4))
    m = (matrix + matrix.transpose(-1, -2)) / 2
    diag_xy = (m[..., 0, 0] + m[..., 1, 1]) / 2
    l8 = (m[..., 0, 0] - m[..., 1, 1]) / (2 * _C4)
    l6 = (m[..., 2, 2] - diag_xy) / (3 * _C3)
    l0 = (m[..., 3, 3] + diag_xy + _C3 * l6) / _C0
    return torch.stack(
        [
            l0,
            2 * m[..., 1, 3] / _C1,
            2 * m[..., 2, 3] / _C1,
            2 * m[..., 0, 3] / _C1,
            2 * m[..., 0, 1] / _C2,
            2 * m[..., 1, 2] / _C2,
            l6,
            2 * m[..., 0, 2] / _C2,
            l8,
        ],
        -1,
    )


def rotate_sh(sh: Tensor, rotation: Tensor) -> Tensor:
    """Rotate a lighting: the result lights ``R n`` as the input lights ``n``.

    Args:
        sh: :math:`(B, 3, 9)` (or :math:`(3, 9)`).
        rotation: :math:`(B, 3, 3)` (or :math:`(3, 3)`) rotation matrices.

    Returns:
        rotated lighting, same shape as ``sh`` broadcast with ``rotation``.

    Raises:
        TypeError: an argument is not a tensor.
        ValueError: bad shapes, batch sizes that do not broadcast, or non-floating-point ``sh``.
    """
    for x, name, tail in ((rotation, "rotation", "3, 3"), (sh, "sh", "3, 9")):
        if not isinstance(x, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor of shape ({tail}) or (B, {tail}), got {type(x).__name__}")
    if rotation.ndim not in (2, 3) or rotation.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must have shape (3, 3) or (B, 3, 3), got {tuple(rotation.shape)}")
    if sh.ndim not in (2, 3) or sh.shape[-2:] != (3, 9):
        raise ValueError(f"sh must have shape (3, 9) or (B, 3, 9), got {tuple(sh.shape)}")
    if not sh.is_floating_point():
        raise ValueError(f"sh must be a floating-point tensor, got {sh.dtype}")
    if rotation.ndim == sh.ndim == 3 and rotation.shape[0] != sh.shape[0] and 1 not in (rotation.shape[0], sh.shape[0]):
        raise ValueError(
            f"sh and rotation must have the same batch size (or one of them 1), got {tuple(sh.shape)} and "
            f"{tuple(rotation.shape)}"
        )
    rot4 = torch.zeros(*rotation.shape[:-2], 4, 4, dtype=sh.dtype, device=sh.device)
    rot4[..., :3, :3] = rotation.to(sh.dtype)
    rot4[..., 3, 3] = 1
    rot4 = rot4.unsqueeze(-3)  # broadcast over colour channels
    # I'(n') = I(R^T n') = n'^T (R M R^T) n'
    return matrix_to_sh(rot4 @ sh_to_matrix(sh) @ rot4.transpose(-1, -2))


@dataclass(frozen=True)
class SphereNormals:
    """Normals of a unit sphere seen by an orthographic camera.

    Attributes:
        normals: :math:`(1, 3, R, R)`, 0 outside the disk.
        mask: :math:`(1, 1, R, R)` bool, pixel centres inside the unit disk.
    """

    normals: Tensor
    mask: Tensor


@lru_cache(maxsize=16)
def _sphere_normals_cpu(resolution: int) -> SphereNormals:
    coords = (torch.arange(resolution, dtype=torch.float64) + 0.5) / resolution * 2 - 1
    y, x = torch.meshgrid(-coords, coords, indexing="ij")  # row 0 is the top: y up
    r2 = x * x + y * y
    mask = r2 < 1
    z = torch.sqrt((1 - r2).clamp_min(0))
    normals = torch.stack([x, y, z]) * mask
    return SphereNormals(normals[None].float(), mask[None, None])


def sphere_normals(resolution: int = 64, *, device: Optional[torch.device] = None) -> SphereNormals:
    """Visible-hemisphere normals of an orthographic sphere image (the lMSE grid)."""
    if resolution < 2:
        raise ValueError(f"resolution must be at least 2, got {resolution}")
    s = _sphere_normals_cpu(int(resolution))
    return SphereNormals(s.normals.to(device), s.mask.to(device))


def render_sphere(sh: Tensor, resolution: int = 64) -> Tensor:
    """Render lightings on a sphere: the reflectance-map picture of the paper's Fig. 6.

    Args:
        sh: :math:`(B, 3, 9)` (or :math:`(3, 9)`).
        resolution: image size in pixels.

    Returns:
        :math:`(B, 3, R, R)` (or :math:`(3, R, R)`) linear RGB, 0 outside the disk.
    """
    single = sh.ndim == 2
    sh_b = sh[None] if single else sh
    check_shape(sh_b, "sh", "B 3 9")
    sphere = sphere_normals(resolution, device=sh.device)
    normals = sphere.normals.to(sh.dtype).expand(sh_b.shape[0], -1, -1, -1)
    image = render_sh(normals, sh_b) * sphere.mask
    return image[0] if single else image


def natural_lightings(albedo: float = 1.0) -> Dict[str, Tensor]:
    """Ramamoorthi & Hanrahan's light probes as SPEC lightings, ``{name: (3, 9)}``.

    These are natural, coloured illuminations (Debevec's probes); ``albedo`` scales
    them (their raw intensities render to roughly [0, 1.5]).

    Raises:
        ValueError: ``albedo`` is not a finite number > 0.
    """
    if not is_number(albedo, 0, strict=True):
        raise ValueError(f"albedo must be a number > 0, got {albedo!r}")
    data = json.loads(resources.files("sfs_torch").joinpath("data/rh_probes.json").read_text())
    return {
        name: irradiance_to_sh(torch.tensor(coefs, dtype=torch.float32).T.contiguous(), albedo)
        for name, coefs in data["probes"].items()
    }


class SHRenderer(nn.Module):
    """Shade normal maps with a fixed SH lighting (module form of :func:`render_sh`)."""

    def __init__(self, sh: Tensor):
        super().__init__()
        self.register_buffer("sh", sh)

    def forward(self, normals: Tensor) -> Tensor:
        return render_sh(normals, self.sh)



class SHRotation(nn.Module):
    """Rotate lightings by one fixed rotation (module form of :func:`rotate_sh`).

    The rotation is a buffer, like :class:`SHRenderer`'s lighting: it is the fixed part
    of the operation (e.g. a camera's or an object's :func:`sfs_torch.camera.centroid_rotation`),
    so it moves with ``.to(device)`` and is saved in the ``state_dict``; the lightings
    are the input. For a rotation that changes every call, use :func:`rotate_sh`.

    Args:
        rotation: rotation matrices :math:`(3, 3)` (shared by the batch) or :math:`(B, 3, 3)`.

    ``forward(sh)``: lightings :math:`(B, 3, 9)` (or :math:`(3, 9)`); returns the rotated
    lightings, which light ``R n`` as the input lights ``n``, of shape ``sh`` broadcast
    with ``rotation``.

    Example:
        >>> SHRotation(torch.eye(3))(torch.ones(2, 3, 9)).shape
        torch.Size([2, 3, 9])
    """

    def __init__(self, rotation: Tensor):
        super().__init__()
        if not isinstance(rotation, Tensor):
            raise TypeError(
                f"rotation must be a torch.Tensor of shape (3, 3) or (B, 3, 3), got {type(rotation).__name__}"
            )
        if rotation.ndim not in (2, 3) or rotation.shape[-2:] != (3, 3) or not rotation.is_floating_point():
            raise ValueError(
                f"rotation must be a floating-point tensor of shape (3, 3) or (B, 3, 3), got {tuple(rotation.shape)} "
                f"{rotation.dtype}"
            )
        self.register_buffer("rotation", rotation)

    def forward(self, sh: Tensor) -> Tensor:
        return rotate_sh(sh, self.rotation)


class SHFit(nn.Module):
    """Fit SH lighting to an image of known normals (module form of :func:`fit_sh`).

    Args:
        nonnegative: optional directions :math:`(M, 3)` on which the fitted shading must
            not be negative (e.g. :func:`sfs_torch.reflectance_map.hemisphere_directions`);
            a buffer, ``None`` for the unconstrained least squares.

    ``forward(normals, colours, mask, weights=None)``: normals and colours
    :math:`(B, 3, H, W)`, mask and weights :math:`(B, 1, H, W)`; returns :math:`(B, 3, 9)`.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1
        >>> SHFit()(n, torch.ones(1, 3, 4, 4), torch.ones(1, 1, 4, 4, dtype=torch.bool)).shape
        torch.Size([1, 3, 9])
    """

    def __init__(self, nonnegative: Optional[Tensor] = None):
        super().__init__()
        if nonnegative is not None:
            check_shape(nonnegative, "nonnegative", "M 3")
            check_finite(nonnegative, "nonnegative")
        self.register_buffer("nonnegative", nonnegative)

    def forward(self, normals: Tensor, colours: Tensor, mask: Tensor, weights: Optional[Tensor] = None) -> Tensor:
        return fit_sh(normals, colours, mask, weights, nonnegative=self.nonnegative)
