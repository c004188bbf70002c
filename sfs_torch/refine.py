r"""Photometric refinement: normals (and a lighting) that explain the image (not in the paper).

The forest predicts every pixel on its own, for one lighting. This stage fits the
normals to the image itself, with torch autograd (L-BFGS), starting from the forest's
normals and the lighting they were predicted for. Two models of the normals:

- ``model="pixel"``: one free unit normal per pixel, the lighting held fixed.
  Self-occluding objects (a leg in front of a body) keep their depth discontinuities;
- ``model="surface"``: the normals of one integrable field ``s`` (height, orthographic,
  or log-depth, perspective; :func:`sfs_torch.integrability.field_normals`), started
  from the kappa-weighted L2 integration of the forest's normals, optionally with the
  lighting refined jointly. It gives a depth map, but cannot represent discontinuities;
- ``model="auto"`` (default): the surface model when the lighting is refined
  (``optimise_lighting``), the pixel model when it is held fixed. Free per-pixel
  normals could explain any image under a wrong lighting, so fitting the lighting
  needs the integrable surface; with a lighting held fixed the pixel model fits closer
  (both measured in docs/refine.md).

Both minimise, per image,

.. math::

    E(n, L) = \underbrace{\tfrac{1}{|M|}\sum_{p \in M} \rho\big(r_p / \bar I\big)}_{\text{photometric}}
        + \lambda_\kappa \underbrace{\tfrac{1}{|M|}\sum_{p \in M} w_p (1 - \mu_p^\top n_p)}_{\text{forest (vMF) prior}}
        + \lambda_c \underbrace{\tfrac{1}{|C|}\sum_{p \in C} (1 - c_p^\top n_p)}_{\text{occluding contour}}
        + \lambda_s \underbrace{\tfrac{1}{|M|}\sum_{p \sim q} |n_p - n_q|^2}_{\text{smoothness}}
        + \lambda_L \underbrace{E_{\text{prior}}(L)}_{\text{natural lighting}}

- ``r = R(n, L) - I`` with ``R`` the SH rendering (:func:`sfs_torch.lighting.render_sh`);
  at pixels clipped at 0 (at or below ``dark_level``) or at 1 the residual is one-sided
  (an attached shadow may render below 0, a highlight above 1); ``rho`` is the
  Charbonnier penalty ``sqrt(x^2 + delta^2) - delta`` and ``\bar I`` the mean image
  value on the mask ``M`` (the loss is scale-free);
- ``mu`` are the forest's normals and ``w = min(kappa / mean kappa, 3)`` its confidence
  (the vMF log-likelihood ``kappa mu^T n`` up to a constant and a scale);
- ``C`` are the rim pixels of the mask and ``c`` their silhouette normals (Eq. 10);
- ``p ~ q`` are 4-neighbours both on the mask;
- ``E_prior`` is :func:`sfs_torch.natural_lighting.lighting_prior_energy` (constant when
  the lighting is held fixed);
- ``lambda_s`` is ``smoothness`` in the surface model and ``pixel_smoothness`` in the
  pixel model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_mask, check_same_size, check_shape, is_integer, is_number
from .integrability import _FieldNormals, _dx, _dy, _edge_masks, _unit, field_normals, integrate_normals
from .lighting import render_sh
from .natural_lighting import LightingPrior, lighting_prior_energy, load_lighting_prior
from .silhouette import SilhouetteConfig, coarse_normals

__all__ = ["RefineConfig", "check_refine_config", "photometric_residual", "free_lighting_residual", "RefinementLoss", "Refinement", "refinement_loss", "refine_shape_and_lighting",
           "PhotometricRefiner", "rim_pixels"]


MAX_CONFIDENCE_WEIGHT = 3.0


@dataclass
class RefineConfig:
    """Options of :func:`refine_shape_and_lighting` (Hydra group ``refine``).

    Attributes:
        when: when :func:`sfs_torch.estimate` runs this stage: ``"never"``, ``"known"``
            (only when the lighting is given) or ``"always"`` (an estimated lighting
            too). The default is the measured one (docs/refine.md).
        model: ``"pixel"`` (a free normal per pixel, the lighting held fixed),
            ``"surface"`` (an integrable field, see the module docstring) or ``"auto"``
            (surface when ``optimise_lighting``, else pixel).
        iterations: L-BFGS iterations (each one evaluation of the loss and its gradient
            at least; the strong-Wolfe line search may add a few).
        delta: Charbonnier smoothing of the photometric residual, relative to the mean
            image value (residuals well above it count linearly: robust to highlights
            and shadows the SH model cannot explain).
        dark_level: image values at or below this count as clipped at 0 (with the
            noise of a real sensor an attached shadow reads slightly above 0).
        normal_weight: ``lambda_kappa``, pull towards the forest's normals.
        contour_weight: ``lambda_c``, pull of the rim normals towards the silhouette's.
        smoothness: ``lambda_s``, pull of neighbouring normals towards each other, in the
            surface model.
        pixel_smoothness: ``lambda_s`` of the pixel model, in place of ``smoothness``: its
            free normals follow the forest's, whose per-pixel noise the photometric term
            does not see along each pixel's curve of equal shading (docs/refine.md,
            "The pixel model's smoothness").
        lighting_weight: ``lambda_L``, pull of the lighting towards the natural-lighting prior.
        optimise_lighting: surface model only: fit the lighting too (``False``: held
            fixed; :func:`sfs_torch.estimate` holds a given lighting fixed by itself).
        levels: ``model="surface"`` only: levels of the coarse-to-fine parameterisation
            (the field is a sum of bilinearly upsampled grids at 1, 1/2, ...,
            1/2^(levels-1) of the resolution), which lets L-BFGS fix smooth errors quickly.
        height_unit: ``model="surface"``, orthographic only: the unit, in pixels, in which
            L-BFGS holds the height (the energy and its minimum do not depend on it). In
            pixels (1, the default) the steps it shares with the lighting's coefficients
            hardly move the surface; about the image's side (256 at 256 px) lets the
            joint refinement converge, as a perspective one does: better on exact
            images, but under the realistic formation a sphere then loses its
            silhouette prior (docs/refine.md, "The orthographic height's unit").
            :func:`sfs_torch.estimate`'s refinement after the prior check sets its own
            (``relief_refinement_unit``).
        skip_prior: in :func:`sfs_torch.estimate` with an estimated lighting, an image
            whose silhouette prior the prior check kept (``keep_prior``) keeps Eq. 10's
            normals and their lighting unrefined; its depth is their L2 integration.
            ``False``: it is refined like any other (a given lighting's always is).
    """

    when: str = "always"
    model: str = "auto"
    iterations: int = 150
    delta: float = 0.02
    dark_level: float = 0.004
    normal_weight: float = 0.2
    contour_weight: float = 0.05
    smoothness: float = 0.01
    pixel_smoothness: float = 0.1
    lighting_weight: float = 0.01
    optimise_lighting: bool = True
    levels: int = 5
    height_unit: float = 1.0
    skip_prior: bool = True


@dataclass(frozen=True)
class RefinementLoss:
    """The terms of :func:`refinement_loss`, each :math:`(B,)`; ``total`` is their weighted sum."""

    total: Tensor
    photometric: Tensor
    normal_prior: Tensor
    contour: Tensor
    smoothness: Tensor
    lighting_prior: Tensor


@dataclass(frozen=True)
class Refinement:
    """Result of :func:`refine_shape_and_lighting`.

    Attributes:
        depth: ``model="surface"``: :math:`(B, 1, H, W)` as
            :class:`sfs_torch.integrability.Surface` defines it (orthographic height, or
            perspective distance along the axis), 0 outside; ``model="pixel"``: ``None``.
        normals: :math:`(B, 3, H, W)` refined unit normals, 0 outside.
        lighting: :math:`(B, 3, 9)` refined SH lighting (the input one if held fixed).
        loss_before, loss_after: :math:`(B,)` the total loss at the start and at the end.
    """

    depth: Optional[Tensor]
    normals: Tensor
    lighting: Tensor
    loss_before: Tensor
    loss_after: Tensor


WHEN = ("never", "known", "always")
MODELS = ("auto", "pixel", "surface")


def check_refine_config(cfg: RefineConfig, prefix: str = "refine.") -> None:
    """``ValueError`` naming the first bad option of ``cfg`` as ``prefix`` + its field name
    (``"refine."``, its group in the pipeline; ``"classical."`` in :mod:`sfs_torch.evaluate`)."""
    if cfg.when not in WHEN:
        raise ValueError(f"{prefix}when must be one of {WHEN}, got {cfg.when!r}")
    if cfg.model not in MODELS:
        raise ValueError(f"{prefix}model must be one of {MODELS}, got {cfg.model!r}")
    for name, minimum in (("iterations", 0), ("levels", 1)):
        if not is_integer(getattr(cfg, name), minimum):
            raise ValueError(f"{prefix}{name} must be an integer >= {minimum}, got {getattr(cfg, name)!r}")
    for name in ("delta", "normal_weight", "contour_weight", "smoothness", "pixel_smoothness", "lighting_weight",
                 "dark_level"):
        if not getattr(cfg, name) >= 0:
            raise ValueError(f"{prefix}{name} must be >= 0, got {getattr(cfg, name)}")
    if not cfg.delta > 0:
        raise ValueError(f"{prefix}delta must be > 0, got {cfg.delta}")
    if not is_number(cfg.height_unit, 0, strict=True):
        raise ValueError(f"{prefix}height_unit must be a number > 0 (pixels), got {cfg.height_unit!r}")


def rim_pixels(mask: Tensor) -> Tensor:
    """Object pixels with a background 4-neighbour (or on the image border): :math:`(B, 1, H, W)` bool."""
    mask = check_mask(mask, allow_full=True)
    outside = F.pad((~mask).float(), (1, 1, 1, 1), value=1.0)
    neighbours = outside[..., :-2, 1:-1] + outside[..., 2:, 1:-1] + outside[..., 1:-1, :-2] + outside[..., 1:-1, 2:]
    return mask & (neighbours > 0)


def _masked_mean(x: Tensor, m: Tensor) -> Tensor:
    """Mean of ``x`` (B, C, H, W) over the pixels of ``m`` (B, 1, H, W) and channels: (B,)."""
    mf = m.to(x.dtype)
    return (x * mf).flatten(1).sum(1) / (mf.flatten(1).sum(1) * x.shape[1]).clamp_min(1.0)


def photometric_residual(
    normals: Tensor, lighting: Tensor, image: Tensor, mask: Tensor, *, delta: float = RefineConfig.delta,
    dark_level: float = RefineConfig.dark_level,
) -> Tensor:
    """How well normals and a lighting explain an image: the refinement's photometric term.

    Mean Charbonnier penalty of ``(render_sh(normals, lighting) - image) / mean(image)``
    over the mask, one-sided at pixels clipped at 0 (at or below ``dark_level``) or at 1.

    Args:
        normals: :math:`(B, 3, H, W)`; lighting: :math:`(B, 3, 9)`; image:
            :math:`(B, 3, H, W)`; mask: :math:`(B, 1, H, W)` bool or 0/1.

    Returns:
        :math:`(B,)`, differentiable in ``normals`` and ``lighting``.

    Raises:
        ValueError: wrong shapes, sizes or mask values, an empty mask.
    """
    mask = _checked_fields(normals, image, mask)
    check_shape(lighting, "lighting", "B 3 9")
    if lighting.shape[0] != image.shape[0]:
        raise ValueError(f"lighting must have one (3, 9) lighting per image, got {tuple(lighting.shape)}")
    return _robust_residual(render_sh(normals, lighting), image, mask, delta, dark_level)


def free_lighting_residual(
    normals: Tensor, image: Tensor, mask: Tensor, *, degree: int = 4, delta: float = RefineConfig.delta,
    dark_level: float = RefineConfig.dark_level, highlight: Optional[float] = None, highlight_quantile: float = 0.95,
    highlight_rounds: int = 3,
) -> Tensor:
    """How well normals explain an image under the best smooth shading of them, whatever the lighting.

    The shading of each channel is a polynomial of degree ``<= degree`` in the normal's
    components (on the sphere, degree 4 spans the SH bands 0-4, where the 9-term model
    stops at 2: a sun's irradiance is not 9-term), fitted by least squares to the object
    pixels not clipped at 0 (``dark_level``) or 1 (all of them where every one is), then
    scored like :func:`photometric_residual`.

    With ``highlight`` (relative to the mean image value), pixels brighter than the fitted
    shading by more than a threshold in any channel count as specular highlights, which no
    smooth diffuse shading of the true normals explains: the shading is refitted without
    them (``highlight_rounds`` times), and each costs the penalty of a residual at the
    threshold: a field that leaves a highlight unexplained pays at most that there, so
    normals bent to reproduce it gain at most that, where the plain score would give them
    the whole highlight's residual. The threshold is
    ``highlight`` or, where larger, the ``highlight_quantile`` quantile of how far the other
    fitted pixels fall *below* the shading (their largest deficit over the channels): noise,
    8-bit steps and a wrong field's shape error leave residuals of both signs, a highlight
    only bright ones, so on a dark, noisy image or for a poor field only the outliers of the
    bright side beyond the dark side's are capped.

    Args:
        normals: :math:`(B, 3, H, W)`; image: :math:`(B, 3, H, W)`; mask: :math:`(B, 1, H, W)` bool or 0/1.

    Returns:
        :math:`(B,)`.

    Raises:
        ValueError: wrong shapes, sizes or mask values, an empty mask, bad options.
    """
    mask = _checked_fields(normals, image, mask)
    if highlight is not None and not highlight > 0:
        raise ValueError(f"highlight must be > 0 or None, got {highlight}")
    if not 0 <= highlight_quantile <= 1:
        raise ValueError(f"highlight_quantile must be in [0, 1], got {highlight_quantile}")
    if not is_integer(highlight_rounds, 0):
        raise ValueError(f"highlight_rounds must be an integer >= 0, got {highlight_rounds!r}")
    powers = [(a, b, c) for a in range(degree + 1) for b in range(degree + 1 - a)
              for c in range(degree + 1 - a - b)]
    unclipped = _unclipped_pixels(image, mask, dark_level)
    scale = _masked_mean(image, mask).clamp_min(1e-6)
    shading = torch.zeros_like(image)
    bright = torch.zeros_like(mask)
    threshold = torch.full((image.shape[0],), highlight or 0.0, dtype=torch.float64, device=image.device)
    # one image at a time on its object's pixels: the background is most of a typical image
    for item in range(image.shape[0]):
        m = mask[item, 0]
        n = normals[item][:, m].double()
        values = image[item][:, m].double().T
        power = [torch.stack([n[i] ** k for k in range(degree + 1)]) for i in range(3)]
        basis = torch.stack([power[0][a] * power[1][b] * power[2][c] for a, b, c in powers], 1)  # (N, K)
        fit = unclipped[item, 0][m]
        fit = fit if bool(fit.any()) else torch.ones_like(fit)
        highlights = torch.zeros_like(fit)
        for _ in range(1 + highlight_rounds):
            kept = fit & ~highlights
            a_fit = basis[kept]
            # the monomials are dependent on the unit sphere (35 of them span 25 functions at degree 4)
            ridge = 1e-6 * len(a_fit) * torch.eye(len(powers), dtype=basis.dtype, device=basis.device)
            coefficients = torch.linalg.solve(a_fit.T @ a_fit + ridge, a_fit.T @ values[kept])
            fitted = basis @ coefficients
            if highlight is None:
                break
            below = (fitted - values).amax(1)[kept] / float(scale[item])
            level = max(highlight, float(torch.quantile(below, highlight_quantile)))
            found = ((values - fitted) > level * float(scale[item])).any(1)
            # keep enough pixels to determine the fit
            if int((fit & ~found).sum()) < len(powers):
                break
            threshold[item] = level
            if torch.equal(found, highlights):
                break
            highlights = found
        shading[item][:, m] = fitted.T.to(image.dtype)
        bright[item, 0][m] = highlights
    penalty = _robust_penalty(shading, image, mask, delta, dark_level)
    if highlight is not None:
        cap = _charbonnier(threshold, delta)[:, None, None, None]
        penalty = torch.where(bright, cap.to(penalty), penalty)
    return _masked_mean(penalty, mask)


def _checked_fields(normals: Tensor, image: Tensor, mask: Tensor) -> Tensor:
    """``mask`` as bool, after checking that ``normals`` and ``image`` are :math:`(B, 3, H, W)`
    and ``mask`` a non-empty :math:`(B, 1, H, W)` of the same sizes (the residuals' inputs)."""
    check_shape(normals, "normals", "B 3 H W")
    check_shape(image, "image", "B 3 H W")
    mask = check_mask(mask, allow_full=True)
    check_same_size(image, "image", normals, "normals")
    check_same_size(image, "image", mask, "mask")
    return mask


def _unclipped_pixels(image: Tensor, mask: Tensor, dark_level: float = RefineConfig.dark_level) -> Tensor:
    """Object pixels clipped in no channel, neither at 0 (at or below ``dark_level``) nor
    at 1: :math:`(B, 3, H, W), (B, 1, H, W) -> (B, 1, H, W)` bool (the pixels whose shading
    :func:`free_lighting_residual` fits)."""
    return mask & ((image > dark_level) & (image < 1)).all(1, keepdim=True)


def _robust_residual(shading: Tensor, image: Tensor, mask: Tensor, delta: float, dark_level: float) -> Tensor:
    """Mean Charbonnier penalty of ``(shading - image) / mean(image)`` over the mask,
    one-sided at clipped pixels: (B,)."""
    return _masked_mean(_robust_penalty(shading, image, mask, delta, dark_level), mask)


def _robust_penalty(shading: Tensor, image: Tensor, mask: Tensor, delta: float, dark_level: float) -> Tensor:
    """:func:`_robust_residual` per pixel and channel: (B, C, H, W)."""
    return _penalty(shading, image, _residual_bounds(image, mask, dark_level), delta)


def _residual_bounds(image: Tensor, mask: Tensor, dark_level: float) -> Tuple[Tensor, Tensor, Tensor]:
    """What the robust residual of an image needs besides a shading: ``(scale, low, high)``,
    its mean value on the mask (B, 1, 1, 1) and, per pixel and channel, bounds on
    ``shading - image`` (B, C, H, W): clipped pixels only bound the shading, as an attached
    shadow may render below 0 and a highlight above 1."""
    scale = _masked_mean(image, mask).clamp_min(1e-6)[:, None, None, None]
    dark = image <= dark_level
    low = torch.where(dark, 0.0, image.new_tensor(-math.inf))
    high = torch.where((image >= 1) & ~dark, 0.0, image.new_tensor(math.inf))
    return scale, low, high


def _penalty(shading: Tensor, image: Tensor, bounds: Tuple[Tensor, Tensor, Tensor], delta: float) -> Tensor:
    """The Charbonnier penalty of ``(shading - image) / scale``, held within ``bounds``
    (:func:`_residual_bounds`): (B, C, H, W)."""
    scale, low, high = bounds
    return _charbonnier((shading - image).clamp(low, high) / scale, delta)


def _charbonnier(x: Tensor, delta: float) -> Tensor:
    """The Charbonnier penalty ``sqrt(x^2 + delta^2) - delta``, elementwise."""
    return torch.sqrt(x * x + delta * delta) - delta


def refinement_loss(
    normals: Tensor,
    lighting: Tensor,
    image: Tensor,
    mask: Tensor,
    prior_normals: Tensor,
    confidence: Tensor,
    rim_normals: Tensor,
    *,
    config: Optional[RefineConfig] = None,
    lighting_prior: Optional[LightingPrior] = None,
) -> RefinementLoss:
    """The refinement energy of normals and a lighting (see the module docstring).

    Unchecked: :func:`refine_shape_and_lighting` validates its inputs, then evaluates this
    energy in every step.
    Differentiable in ``normals`` and ``lighting`` (for the surface model, compose with
    :func:`sfs_torch.integrability.field_normals`).

    Args:
        normals: :math:`(B, 3, H, W)` unit normals, 0 outside the mask.
        lighting: :math:`(B, 3, 9)`.
        image: :math:`(B, 3, H, W)` linear RGB.
        mask: :math:`(B, 1, H, W)` bool object pixels.
        prior_normals: :math:`(B, 3, H, W)` the forest's normals ``mu``.
        confidence: :math:`(B, 1, H, W)` per-pixel weights ``w`` of the normal prior.
        rim_normals: :math:`(B, 3, H, W)` target normals on the rim, 0 elsewhere (rim =
            non-zero).
        config: weights (``smoothness`` as ``lambda_s``), ``delta`` and ``dark_level``.
        lighting_prior: natural-lighting prior (``None``: the packaged one).

    Returns:
        :class:`RefinementLoss`.
    """
    return _Energy(image, mask, prior_normals, confidence, rim_normals, config or RefineConfig(),
                   lighting_prior)(normals, lighting)


class _Energy:
    """:func:`refinement_loss` for one image, mask, normal prior, confidence, rim, config and
    lighting prior, as a function of the normals and the lighting. What depends on those
    alone (each term's pixel weights, the residual's bounds) is computed once: the
    refinement evaluates it in every step. Unchecked: :func:`refine_shape_and_lighting`
    validates its inputs."""

    def __init__(self, image: Tensor, mask: Tensor, prior_normals: Tensor, confidence: Tensor, rim_normals: Tensor,
                 cfg: RefineConfig, lighting_prior: Optional[LightingPrior]):
        self.image, self.prior_normals, self.rim_normals, self.cfg = image, prior_normals, rim_normals, cfg
        self.bounds = _residual_bounds(image, mask, cfg.dark_level)
        mf = mask.to(image.dtype)
        count = mf.flatten(1).sum(1)[:, None, None, None].clamp_min(1.0)
        # the terms are means: over the mask (and, photometric, the channels), over the rim
        self.photometric_weight = mf / (image.shape[1] * count)
        self.prior_weight = confidence * mf / count
        rim = (rim_normals.abs().sum(1, keepdim=True) > 0).to(image.dtype)
        self.rim_weight = rim / rim.flatten(1).sum(1)[:, None, None, None].clamp_min(1.0)
        # neighbour differences on the pairs of mask pixels the integrator also uses
        ex, ey = _edge_masks(mask)
        self.edges = (ex / count, ey / count)
        self.lighting_prior = lighting_prior if lighting_prior is not None else load_lighting_prior(device=image.device)

    def __call__(self, normals: Tensor, lighting: Tensor) -> RefinementLoss:
        cfg = self.cfg
        penalty = _penalty(render_sh(normals, lighting), self.image, self.bounds, cfg.delta)
        photometric = (penalty * self.photometric_weight).flatten(1).sum(1)
        normal_prior = ((1 - (normals * self.prior_normals).sum(1, keepdim=True)) * self.prior_weight).flatten(1).sum(1)
        contour = ((1 - (normals * self.rim_normals).sum(1, keepdim=True)) * self.rim_weight).flatten(1).sum(1)
        ex, ey = self.edges
        pairs = _dx(normals).square().sum(1, keepdim=True) * ex + _dy(normals).square().sum(1, keepdim=True) * ey
        smooth = pairs.flatten(1).sum(1)
        light = lighting_prior_energy(lighting, self.lighting_prior)  # used in the lighting's device and dtype
        total = (photometric + cfg.normal_weight * normal_prior + cfg.contour_weight * contour
                 + cfg.smoothness * smooth + cfg.lighting_weight * light)
        return RefinementLoss(total, photometric, normal_prior, contour, smooth, light)


def refine_shape_and_lighting(
    image: Tensor,
    mask: Tensor,
    normals: Tensor,
    lighting: Tensor,
    *,
    confidence: Optional[Tensor] = None,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    config: Optional[RefineConfig] = None,
    lighting_prior: Optional[LightingPrior] = None,
    silhouette: Optional[SilhouetteConfig] = None,
) -> Refinement:
    """Fit normals (per pixel, or of an integrable surface) and optionally the lighting to an image.

    Args:
        image: :math:`(B, 3, H, W)` linear RGB in [0, 1].
        mask: :math:`(B, 1, H, W)` bool or 0/1 object pixels.
        normals: :math:`(B, 3, H, W)` camera-frame unit normals to start from and to
            stay near (e.g. the forest's prediction).
        lighting: :math:`(B, 3, 9)` SH lighting (camera frame), held fixed or, for
            ``model="surface"`` with ``optimise_lighting``, the start of its fit.
        confidence: :math:`(B, 1, H, W)` non-negative per-pixel confidence of
            ``normals`` (e.g. the forest's kappa); ``None``: uniform.
        focal: focal length in pixels; ``None`` is orthographic.
        principal_point: ``(cx, cy)`` in pixels; default image centre.
        config: :class:`RefineConfig`.
        lighting_prior: natural-lighting prior (``None``: the packaged one).
        silhouette: options of the silhouette normals the rim is pulled towards; default
            :class:`~sfs_torch.silhouette.SilhouetteConfig`.

    Returns:
        :class:`Refinement`. The optimisation itself is not differentiated through: inputs
        that require grad are read as constants and no output carries a gradient.

    Raises:
        ValueError: wrong shapes, non-finite values, negative confidence, bad options.
    """
    cfg = config or RefineConfig()
    check_refine_config(cfg)
    if cfg.model == "auto":
        cfg = replace(cfg, model="surface" if cfg.optimise_lighting else "pixel")
    if cfg.model == "pixel":
        cfg = replace(cfg, smoothness=cfg.pixel_smoothness)
    check_shape(image, "image", "B 3 H W")
    check_shape(normals, "normals", "B 3 H W")
    check_shape(lighting, "lighting", "B 3 9")
    mask = check_mask(mask)
    check_same_size(image, "image", mask, "mask")
    check_same_size(image, "image", normals, "normals")
    if lighting.shape[0] != image.shape[0]:
        raise ValueError(f"lighting must have one (3, 9) lighting per image, got {tuple(lighting.shape)}")
    for x, name in ((image, "image"), (normals, "normals"), (lighting, "lighting")):
        check_finite(x, name)
    # the optimisation is not differentiated through: every closure's backward would also
    # run into a graph the inputs bring with them (and fail at the second)
    image, normals, lighting = image.detach(), normals.detach(), lighting.detach()
    if confidence is None:
        confidence = mask.to(image.dtype)
    confidence = confidence.detach()
    check_shape(confidence, "confidence", "B 1 H W")
    check_finite(confidence, "confidence")
    if bool((confidence < 0).any()):
        raise ValueError("confidence must be non-negative")

    prior = (lighting_prior or load_lighting_prior()).to(image.device, image.dtype)
    mf = mask.to(image.dtype)
    mean_conf = (confidence * mf).flatten(1).sum(1) / mf.flatten(1).sum(1)
    weights = (confidence / mean_conf.clamp_min(1e-12)[:, None, None, None]).clamp_max(MAX_CONFIDENCE_WEIGHT) * mf
    rim_normals = coarse_normals(mask, focal, principal_point, silhouette).to(image.dtype) * rim_pixels(mask)
    height, width = image.shape[-2:]
    centre = (width / 2.0, height / 2.0) if principal_point is None else tuple(float(c) for c in principal_point)
    # the optimised variable: per-pixel normals (B, 3, H, W), or the surface field (B, H, W)
    result = torch.zeros_like(normals if cfg.model == "pixel" else image[:, 0])
    lights, before, after = [], [], []
    # one image at a time, on its object's bounding box: a batched line search (and the
    # integration's batch-wide stopping rule) would couple the images, and the
    # background costs time but adds nothing
    for b in range(image.shape[0]):
        rows, cols = _bounding_box(mask[b, 0], margin=2)
        crop = (b, slice(None), rows, cols)
        f, light, loss_before, loss_after = _optimise(
            lighting[b : b + 1].to(image.dtype), image[crop][None], mask[crop][None], normals[crop][None],
            weights[crop][None], rim_normals[crop][None], focal, (centre[0] - cols.start, centre[1] - rows.start),
            cfg, prior,
        )
        result[(b, Ellipsis, rows, cols)] = f[0]
        lights.append(light)
        before.append(loss_before)
        after.append(loss_after)
    light, before, after = torch.cat(lights), torch.cat(before), torch.cat(after)
    with torch.no_grad():
        if cfg.model == "pixel":
            return Refinement(depth=None, normals=result, lighting=light, loss_before=before, loss_after=after)
        m = mask[:, 0]
        depth = result if focal is None else torch.where(m, torch.exp(result), 0.0)
        out_normals = field_normals(result, m, focal, principal_point)
    return Refinement(depth=depth[:, None] * mf, normals=out_normals, lighting=light, loss_before=before,
                      loss_after=after)


def _bounding_box(m: Tensor, margin: int) -> Tuple[slice, slice]:
    """Row and column slices around the ``True`` pixels of ``m`` (H, W), widened by ``margin``."""
    rows = torch.nonzero(m.any(1)).flatten()
    cols = torch.nonzero(m.any(0)).flatten()
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    return (slice(max(r0 - margin, 0), min(r1 + margin, m.shape[0])),
            slice(max(c0 - margin, 0), min(c1 + margin, m.shape[1])))


def _optimise(lighting, image, mask, normals, weights, rim_normals, focal, principal_point, cfg, prior):
    """L-BFGS on one image: the optimised variable, the lighting, the loss before and after."""
    m = mask[:, 0]
    if cfg.model == "pixel":
        variable = _PixelNormals(normals, mask)
        optimise_lighting = False
    else:
        with torch.no_grad():
            surface = integrate_normals(normals, mask, method="l2", weights=weights, focal=focal,
                                        principal_point=principal_point)
        start = surface.depth[:, 0] if focal is None else torch.log(torch.where(m, surface.depth[:, 0], 1.0))
        variable = _Pyramid(torch.where(m, start, 0.0), cfg.levels, m, focal, principal_point,
                            unit=cfg.height_unit if focal is None else 1.0)
        optimise_lighting = cfg.optimise_lighting
    # contiguous copies: L-BFGS flattens each parameter's gradient with a view, which a
    # strided input (a transposed lighting, permuted normals) would make fail
    light = lighting.detach().clone(memory_format=torch.contiguous_format).requires_grad_(optimise_lighting)
    params = variable.parameters + ([light] if optimise_lighting else [])

    energy = _Energy(image, mask, normals, weights, rim_normals, cfg, prior)

    def loss_of(l: Tensor) -> Tensor:
        return energy(variable.normals(), l).total

    with torch.no_grad():
        start_value = variable.value()
        before = loss_of(light)
    start_light = light.detach().clone()
    if cfg.iterations > 0 and bool(torch.isfinite(before).all()):
        overflow_loss = 1e3 * (before.sum().abs() + 1)
        optimiser = torch.optim.LBFGS(params, lr=1.0, max_iter=cfg.iterations, history_size=20,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12)

        def closure() -> Tensor:
            optimiser.zero_grad()
            loss = loss_of(light).sum()
            loss.backward()
            if not bool(torch.isfinite(loss)):
                # A trial step that overflowed: the strong-Wolfe line search steps back from
                # a loss far above the start's (with no slope to follow), whereas a NaN or
                # an infinite one derails its interpolation.
                for p in params:
                    p.grad.zero_()
                return overflow_loss
            return loss

        with torch.enable_grad():
            optimiser.step(closure)
    with torch.no_grad():
        value = variable.value()
        after = loss_of(light)
    # never return something worse than the start (or non-finite)
    if not bool(torch.isfinite(after).all()) or bool((after > before).any()):
        return start_value, start_light, before, before
    return value, light.detach(), before, after


class _PixelNormals:
    """One free normal per pixel, parameterised by an unnormalised vector."""

    def __init__(self, start: Tensor, mask: Tensor):
        self.mask = mask
        self.vector = start.detach().clone(memory_format=torch.contiguous_format).requires_grad_(True)
        self.parameters = [self.vector]

    def normals(self) -> Tensor:
        return _unit(self.vector) * self.mask

    def value(self) -> Tensor:
        return self.normals().detach()


class _Pyramid:
    """A surface field as the sum of upsampled coarser levels: plain gradient steps on
    per-pixel values fix smooth errors very slowly, steps on coarse levels fix them at once."""

    def __init__(self, start: Tensor, n_levels: int, m: Tensor, focal, principal_point, unit: float):
        h, w = start.shape[-2:]
        self.field_normals = _FieldNormals(m, focal, principal_point, start.dtype)
        self.unit = unit  # the field is held divided by it (RefineConfig.height_unit)
        # the division makes the fresh leaf; contiguous() copies only a strided start
        self.parameters = [(start / self.unit).contiguous().requires_grad_(True)]
        # bilinear upsampling (``F.interpolate``, ``align_corners=False``) is separable: a
        # matrix product on each side, whose backward takes a fraction of interpolate's
        self.upsampling = []
        for level in range(1, n_levels):
            shape = (max(1, h >> level), max(1, w >> level))
            self.parameters.append(torch.zeros(start.shape[0], *shape, dtype=start.dtype, device=start.device,
                                               requires_grad=True))
            self.upsampling.append((_upsampling(shape[0], h, start), _upsampling(shape[1], w, start).T))

    def value(self) -> Tensor:
        out = self.parameters[0]
        for coarse, (rows, cols) in zip(self.parameters[1:], self.upsampling):
            out = out + rows @ coarse @ cols
        return out * self.unit

    def normals(self) -> Tensor:
        return self.field_normals(self.value())


def _upsampling(size: int, out: int, like: Tensor) -> Tensor:
    """(out, size): the 1-D linear upsampling from ``size`` to ``out`` samples of bilinear
    ``F.interpolate`` (``align_corners=False``), in ``like``'s dtype and device."""
    eye = torch.eye(size, dtype=like.dtype, device=like.device)[:, None, :, None]
    return F.interpolate(eye, size=(out, 1), mode="bilinear", align_corners=False)[:, 0, :, 0].T


class PhotometricRefiner(nn.Module):
    """Module form of :func:`refine_shape_and_lighting` with a fixed camera and config."""

    def __init__(self, config: Optional[RefineConfig] = None, focal: Optional[float] = None,
                 principal_point: Optional[Sequence[float]] = None, silhouette: Optional[SilhouetteConfig] = None):
        super().__init__()
        self.config = config or RefineConfig()
        self.focal, self.principal_point = focal, principal_point
        self.silhouette = silhouette
        prior = load_lighting_prior()
        self.register_buffer("prior_mean", prior.mean)
        self.register_buffer("prior_precision", prior.precision)

    def forward(self, image: Tensor, mask: Tensor, normals: Tensor, lighting: Tensor,
                confidence: Optional[Tensor] = None) -> Refinement:
        return refine_shape_and_lighting(
            image, mask, normals, lighting, confidence=confidence, focal=self.focal,
            principal_point=self.principal_point, config=self.config,
            lighting_prior=LightingPrior(self.prior_mean, self.prior_precision), silhouette=self.silhouette,
        )
