"""Integrability (paper Sec. 5, Eq. 3; Sec. 9.2): fuse per-pixel normals into a surface.

The forest predicts every pixel on its own, so its normals need not be the normals of
any surface. Here we solve for the surface whose finite differences best match the
normals' gradients, ON THE OBJECT MASK only, with natural boundary conditions: only
pixel pairs that both lie inside the mask contribute, so the silhouette imposes nothing.

Frames (SPEC): x right, y up, z towards the viewer; pixel ``(i, j)`` sits at
``u = j + 0.5 - cx``, ``v = cy - (i + 0.5)``.

- Orthographic: the surface is the height ``z(u, v)`` towards the viewer, in pixel
  units; ``n ∝ (-z_u, -z_v, 1)``, so ``p = z_u = -n_x / n_z`` and ``q = z_v = -n_y / n_z``.
  ``Surface.depth`` is this height ``z`` (camera-frame z coordinate, larger is nearer),
  fixed to zero mean on every connected component of the mask.
- Perspective (focal ``f`` in pixels): a surface point is ``d (u / f, v / f, -1)`` with
  ``d > 0`` the distance along the optical axis. With ``s = log d``,
  ``s_u = n_x / k`` and ``s_v = n_y / k`` where ``k = f n_z - u n_x - v n_y > 0`` for a
  visible point; conversely ``n ∝ (f s_u, f s_v, 1 + u s_u + v s_v)``.
  ``Surface.depth`` is ``d``, fixed to geometric mean 1 on every connected component.

Both cases integrate a field ``(g_u, g_v)`` into a scalar ``s``: every horizontal pair of
mask pixels ``(i, j), (i, j + 1)`` asks ``s[i, j+1] - s[i, j] = (g_u[i, j] + g_u[i, j+1]) / 2``
and every vertical pair ``(i, j), (i + 1, j)`` asks
``s[i+1, j] - s[i, j] = -(g_v[i, j] + g_v[i+1, j]) / 2`` (row ``i + 1`` is one pixel lower).
The weighted least-squares normal equations are a graph Laplacian on the mask; we solve
them matrix-free with conjugate gradients preconditioned by an aggregation multigrid
V-cycle (2x2 aggregates keep the 4-neighbour structure on every level), in torch, on any
device. The Laplacian's nullspace is one constant per connected component: the right-hand
side is orthogonal to it, CG stays consistent on the singular system, the coarsest level
uses a pseudo-inverse, and the result is projected to zero mean on every component.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_mask, check_same_size, check_shape, from_batch, is_integer, is_number, to_batch
from .camera import _check_camera, pixel_grid

__all__ = [
    "IntegrabilityConfig",
    "check_integrability_config",
    "Surface",
    "Integrator",
    "DepthToNormals",
    "integrate_normals",
    "integrate_convex",
    "depth_to_normals",
    "bas_relief_normals",
    "median_slope",
    "depth_to_mesh",
    "mask_components",
]

logger = logging.getLogger(__name__)

METHODS = ("l2", "l1", "conv")


@dataclass
class IntegrabilityConfig:
    """Options of :class:`Integrator` (and of :func:`integrate_normals`).

    ``hydra.utils.instantiate(IntegrabilityConfig())`` builds an L2 :class:`Integrator`.
    Whether the pipeline integrates at all is its ``integrate.method`` (``"none"``, its
    default, or one of these solvers; :class:`~sfs_torch.pipeline.PipelineConfig`).

    Attributes:
        method: the solver: ``"l2"`` (least squares), ``"l1"`` (robust, IRLS) or ``"conv"``
            (convex combination of candidate normals).
        max_iter: conjugate-gradient iterations per linear solve.
        tol: relative residual at which a linear solve stops.
        min_nz: smallest cosine between a normal and the viewing direction; steeper
            normals are clamped there (slopes up to ``sqrt(1 - min_nz^2) / min_nz``).
        l1_iter: reweighting rounds of the L1 variant.
        l1_delta: smoothing of the L1 penalty, ``sqrt(r^2 + delta^2)``, in the units of
            the gradient (pixels per pixel, or log-depth per pixel).
        conv_iter: accelerated projected-gradient steps on the convex weights (each with
            one warm-started depth solve).
        conv_prior: pull of the convex weights towards the mean of the candidates.
    """

    _target_: str = "sfs_torch.integrability.Integrator"
    method: str = "l2"
    max_iter: int = 500
    tol: float = 1e-5
    min_nz: float = 0.05
    l1_iter: int = 15
    l1_delta: float = 0.02
    conv_iter: int = 10
    conv_prior: float = 0.1


def check_integrability_config(cfg: IntegrabilityConfig, prefix: str = "") -> None:
    """``ValueError`` naming the first bad option of ``cfg`` as ``prefix`` + its field name
    (``"integrate."`` in the pipeline, none in :class:`Integrator`, whose arguments they are).

    ``method`` must be a solver of :data:`METHODS`; the pipeline's ``integrate.method="none"``
    (no solver) is the pipeline's to check.

    Example:
        >>> check_integrability_config(IntegrabilityConfig(tol=0.0), prefix="integrate.")
        Traceback (most recent call last):
        ...
        ValueError: integrate.tol must be > 0, got 0.0
    """
    if cfg.method not in METHODS:
        raise ValueError(f"{prefix}method must be one of {METHODS}, got {cfg.method!r}")
    for name, minimum in (("max_iter", 1), ("l1_iter", 0), ("conv_iter", 0)):
        if not is_integer(getattr(cfg, name), minimum):
            raise ValueError(f"{prefix}{name} must be an integer >= {minimum}, got {getattr(cfg, name)!r}")
    # an infinite tol stops the solver before its first step (an all-zero depth)
    for name in ("tol", "l1_delta"):
        if not is_number(getattr(cfg, name), 0, strict=True):
            raise ValueError(f"{prefix}{name} must be > 0, got {getattr(cfg, name)!r}")
    if not (is_number(cfg.min_nz, 0, strict=True) and cfg.min_nz < 1):
        raise ValueError(f"{prefix}min_nz must be in (0, 1), got {cfg.min_nz!r}")
    if not is_number(cfg.conv_prior, 0):
        raise ValueError(f"{prefix}conv_prior must be >= 0, got {cfg.conv_prior!r}")


@dataclass(frozen=True)
class Surface:
    """Result of integration.

    Attributes:
        depth: :math:`(B, 1, H, W)`; orthographic: height towards the viewer in pixels,
            zero mean per connected component; perspective: distance along the optical
            axis, geometric mean 1 per component. 0 outside the mask.
        normals: :math:`(B, 3, H, W)` unit normals of that surface (camera frame,
            :func:`depth_to_normals`), 0 outside the mask.
    """

    depth: Tensor
    normals: Tensor


# ----------------------------------------------------------------------------- grid operators
# Fields live on the full (B, H, W) grid, 0 outside the mask. Horizontal edge weights
# ``wx[b, i, j]`` join (i, j) and (i, j + 1) (last column 0), vertical ``wy[b, i, j]``
# join (i, j) and (i + 1, j) (last row 0).


def _dx(s: Tensor) -> Tensor:
    return F.pad(s[..., :, 1:] - s[..., :, :-1], (0, 1))


def _dy(s: Tensor) -> Tensor:
    return F.pad(s[..., 1:, :] - s[..., :-1, :], (0, 0, 0, 1))


def _dxt(f: Tensor) -> Tensor:
    # adjoint of _dx for f with a zero last column
    return F.pad(f[..., :, :-1], (1, 0)) - f


def _dyt(f: Tensor) -> Tensor:
    return F.pad(f[..., :-1, :], (0, 0, 1, 0)) - f


def _edge_masks(mask: Tensor) -> Tuple[Tensor, Tensor]:
    ex = F.pad(mask[..., :, 1:] & mask[..., :, :-1], (0, 1))
    ey = F.pad(mask[..., 1:, :] & mask[..., :-1, :], (0, 0, 0, 1))
    return ex, ey


def _edge_mean(x: Tensor, axis: str) -> Tensor:
    """Mean of a pixel field over the two ends of each edge (0 on the last column/row)."""
    if axis == "x":
        return F.pad(0.5 * (x[..., :, 1:] + x[..., :, :-1]), (0, 1))
    return F.pad(0.5 * (x[..., 1:, :] + x[..., :-1, :]), (0, 0, 0, 1))


class _Level:
    """One level of the aggregation hierarchy: ``A = Dx^T Wx Dx + Dy^T Wy Dy``."""

    def __init__(self, wx: Tensor, wy: Tensor):
        self.wx, self.wy = wx, wy
        diag = wx + F.pad(wx[..., :, :-1], (1, 0)) + wy + F.pad(wy[..., :-1, :], (0, 0, 1, 0))
        self.inv_diag = torch.where(diag > 0, 1.0 / diag.clamp_min(torch.finfo(diag.dtype).tiny), 0.0)

    def apply(self, x: Tensor) -> Tensor:
        return _dxt(self.wx * _dx(x)) + _dyt(self.wy * _dy(x))

    def coarsen(self) -> "_Level":
        h, w = self.wx.shape[-2:]
        pad = (0, w % 2, 0, h % 2)
        wx, wy = F.pad(self.wx, pad), F.pad(self.wy, pad)
        # Only edges that cross between 2x2 aggregates survive, their weights summed:
        # P^T A P of a piecewise-constant prolongation P is again a 4-neighbour Laplacian.
        wxc = wx[..., 0::2, 1::2] + wx[..., 1::2, 1::2]
        wyc = wy[..., 1::2, 0::2] + wy[..., 1::2, 1::2]
        return _Level(wxc, wyc)

    def dense(self) -> Tensor:
        """The level's matrix, :math:`(B, n, n)` with ``n = h w`` (coarsest level only)."""
        h, w = self.wx.shape[-2:]
        basis = torch.eye(h * w, dtype=self.wx.dtype, device=self.wx.device).reshape(1, h * w, h, w)
        cols = _dxt(self.wx[:, None] * _dx(basis)) + _dyt(self.wy[:, None] * _dy(basis))
        return cols.flatten(2).transpose(1, 2)


def _restrict(r: Tensor) -> Tensor:
    h, w = r.shape[-2:]
    r = F.pad(r, (0, w % 2, 0, h % 2))
    return r[..., 0::2, 0::2] + r[..., 0::2, 1::2] + r[..., 1::2, 0::2] + r[..., 1::2, 1::2]


def _prolong(e: Tensor, shape: torch.Size) -> Tensor:
    return e.repeat_interleave(2, -2).repeat_interleave(2, -1)[..., : shape[-2], : shape[-1]]


# devices whose linear algebra has float64; others (e.g. MPS) take the coarse level to the CPU
_FLOAT64_DEVICES = ("cpu", "cuda")


class _CoarseInverse:
    """Pseudo-inverse of one coarsest level, reusable for reweightings of the same mask.

    Singular (one constant per connected component): the pseudo-inverse ignores that.
    In float64: float32 eigh (LAPACK ssyevd) returned NaN eigenvectors for a real coarse
    level with many empty rows (tests/data/coarse_level_eigh_nan.npz). On the level's
    device where it has float64, else on the CPU.
    """

    def __init__(self, level: _Level):
        a = level.dense().detach()
        where = a.device if a.device.type in _FLOAT64_DEVICES else torch.device("cpu")
        pinv = torch.linalg.pinv(a.to(where, torch.float64), hermitian=True, rtol=1e-4)
        self.inv = pinv.to(a.device, a.dtype)
        self.trace = _level_trace(level)

    def scaled(self, level: _Level) -> Tensor:
        """The inverse for ``level`` (same mask, other weights): times the ratio of the traces."""
        trace = _level_trace(level)
        ratio = self.trace / trace.clamp_min(torch.finfo(trace.dtype).tiny)
        return self.inv * torch.where(trace > 0, ratio, 0.0)[:, None, None]


def _level_trace(level: _Level) -> Tensor:
    # trace of Dx^T Wx Dx + Dy^T Wy Dy: every edge weight counts at both of its pixels
    return 2.0 * (level.wx.detach().flatten(1).sum(1) + level.wy.detach().flatten(1).sum(1))


class _Multigrid:
    """Symmetric aggregation V-cycle used as the preconditioner of CG.

    ``coarse``: the coarsest level's inverse of an earlier problem on the same mask (the
    IRLS rounds of the L1 solver), rescaled by the ratio of the levels' traces instead
    of recomputed. Any positive semi-definite coarse solve with the level's nullspace
    keeps the V-cycle a symmetric positive definite preconditioner, so CG still
    converges to the same solution; only its iteration count can change.
    """

    def __init__(self, level: _Level, coarsest: int = 8, smooth: int = 1, omega: float = 0.7, boost: float = 1.6,
                 coarse: Optional[_CoarseInverse] = None):
        self.levels: List[_Level] = [level]
        while max(self.levels[-1].wx.shape[-2:]) > coarsest:
            self.levels.append(self.levels[-1].coarsen())
        if coarse is None:
            self.coarse = _CoarseInverse(self.levels[-1])
            self.coarse_inv = self.coarse.inv
        else:
            self.coarse = coarse
            self.coarse_inv = coarse.scaled(self.levels[-1])
        self.smooth, self.omega, self.boost = smooth, omega, boost

    def __call__(self, r: Tensor) -> Tensor:
        return self._cycle(0, r)

    def _cycle(self, k: int, r: Tensor) -> Tensor:
        lev = self.levels[k]
        if k == len(self.levels) - 1:
            b, h, w = r.shape
            return (self.coarse_inv @ r.reshape(b, h * w, 1)).reshape(b, h, w)
        x = self.omega * lev.inv_diag * r
        for _ in range(self.smooth - 1):
            x = x + self.omega * lev.inv_diag * (r - lev.apply(x))
        ec = self._cycle(k + 1, _restrict(r - lev.apply(x)))
        # plain aggregation under-corrects smooth errors; a fixed over-correction helps (Braess)
        x = x + self.boost * _prolong(ec, r.shape)
        for _ in range(self.smooth):
            x = x + self.omega * lev.inv_diag * (r - lev.apply(x))
        return x


def _pcg(level: _Level, precond: _Multigrid, b: Tensor, x0: Optional[Tensor], max_iter: int, tol: float) -> Tensor:
    """Batched preconditioned CG for ``level.apply(x) = b``; ``b``: (B, H, W)."""
    # a residual below the dtype's precision is never reached: CG would iterate on rounding
    # noise, which blows up instead of converging, until max_iter
    tol = max(tol, torch.finfo(b.dtype).eps)
    x = torch.zeros_like(b) if x0 is None else x0
    r = b - level.apply(x) if x0 is not None else b.clone()
    bnorm = b.flatten(1).norm(dim=1).clamp_min(torch.finfo(b.dtype).tiny)
    z = precond(r)
    p = z
    rz = (r * z).flatten(1).sum(1)
    for it in range(max_iter):
        # checked every step: iterating on past machine precision makes CG blow up
        if bool(((r.flatten(1).norm(dim=1) / bnorm) <= tol).all()):
            logger.debug("integrability CG converged in %d iterations", it)
            break
        ap = level.apply(p)
        pap = (p * ap).flatten(1).sum(1)
        alpha = torch.where(pap > 0, rz / pap.clamp_min(torch.finfo(b.dtype).tiny), 0.0)[:, None, None]
        x = x + alpha * p
        r = r - alpha * ap
        z = precond(r)
        rz_new = (r * z).flatten(1).sum(1)
        beta = torch.where(rz > 0, rz_new / rz.clamp_min(torch.finfo(b.dtype).tiny), 0.0)[:, None, None]
        p = z + beta * p
        rz = rz_new
    else:
        rel = r.flatten(1).norm(dim=1) / bnorm
        if bool((rel <= tol).all()):
            return x
        if not bool(torch.isfinite(rel).all()):
            raise FloatingPointError("integrability solve diverged to NaN/inf; please report the input that caused it")
        logger.warning("integrability CG stopped after %d iterations at relative residual %.2e", max_iter, float(rel.max()))
    return x


# ----------------------------------------------------------------------------- components


def mask_components(mask: Tensor) -> Tensor:
    """Label the 4-connected components of a mask.

    Args:
        mask: :math:`(B, 1, H, W)` bool.

    Returns:
        :math:`(B, 1, H, W)` int64: for each object pixel the flat index ``i * W + j`` of
        the first pixel of its component, ``-1`` outside the mask.
    """
    b, _, h, w = mask.shape
    m = mask[:, 0]
    big = h * w
    idx = torch.arange(big, device=mask.device).reshape(1, h, w).expand(b, h, w)
    lab = torch.where(m, idx, big)
    ex, ey = _edge_masks(m)
    while True:
        # hook each pixel to its smallest neighbouring label, then jump pointers
        nb = torch.minimum(lab, torch.where(ex, F.pad(lab[:, :, 1:], (0, 1), value=big), big))
        nb = torch.minimum(nb, torch.where(F.pad(ex[:, :, :-1], (1, 0)), F.pad(lab[:, :, :-1], (1, 0), value=big), big))
        nb = torch.minimum(nb, torch.where(ey, F.pad(lab[:, 1:, :], (0, 0, 0, 1), value=big), big))
        nb = torch.minimum(nb, torch.where(F.pad(ey[:, :-1, :], (0, 0, 1, 0)), F.pad(lab[:, :-1, :], (0, 0, 1, 0), value=big), big))
        flat = torch.where(m, nb, 0).flatten(1)
        for _ in range(4):
            flat = torch.minimum(flat, flat.gather(1, flat))
        new = torch.where(m, flat.reshape(b, h, w), big)
        if torch.equal(new, lab):
            break
        lab = new
    return torch.where(m, lab, -1)[:, None]


def _component_mean(x: Tensor, labels: Tensor, weights: Optional[Tensor] = None) -> Tensor:
    """Per-pixel mean of ``x`` (B, H, W) over its component (labels (B, H, W), -1 outside)."""
    b, h, w = x.shape
    inside = labels >= 0
    lab = labels.clamp_min(0).flatten(1)
    wt = inside.to(x.dtype) if weights is None else weights * inside
    sums = torch.zeros(b, h * w, dtype=x.dtype, device=x.device).scatter_add(1, lab, (x * wt).flatten(1))
    cnt = torch.zeros(b, h * w, dtype=x.dtype, device=x.device).scatter_add(1, lab, wt.flatten(1))
    mean = sums.gather(1, lab) / cnt.gather(1, lab).clamp_min(torch.finfo(x.dtype).tiny)
    return torch.where(inside, mean.reshape(b, h, w), 0.0)


def _project(x: Tensor, labels: Tensor) -> Tensor:
    return torch.where(labels >= 0, x - _component_mean(x, labels), 0.0)


# ----------------------------------------------------------------------------- linear solve


class _Problem:
    """Weighted least squares ``min_s |Wx^½(Dx s - tx)|² + |Wy^½(Dy s - ty)|²`` on one mask."""

    def __init__(self, wx: Tensor, wy: Tensor, labels: Tensor, max_iter: int, tol: float,
                 coarse: Optional[_CoarseInverse] = None):
        self.level = _Level(wx, wy)
        self.precond = _Multigrid(self.level, coarse=coarse)
        self.labels, self.max_iter, self.tol = labels, max_iter, tol

    def solve(self, b: Tensor, x0: Optional[Tensor] = None) -> Tensor:
        return _project(_pcg(self.level, self.precond, b, x0, self.max_iter, self.tol), self.labels)


class _Solve(torch.autograd.Function):
    """``s = argmin`` of the weighted problem; backward by implicit differentiation."""

    @staticmethod
    def forward(ctx, tx, ty, wx, wy, problem: _Problem, x0):
        s = problem.solve(_dxt(wx * tx) + _dyt(wy * ty), x0)
        ctx.problem = problem
        ctx.save_for_backward(tx, ty, wx, wy, s)
        return s

    @staticmethod
    def backward(ctx, grad):
        tx, ty, wx, wy, s = ctx.saved_tensors
        # s is projected to zero mean per component, so only the projected gradient matters
        lam = ctx.problem.solve(_project(grad, ctx.problem.labels))
        lx, ly = _dx(lam), _dy(lam)
        return wx * lx, wy * ly, lx * (tx - _dx(s)), ly * (ty - _dy(s)), None, None


# ----------------------------------------------------------------------------- normals <-> gradients


def _gradients(normals: Tensor, focal: Optional[float], principal_point, min_nz: float) -> Tuple[Tensor, Tensor, Tensor]:
    """Per-pixel ``(g_u, g_v)`` of height (orthographic) or log-depth (perspective), and the
    positive factor ``c`` with ``g = (normal components) / c``; each (..., H, W)."""
    nx, ny, nz = normals.unbind(-3)
    if focal is None:
        nz = nz.clamp_min(min_nz)
        return -nx / nz, -ny / nz, nz
    h, w = normals.shape[-2:]
    u, v = pixel_grid(h, w, principal_point, device=normals.device, dtype=normals.dtype)
    k_min = min_nz * torch.sqrt(focal * focal + u * u + v * v)
    k = (focal * nz - u * nx - v * ny).clamp_min(k_min)
    return nx / k, ny / k, k / focal


def _edge_targets(gu: Tensor, gv: Tensor, ex: Tensor, ey: Tensor) -> Tuple[Tensor, Tensor]:
    return _edge_mean(gu, "x") * ex, -_edge_mean(gv, "y") * ey


def _edge_weights(weights: Tensor, ex: Tensor, ey: Tensor) -> Tuple[Tensor, Tensor]:
    # harmonic mean of the two pixels' confidences: one unreliable pixel is enough to
    # make an edge unreliable, and equal confidences keep their value
    def harmonic(a: Tensor, b: Tensor) -> Tensor:
        return 2.0 * a * b / (a + b).clamp_min(torch.finfo(a.dtype).tiny)

    wx = F.pad(harmonic(weights[..., :, 1:], weights[..., :, :-1]), (0, 1))
    wy = F.pad(harmonic(weights[..., 1:, :], weights[..., :-1, :]), (0, 0, 0, 1))
    return wx * ex, wy * ey


def _surface(s: Tensor, mask: Tensor, focal, principal_point) -> Surface:
    """Surface from the integrated field ``s`` (B, H, W), already zero mean per component."""
    m = mask[:, 0]
    depth = s if focal is None else torch.where(m, torch.exp(s), 0.0)
    depth = depth[:, None]
    return Surface(depth=depth, normals=depth_to_normals(depth, mask, focal, principal_point))


def _check_inputs(normals: Tensor, mask: Tensor, weights: Optional[Tensor], name: str, spec: str) -> Tuple[Tensor, Optional[Tensor]]:
    """The bool mask, and the weights in the normals' dtype (which the solve mixes)."""
    check_shape(normals, name, spec)
    check_finite(normals, name)
    mask = check_mask(mask, allow_full=True)
    check_same_size(normals, name, mask, "mask")
    if weights is not None:
        check_shape(weights, "weights", "B 1 H W")
        check_same_size(normals, name, weights, "weights")
        check_finite(weights, "weights")
        if bool((weights < 0).any()):
            raise ValueError("weights must be non-negative")
        weights = weights.to(normals.dtype)
    return mask, weights


def _working_dtype(x: Tensor) -> Tensor:
    """``x`` in the dtype the solve runs in: half precision in float32, whose ~1e-3 (float16)
    or ~1e-2 (bfloat16) relative rounding left the conjugate gradients far from the solution."""
    return x.float() if x.is_floating_point() and torch.finfo(x.dtype).bits < 32 else x


# ----------------------------------------------------------------------------- public API


def integrate_normals(
    normals: Tensor,
    mask: Tensor,
    *,
    method: str = IntegrabilityConfig.method,
    weights: Optional[Tensor] = None,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    max_iter: int = IntegrabilityConfig.max_iter,
    tol: float = IntegrabilityConfig.tol,
    min_nz: float = IntegrabilityConfig.min_nz,
    l1_iter: int = IntegrabilityConfig.l1_iter,
    l1_delta: float = IntegrabilityConfig.l1_delta,
    **conv_options,
) -> Surface:
    r"""Integrate a normal field into a surface on the mask.

    Args:
        normals: camera-frame unit normals, :math:`(B, 3, H, W)` or :math:`(3, H, W)`;
            for ``method="conv"`` candidate normals :math:`(B, S, 3, H, W)` (see
            :func:`integrate_convex`).
        mask: :math:`(B, 1, H, W)`, :math:`(1, H, W)` or :math:`(H, W)`, bool or 0/1.
        method: ``"l2"``, ``"l1"`` (IRLS on a smoothed L1 penalty) or ``"conv"``.
        weights: per-pixel confidence :math:`(B, 1, H, W)` (e.g. the forest's kappa),
            non-negative; an edge weighs the harmonic mean of its two pixels. Zero
            weights can cut a component apart, leaving the pieces' offsets arbitrary.
        focal: focal length in pixels (perspective, log-depth); ``None``: orthographic.
        principal_point: ``(cx, cy)`` in pixels; default image centre.
        max_iter: conjugate-gradient iterations per solve.
        tol: relative residual of each conjugate-gradient solve.
        min_nz: normals more grazing than this cosine to the view ray are clamped.
        l1_iter: IRLS rounds of the L1 variant; 0 and 1 both give the plain weighted L2
            solve (the first round).
        l1_delta: smoothing of the L1 variant.
        conv_options: ``conv_iter``, ``conv_prior`` for ``"conv"``.

    Returns:
        :class:`Surface` with ``depth`` :math:`(B, 1, H, W)` and refined ``normals``
        :math:`(B, 3, H, W)` (no batch axis for unbatched input). Differentiable with
        respect to ``normals`` and ``weights`` (implicit differentiation of the linear
        solve; for ``"l1"`` through the last reweighted solve with its weights fixed).
        Half-precision normals are integrated in float32; the result has their dtype.
        ``tol`` is floored at the machine epsilon of the working dtype.

    Raises:
        ValueError: an option out of range (:func:`check_integrability_config`), wrong
            shapes, non-finite values, negative weights, or a focal length or principal
            point that is not finite and positive, or not two finite numbers.

    Example:
        >>> n = torch.zeros(1, 3, 8, 8); n[:, 2] = 1.0
        >>> integrate_normals(n, torch.ones(1, 1, 8, 8, dtype=torch.bool)).depth.abs().max()
        tensor(0.)
    """
    check_integrability_config(IntegrabilityConfig(
        method=method, max_iter=max_iter, tol=tol, min_nz=min_nz, l1_iter=l1_iter, l1_delta=l1_delta,
    ))
    if method == "conv":
        return integrate_convex(
            normals, mask, weights=weights, focal=focal, principal_point=principal_point,
            max_iter=max_iter, tol=tol, min_nz=min_nz, **conv_options,
        )
    if conv_options:
        raise ValueError(f"unknown options for method {method!r}: {sorted(conv_options)}")
    normals, single = to_batch(normals, "normals", 3)
    mask, _ = to_batch(mask, "mask", 1)
    if weights is not None:
        weights, _ = to_batch(weights, "weights", 1)
    focal, principal_point = _check_camera(focal, principal_point)
    dtype = normals.dtype
    normals = _working_dtype(normals)
    mask, weights = _check_inputs(normals, mask, weights, "normals", "B 3 H W")
    if mask.device != normals.device:
        raise ValueError(f"mask is on {mask.device} but normals on {normals.device}")
    m = mask[:, 0]
    labels = mask_components(mask)[:, 0]
    ex, ey = _edge_masks(m)
    gu, gv, _ = _gradients(normals, focal, principal_point, min_nz)
    tx, ty = _edge_targets(gu, gv, ex, ey)
    w = m.to(normals.dtype) if weights is None else weights[:, 0]
    wx, wy = _edge_weights(w, ex, ey)
    s, coarse = None, None
    # the first round is the plain weighted L2 solve, so no IRLS round at all means that one
    rounds = max(l1_iter, 1) if method == "l1" else 1
    for it in range(rounds):
        ax, ay = wx, wy
        if method == "l1" and s is not None:
            # IRLS for sum w |r|: weight w / sqrt(r^2 + delta^2), from the current residuals
            rx, ry = (_dx(s) - tx).detach(), (_dy(s) - ty).detach()
            ax = wx * torch.rsqrt(rx * rx + l1_delta**2) * l1_delta
            ay = wy * torch.rsqrt(ry * ry + l1_delta**2) * l1_delta
        # the coarse pseudo-inverse once per mask: later rounds rescale the first one's
        problem = _Problem(ax.detach(), ay.detach(), labels, max_iter, tol, coarse=coarse)
        coarse = problem.precond.coarse
        last = it == rounds - 1
        x0 = None if s is None else s.detach()
        s = _Solve.apply(tx, ty, ax, ay, problem, x0) if last else problem.solve(
            _dxt(ax * tx.detach()) + _dyt(ay * ty.detach()), x0
        )
    return _result(_surface(s, mask, focal, principal_point), dtype, single)


def _result(out: Surface, dtype: torch.dtype, single: bool) -> Surface:
    """``out`` in the input's dtype, without the batch axis for unbatched input."""
    return Surface(depth=from_batch(out.depth.to(dtype), single), normals=from_batch(out.normals.to(dtype), single))


def _project_simplex(a: Tensor, dim: int) -> Tensor:
    """Euclidean projection onto the probability simplex along ``dim``."""
    srt, _ = torch.sort(a, dim=dim, descending=True)
    css = srt.cumsum(dim) - 1.0
    shape = [1] * a.ndim
    shape[dim] = a.shape[dim]
    k = torch.arange(1, a.shape[dim] + 1, device=a.device, dtype=a.dtype).reshape(shape)
    cond = srt - css / k > 0
    rho = cond.to(a.dtype).cumsum(dim).argmax(dim, keepdim=True)
    theta = css.gather(dim, rho) / (rho + 1).to(a.dtype)
    return (a - theta).clamp_min(0.0)


def integrate_convex(
    candidates: Tensor,
    mask: Tensor,
    *,
    weights: Optional[Tensor] = None,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    max_iter: int = IntegrabilityConfig.max_iter,
    tol: float = IntegrabilityConfig.tol,
    min_nz: float = IntegrabilityConfig.min_nz,
    conv_iter: int = IntegrabilityConfig.conv_iter,
    conv_prior: float = IntegrabilityConfig.conv_prior,
) -> Surface:
    r"""Most integrable convex combination of candidate normals per pixel (paper Sec. 5).

    Each pixel's normal is a convex combination of its ``S`` candidates (e.g. samples
    the caller drew from the forest's leaf distributions). We parametrise it in gradient
    space: ``g = sum_s alpha_s g_s`` with ``alpha`` on the simplex and ``g_s`` the
    candidates' height (log-depth) gradients. Because ``g_s`` is the candidate normal
    divided by a positive per-candidate factor, ``sum_s alpha_s g_s`` is the gradient of
    the normalised non-negative combination ``sum_s beta_s n_s`` with
    ``beta_s ∝ alpha_s / c_s``: exactly the convex hull directions of the candidates.
    The weights start at ``alpha0_s ∝ c_s``, the (normalised) mean of the candidate
    normals, and the energy ``E(s, alpha) = sum_edges w (D s - t(alpha))^2 + conv_prior
    sum_pixels w |alpha - alpha0|^2`` is jointly convex. We minimise
    ``min_s E(s, alpha)`` over ``alpha`` by FISTA (accelerated projected gradient onto the
    simplex, per-pixel Lipschitz step); each step is one warm-started L2 solve for ``s``.

    Args:
        candidates: unit normals :math:`(B, S, 3, H, W)` or :math:`(S, 3, H, W)`.
        mask: :math:`(B, 1, H, W)` bool or 0/1.
        weights: per-pixel confidence :math:`(B, 1, H, W)`.
        focal: camera, as in :func:`integrate_normals`.
        principal_point: camera, as in :func:`integrate_normals`.
        conv_iter: FISTA steps on the weights;
        conv_prior: pull towards the candidates' mean (relative to edge weights).

    Returns:
        :class:`Surface` of the final combination; ``depth`` is differentiable with
        respect to ``candidates`` through the last solve (combination weights fixed).
        Half precision is computed in float32, as in :func:`integrate_normals`.

    Raises:
        ValueError: as :func:`integrate_normals`.
    """
    check_integrability_config(IntegrabilityConfig(
        method="conv", max_iter=max_iter, tol=tol, min_nz=min_nz, conv_iter=conv_iter, conv_prior=conv_prior,
    ))
    candidates, single = to_batch(candidates, "candidates", None, ndim_single=4)
    mask, _ = to_batch(mask, "mask", 1)
    if weights is not None:
        weights, _ = to_batch(weights, "weights", 1)
    if candidates.ndim != 5 or candidates.shape[2] != 3:
        raise ValueError(f"candidates must have shape (B, S, 3, H, W), got {tuple(candidates.shape)}")
    check_finite(candidates, "candidates")
    focal, principal_point = _check_camera(focal, principal_point)
    dtype = candidates.dtype
    candidates = _working_dtype(candidates)
    mask, weights = _check_inputs(candidates[:, 0], mask, weights, "candidates", "B 3 H W")
    m = mask[:, 0]
    labels = mask_components(mask)[:, 0]
    ex, ey = _edge_masks(m)
    gu, gv, factor = _gradients(candidates, focal, principal_point, min_nz)  # (B, S, H, W)
    gu_d, gv_d = gu.detach(), gv.detach()
    # start from (and regularise towards) the normalised mean of the candidate normals:
    # in gradient space its weights are proportional to the factors c_s
    factor = factor.detach()
    prior = factor / factor.sum(1, keepdim=True).clamp_min(torch.finfo(factor.dtype).tiny)
    w = m.to(candidates.dtype) if weights is None else weights[:, 0]
    wx, wy = _edge_weights(w, ex, ey)
    problem = _Problem(wx, wy, labels, max_iter, tol)
    alpha = prior
    # Lipschitz bound of the alpha-gradient per pixel (Gershgorin over the edge coupling)
    wsum = wx + F.pad(wx[..., :, :-1], (1, 0)) + wy + F.pad(wy[..., :-1, :], (0, 0, 1, 0))
    lip = wsum * (gu_d * gu_d + gv_d * gv_d).sum(1) + 2.0 * conv_prior * w
    step = torch.where(lip > 0, 1.0 / lip.clamp_min(torch.finfo(lip.dtype).tiny), 0.0)[:, None]
    s, y, momentum = None, alpha, 1.0
    for _ in range(conv_iter):
        # FISTA on the reduced objective E(alpha) = min_s E(s, alpha): by Danskin's theorem
        # its gradient is the partial gradient at the optimal s, one warm-started solve per step
        tx, ty = _edge_targets((y * gu_d).sum(1), (y * gv_d).sum(1), ex, ey)
        s = problem.solve(_dxt(wx * tx) + _dyt(wy * ty), s)
        # dE/dt on edges, spread back to the two pixels of each edge (adjoint of _edge_mean)
        fx, fy = -2.0 * wx * (_dx(s) - tx), -2.0 * wy * (_dy(s) - ty)
        du = 0.5 * (fx + F.pad(fx[..., :, :-1], (1, 0)))
        dv = -0.5 * (fy + F.pad(fy[..., :-1, :], (0, 0, 1, 0)))
        grad = du[:, None] * gu_d + dv[:, None] * gv_d + 2.0 * conv_prior * w[:, None] * (y - prior)
        new = _project_simplex(y - step * grad, 1)
        next_momentum = 0.5 * (1.0 + (1.0 + 4.0 * momentum * momentum) ** 0.5)
        y = new + ((momentum - 1.0) / next_momentum) * (new - alpha)
        alpha, momentum = new, next_momentum
    tx, ty = _edge_targets((alpha * gu).sum(1), (alpha * gv).sum(1), ex, ey)
    s = _Solve.apply(tx, ty, wx, wy, problem, s)
    return _result(_surface(s, mask, focal, principal_point), dtype, single)


_OFFSETS = (-2, -1, 0, 1, 2)


def _stencil(m: Tensor, dim: int) -> Tensor:
    """Coefficients of the derivative along ``dim`` (-1: columns, -2: rows, increasing index)
    on the mask ``m`` (B, H, W) bool: (5, B, H, W), one map per offset of :data:`_OFFSETS`.

    Central where both neighbours lie in the mask, else second-order one-sided, else
    first-order one-sided, else 0 (and 0 off the mask); exact for quadratics, like the
    solver's edge rule. The rule depends on the mask alone, so an inner loop computes it once.
    """

    def inside(k: int) -> Tensor:
        # whether the pixel at index + k lies in the mask (not beyond the border)
        n = m.shape[dim]
        if abs(k) >= n:
            return torch.zeros_like(m)
        if k > 0:
            return F.pad(m.narrow(dim, k, n - k), _pad_arg(dim, 0, k))
        return F.pad(m.narrow(dim, 0, n + k), _pad_arg(dim, -k, 0))

    has = {k: inside(k) for k in (-2, -1, 1, 2)}
    rules = [  # in order of preference: where each rule can apply, its coefficients of offsets -2 .. 2
        (has[1] & has[-1], (0.0, -0.5, 0.0, 0.5, 0.0)), (has[1] & has[2], (0.0, 0.0, -1.5, 2.0, -0.5)),
        (has[-1] & has[-2], (0.5, -2.0, 1.5, 0.0, 0.0)), (has[1], (0.0, 0.0, -1.0, 1.0, 0.0)),
        (has[-1], (0.0, -1.0, 1.0, 0.0, 0.0)),
    ]
    coefficients = torch.zeros(len(_OFFSETS), *m.shape, device=m.device)
    free = m.clone()  # mask pixels no earlier rule took
    for where, values in rules:
        where = where & free
        coefficients += torch.tensor(values, device=m.device)[:, None, None, None] * where
        free &= ~where
    return coefficients


def _apply_stencil(s: Tensor, coefficients: Tensor, dim: int) -> Tensor:
    """The derivative of ``s`` (B, H, W) whose :func:`_stencil` along ``dim`` is ``coefficients``."""
    padded = F.pad(s, _pad_arg(dim, 2, 2))
    n = s.shape[dim]
    shifted = torch.stack([padded.narrow(dim, 2 + k, n) for k in _OFFSETS])
    return (coefficients * shifted).sum(0)


def _pad_arg(dim: int, before: int, after: int) -> Tuple[int, ...]:
    # F.pad lists (before, after) pairs from the last dimension backwards
    pads = [0, 0] * (-dim)
    pads[-2] = before
    pads[-1] = after
    return tuple(pads)


def depth_to_normals(
    depth: Tensor, mask: Tensor, focal: Optional[float] = None, principal_point: Optional[Sequence[float]] = None
) -> Tensor:
    r"""Unit normals of a depth map, with the finite differences the solver assumes.

    Args:
        depth: :math:`(B, 1, H, W)`; orthographic: height towards the viewer in pixels;
            perspective: positive distance along the optical axis (scale irrelevant).
        mask: :math:`(B, 1, H, W)` bool or 0/1.
        focal: focal length in pixels; ``None`` is orthographic.
        principal_point: ``(cx, cy)`` in pixels; default image centre.

    Returns:
        :math:`(B, 3, H, W)` camera-frame unit normals (``n_z > 0``), 0 outside the mask.
    """
    depth, single = to_batch(depth, "depth", 1)
    mask, _ = to_batch(mask, "mask", 1)
    check_shape(depth, "depth", "B 1 H W")
    mask = check_mask(mask, allow_full=True)
    check_same_size(depth, "depth", mask, "mask")
    focal, principal_point = _check_camera(focal, principal_point)
    m = mask[:, 0]
    if focal is None:
        s = torch.where(m, depth[:, 0], 0.0)
    else:
        if bool((depth[:, 0][m] <= 0).any()):
            raise ValueError("depth must be positive on the mask under perspective projection")
        s = torch.where(m, torch.log(torch.where(m, depth[:, 0], 1.0)), 0.0)
    return from_batch(field_normals(s, m, focal, principal_point), single)


def bas_relief_normals(normals: Tensor, scale: Union[float, Tensor], tilt_x: Union[float, Tensor] = 0.0,
                       tilt_y: Union[float, Tensor] = 0.0) -> Tensor:
    r"""Normals of an orthographic surface after a generalised bas-relief transform.

    The surface ``z`` becomes ``scale * z + tilt_x * x + tilt_y * y`` (``x`` right, ``y``
    up, in pixels): its normals are ``normalize(scale n_x - tilt_x n_z, scale n_y - tilt_y n_z, n_z)``.
    Under orthographic projection the transform, with the lighting transformed alike,
    changes the shading of a uniform-albedo object only through an albedo factor
    (Belhumeur et al. 1999).

    Args:
        normals: :math:`(B, 3, H, W)` or :math:`(3, H, W)` camera-frame normals (0 where
            there is no surface).
        scale: a number, or a :math:`(B,)` tensor for one transform per image (differentiable).
        tilt_x: likewise.
        tilt_y: likewise.

    Returns:
        unit normals of the same shape, 0 where ``normals`` is 0.
    """
    normals, single = to_batch(normals, "normals", 3)
    check_shape(normals, "normals", "B 3 H W")
    params = []
    for name, value in (("scale", scale), ("tilt_x", tilt_x), ("tilt_y", tilt_y)):
        if isinstance(value, Tensor) and value.numel() not in (1, normals.shape[0]):
            raise ValueError(f"{name} must be a number or hold one value per image ({normals.shape[0]}), "
                             f"got shape {tuple(value.shape)}")
        params.append(torch.as_tensor(value, dtype=normals.dtype, device=normals.device).reshape(-1, 1, 1))
    s, tx, ty = params
    x, y, z = normals.unbind(1)
    return from_batch(F.normalize(torch.stack([s * x - tx * z, s * y - ty * z, z], 1), dim=1), single)


def median_slope(normals: Tensor, mask: Tensor) -> Tensor:
    r"""Median over each object of its surface slope ``|(n_x, n_y)| / n_z`` (orthographic).

    A bas-relief scale ``s`` multiplies every pixel's slope by ``s`` (:func:`bas_relief_normals`),
    so it multiplies this median by ``s`` too. ``n_z`` is floored at 1e-3: the rim's
    normals lie in the image plane, and the median does not depend on how large their slope reads.

    Args:
        normals: :math:`(B, 3, H, W)` or :math:`(3, H, W)` camera-frame normals.
        mask: :math:`(B, 1, H, W)` or :math:`(1, H, W)` bool, none empty.

    Returns:
        :math:`(B,)`, or a 0-d tensor for unbatched input.
    """
    normals, single = to_batch(normals, "normals", 3)
    mask, _ = to_batch(mask, "mask", 1)
    check_shape(normals, "normals", "B 3 H W")
    mask = check_mask(mask, allow_full=True)
    check_same_size(normals, "normals", mask, "mask")
    slope = normals[:, :2].norm(dim=1) / normals[:, 2].clamp_min(1e-3)
    out = torch.stack([slope[b][mask[b, 0]].median() for b in range(len(slope))])
    return out[0] if single else out


def field_normals(s: Tensor, m: Tensor, focal: Optional[float], principal_point: Optional[Sequence[float]]) -> Tensor:
    """Unit normals of the integrated field ``s`` (height, or log-depth with ``focal``).

    Unchecked; :func:`depth_to_normals` is the checked public form and
    ``_FieldNormals`` the form for inner loops (:mod:`sfs_torch.refine`). ``s`` and
    ``m`` are :math:`(B, H, W)`; returns :math:`(B, 3, H, W)`.
    """
    return _FieldNormals(m, focal, principal_point, s.dtype)(s)


class _FieldNormals:
    """:func:`field_normals` on one mask ``m`` (B, H, W) bool, camera and dtype, for many fields:
    what depends on the mask and camera alone (the derivatives' stencils, the pixel grid) is
    computed once, not in every step of the refinement's inner loop."""

    def __init__(self, m: Tensor, focal: Optional[float], principal_point: Optional[Sequence[float]],
                 dtype: torch.dtype):
        self.inside, self.focal = m[:, None].to(dtype), focal
        self.along_u, self.along_v = (_stencil(m, dim).to(dtype) for dim in (-1, -2))
        self.grid = None if focal is None else pixel_grid(*m.shape[-2:], principal_point, device=m.device, dtype=dtype)

    def __call__(self, s: Tensor) -> Tensor:
        gu = _apply_stencil(s, self.along_u, -1)
        gv = -_apply_stencil(s, self.along_v, -2)  # rows grow downwards, v upwards
        if self.focal is None:
            n = torch.stack([-gu, -gv, torch.ones_like(gu)], 1)
        else:
            u, v = self.grid
            n = torch.stack([self.focal * gu, self.focal * gv, 1.0 + u * gu + v * gv], 1)
        return _unit(n) * self.inside  # a product: where() took several times as long, forward and backward


def _unit(v: Tensor) -> Tensor:
    """``v`` divided by its length along dim 1: :math:`(B, C, H, W) -> (B, C, H, W)`.

    The length is the root of a sum over the channels: ``Tensor.norm`` across them (and
    ``F.normalize``) took 2-9x as long, forward and backward, in the refinement's inner
    loop. The sum is clamped before the root, so a zero vector (the background) maps to 0
    with a finite gradient.
    """
    return v / torch.sqrt((v * v).sum(1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny))


def depth_to_mesh(
    depth: Tensor, mask: Tensor, focal: Optional[float] = None, principal_point: Optional[Sequence[float]] = None
):
    r"""Triangle mesh of one depth map in the camera frame.

    Vertices are the mask pixels: orthographic ``(u, v, depth)``, perspective
    ``depth * (u / f, v / f, -1)``. Every 2x2 block of pixels gives two triangles when
    all four lie in the mask and one when three do; faces wind counter-clockwise as seen
    from the camera, so their normals face the viewer.

    Args:
        depth: :math:`(1, H, W)` or :math:`(H, W)` (or :math:`(1, 1, H, W)`).
        mask: same size, bool or 0/1.

    Returns:
        ``trimesh.Trimesh`` (float64 vertices, not processed/merged).
    """
    import trimesh

    if not isinstance(depth, Tensor):
        raise TypeError(f"depth must be a torch.Tensor, got {type(depth).__name__}")
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask must be a torch.Tensor, got {type(mask).__name__}")
    d = depth.reshape(depth.shape[-2:]) if depth.ndim >= 2 and depth[..., 0, 0].numel() == 1 else None
    mk = mask.reshape(mask.shape[-2:]) if mask.ndim >= 2 and mask[..., 0, 0].numel() == 1 else None
    if d is None or mk is None or d.shape != mk.shape:
        raise ValueError(f"depth and mask must be one (H, W) or (1, H, W) map each, got {tuple(depth.shape)} and {tuple(mask.shape)}")
    mk = check_mask(mk[None, None], allow_full=True)[0, 0]
    focal, principal_point = _check_camera(focal, principal_point)
    h, w = d.shape
    d = d.detach().to("cpu", torch.float64)
    mk = mk.cpu()
    u, v = pixel_grid(h, w, principal_point, dtype=torch.float64)
    if focal is None:
        verts = torch.stack([u, v, d], -1)
    else:
        verts = d[..., None] * torch.stack([u / focal, v / focal, -torch.ones_like(u)], -1)
    index = torch.full((h, w), -1, dtype=torch.long)
    index[mk] = torch.arange(int(mk.sum()))
    a, b, c, e = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]  # tl, tr, bl, br
    # Counter-clockwise in (u, v) (v up): bl -> br -> tr and bl -> tr -> tl, etc.
    full = (a >= 0) & (b >= 0) & (c >= 0) & (e >= 0)
    tris = [
        torch.stack([c, e, b], -1)[full], torch.stack([c, b, a], -1)[full],
        torch.stack([c, e, b], -1)[~full & (c >= 0) & (e >= 0) & (b >= 0)],
        torch.stack([c, b, a], -1)[~full & (c >= 0) & (b >= 0) & (a >= 0)],
        torch.stack([c, e, a], -1)[~full & (c >= 0) & (e >= 0) & (a >= 0)],
        torch.stack([e, b, a], -1)[~full & (e >= 0) & (b >= 0) & (a >= 0)],
    ]
    faces = torch.cat(tris, 0)
    return trimesh.Trimesh(vertices=verts[mk].numpy(), faces=faces.numpy(), process=False)


class Integrator(nn.Module):
    """Thin module around :func:`integrate_normals`; stores the options.

    ``forward(normals, mask, weights=None)`` takes :math:`(B, 3, H, W)` normals, or
    :math:`(B, S, 3, H, W)` candidates when ``method="conv"``.

    Raises:
        ValueError: an option out of range, named (:func:`check_integrability_config`), or
            a bad ``focal`` or ``principal_point``.
    """

    def __init__(
        self,
        method: str = IntegrabilityConfig.method,
        max_iter: int = IntegrabilityConfig.max_iter,
        tol: float = IntegrabilityConfig.tol,
        min_nz: float = IntegrabilityConfig.min_nz,
        l1_iter: int = IntegrabilityConfig.l1_iter,
        l1_delta: float = IntegrabilityConfig.l1_delta,
        conv_iter: int = IntegrabilityConfig.conv_iter,
        conv_prior: float = IntegrabilityConfig.conv_prior,
        focal: Optional[float] = None,
        principal_point: Optional[Sequence[float]] = None,
    ):
        super().__init__()
        # "none" is the pipeline's choice not to integrate (integrate=none): it builds no Integrator
        check_integrability_config(IntegrabilityConfig(
            method=method, max_iter=max_iter, tol=tol, min_nz=min_nz, l1_iter=l1_iter, l1_delta=l1_delta,
            conv_iter=conv_iter, conv_prior=conv_prior,
        ))
        self.method, self.max_iter, self.tol, self.min_nz = method, max_iter, tol, min_nz
        self.l1_iter, self.l1_delta = l1_iter, l1_delta
        self.conv_iter, self.conv_prior = conv_iter, conv_prior
        self.focal, self.principal_point = _check_camera(focal, principal_point)

    def forward(self, normals: Tensor, mask: Tensor, weights: Optional[Tensor] = None) -> Surface:
        common = dict(weights=weights, focal=self.focal, principal_point=self.principal_point,
                      max_iter=self.max_iter, tol=self.tol, min_nz=self.min_nz)
        if self.method == "conv":
            return integrate_convex(normals, mask, conv_iter=self.conv_iter,
                                    conv_prior=self.conv_prior, **common)
        return integrate_normals(normals, mask, method=self.method, l1_iter=self.l1_iter,
                                 l1_delta=self.l1_delta, **common)


class DepthToNormals(nn.Module):
    """Unit normals of depth maps (module form of :func:`depth_to_normals`); stores the camera.

    Differentiable in ``depth`` (the finite differences depend on the mask alone).

    Args:
        focal: focal length in pixels, ``None`` for an orthographic camera (``depth`` is
            then the height towards the viewer; with ``focal``, the positive distance
            along the optical axis).
        principal_point: ``(cx, cy)`` in pixels; default the image centre.

    ``forward(depth, mask)``: depth and mask :math:`(B, 1, H, W)` (or :math:`(1, H, W)`,
    :math:`(H, W)`); returns :math:`(B, 3, H, W)` unit normals, 0 outside the mask.

    Example:
        >>> DepthToNormals()(torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 4)).shape
        torch.Size([1, 3, 4, 4])
    """

    def __init__(self, focal: Optional[float] = None, principal_point: Optional[Sequence[float]] = None):
        super().__init__()
        self.focal, self.principal_point = _check_camera(focal, principal_point)

    def forward(self, depth: Tensor, mask: Tensor) -> Tensor:
        return depth_to_normals(depth, mask, self.focal, self.principal_point)

    def extra_repr(self) -> str:
        return f"focal={self.focal}, principal_point={self.principal_point}"
