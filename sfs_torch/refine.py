r"""Photometric refinement: a surface and a lighting that explain the image (not in the paper).

The forest predicts every pixel on its own, for one lighting hypothesis. This stage
fits an integrable surface and the SH lighting jointly to the image, with torch
autograd (L-BFGS), starting from the forest's normals (integrated by
:func:`sfs_torch.integrability.integrate_normals`) and the lighting they were
predicted for. It minimises, per image,

.. math::

    E(s, L) = \underbrace{\tfrac{1}{|V|}\sum_{p \in V} \rho\big((R(n_p(s), L) - I_p)/\bar I\big)}_{\text{photometric}}
        + \lambda_\kappa \underbrace{\tfrac{1}{|M|}\sum_{p \in M} w_p (1 - \mu_p^\top n_p(s))}_{\text{forest (vMF) prior}}
        + \lambda_c \underbrace{\tfrac{1}{|C|}\sum_{p \in C} (1 - c_p^\top n_p(s))}_{\text{occluding contour}}
        + \lambda_L \underbrace{E_{\text{prior}}(L)}_{\text{natural lighting}}

- ``s`` is the height (orthographic) or log-depth (perspective) on the mask and
  ``n(s)`` its normals (:func:`sfs_torch.integrability.field_normals`), so the normals
  are integrable by construction;
- ``R`` renders SH lighting (:func:`sfs_torch.lighting.render_sh`), ``rho`` is the
  Charbonnier penalty ``sqrt(x^2 + delta^2) - delta``, ``V`` the object pixels not
  clipped at 0 or 1, ``\bar I`` the mean image value there (the loss is scale-free);
- ``mu`` are the forest's normals and ``w = min(kappa / mean kappa, 3)`` its confidence
  (the vMF log-likelihood ``kappa mu^T n`` up to a constant and a scale);
- ``C`` are the rim pixels of the mask and ``c`` their silhouette normals (Eq. 10),
  which point outwards and almost perpendicular to the view ray;
- ``E_prior`` is :func:`sfs_torch.natural_lighting.lighting_prior_energy`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_finite, check_mask, check_same_size, check_shape
from .integrability import field_normals, integrate_normals
from .lighting import render_sh
from .natural_lighting import LightingPrior, lighting_prior_energy, load_lighting_prior
from .silhouette import coarse_normals

__all__ = ["RefineConfig", "check_refine_config", "RefinementLoss", "Refinement", "refinement_loss", "refine_shape_and_lighting",
           "PhotometricRefiner", "rim_pixels"]

log = logging.getLogger(__name__)

MAX_CONFIDENCE_WEIGHT = 3.0


@dataclass
class RefineConfig:
    """Options of :func:`refine_shape_and_lighting` (Hydra group ``refine``).

    Attributes:
        when: when :func:`sfs_torch.estimate` runs this stage: ``"never"``, ``"known"``
            (only when the lighting is given; the lighting is then held fixed) or
            ``"always"`` (an estimated lighting is refined too). The default is the
            measured one (docs/refine.md).
        iterations: L-BFGS iterations (each one evaluation of the loss and its gradient
            at least; the strong-Wolfe line search may add a few).
        delta: Charbonnier smoothing of the photometric residual, relative to the mean
            image value (residuals well above it count linearly: robust to highlights
            and shadows the SH model cannot explain).
        normal_weight: ``lambda_kappa``, pull towards the forest's normals.
        contour_weight: ``lambda_c``, pull of the rim normals towards the silhouette's.
        lighting_weight: ``lambda_L``, pull of the lighting towards the natural-lighting prior.
        optimise_lighting: fit the lighting too (``False``: the lighting is held fixed,
            e.g. when it is known; :func:`sfs_torch.estimate` sets it by itself).
        rim_width: rings of rim pixels left out of the photometric term (their finite
            differences are one-sided).
        levels: levels of the coarse-to-fine parameterisation of the surface (the field
            is a sum of bilinearly upsampled grids at 1, 1/2, ..., 1/2^(levels-1) of the
            resolution), which lets L-BFGS fix smooth errors quickly.
    """

    when: str = "known"
    iterations: int = 60
    delta: float = 0.02
    normal_weight: float = 0.05
    contour_weight: float = 0.05
    lighting_weight: float = 0.01
    optimise_lighting: bool = True
    rim_width: int = 0
    levels: int = 5


@dataclass(frozen=True)
class RefinementLoss:
    """The terms of :func:`refinement_loss`, each :math:`(B,)`; ``total`` is their weighted sum."""

    total: Tensor
    photometric: Tensor
    normal_prior: Tensor
    contour: Tensor
    lighting_prior: Tensor


@dataclass(frozen=True)
class Refinement:
    """Result of :func:`refine_shape_and_lighting`.

    Attributes:
        depth: :math:`(B, 1, H, W)` as :class:`sfs_torch.integrability.Surface` defines it
            (orthographic height, or perspective distance along the axis), 0 outside.
        normals: :math:`(B, 3, H, W)` that surface's unit normals, 0 outside.
        lighting: :math:`(B, 3, 9)` refined SH lighting (the input one if held fixed).
        loss_before, loss_after: :math:`(B,)` the total loss at the start and at the end.
    """

    depth: Tensor
    normals: Tensor
    lighting: Tensor
    loss_before: Tensor
    loss_after: Tensor


WHEN = ("never", "known", "always")


def check_refine_config(cfg: RefineConfig) -> None:
    """Raise ``ValueError`` naming the option for an invalid :class:`RefineConfig`."""
    if cfg.when not in WHEN:
        raise ValueError(f"refine.when must be one of {WHEN}, got {cfg.when!r}")
    for name in ("iterations", "rim_width"):
        if getattr(cfg, name) < 0:
            raise ValueError(f"refine.{name} must be >= 0, got {getattr(cfg, name)}")
    if cfg.levels < 1:
        raise ValueError(f"refine.levels must be >= 1, got {cfg.levels}")
    for name in ("delta", "normal_weight", "contour_weight", "lighting_weight"):
        if not getattr(cfg, name) >= 0:
            raise ValueError(f"refine.{name} must be >= 0, got {getattr(cfg, name)}")
    if not cfg.delta > 0:
        raise ValueError(f"refine.delta must be > 0, got {cfg.delta}")


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


def refinement_loss(
    field: Tensor,
    lighting: Tensor,
    image: Tensor,
    mask: Tensor,
    prior_normals: Tensor,
    confidence: Tensor,
    rim_normals: Tensor,
    *,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    config: Optional[RefineConfig] = None,
    lighting_prior: Optional[LightingPrior] = None,
) -> RefinementLoss:
    """The refinement energy of a surface and a lighting (see the module docstring).

    Unchecked inner-loop form; :func:`refine_shape_and_lighting` validates its inputs.

    Args:
        field: :math:`(B, H, W)` height (orthographic) or log-depth (perspective).
        lighting: :math:`(B, 3, 9)`.
        image: :math:`(B, 3, H, W)` linear RGB.
        mask: :math:`(B, 1, H, W)` bool object pixels.
        prior_normals: :math:`(B, 3, H, W)` the forest's normals ``mu``.
        confidence: :math:`(B, 1, H, W)` per-pixel weights ``w`` of the normal prior.
        rim_normals: :math:`(B, 3, H, W)` target normals on the rim, 0 elsewhere (rim =
            non-zero).
        focal, principal_point: camera; ``focal=None`` is orthographic.
        config: weights and the Charbonnier ``delta``.
        lighting_prior: natural-lighting prior (``None``: the packaged one).

    Returns:
        :class:`RefinementLoss`.
    """
    cfg = config or RefineConfig()
    m = mask[:, 0]
    normals = field_normals(field, m, focal, principal_point)
    interior = mask
    for _ in range(cfg.rim_width):
        interior = interior & ~rim_pixels(interior)
    valid = interior & ((image > 0) & (image < 1)).all(1, keepdim=True)
    scale = _masked_mean(image, valid).clamp_min(1e-6)[:, None, None, None]
    residual = (render_sh(normals, lighting) - image) / scale
    delta = cfg.delta
    photometric = _masked_mean(torch.sqrt(residual * residual + delta * delta) - delta, valid)
    normal_prior = _masked_mean(confidence * (1 - (normals * prior_normals).sum(1, keepdim=True)), mask)
    rim = rim_normals.abs().sum(1, keepdim=True) > 0
    contour = _masked_mean(1 - (normals * rim_normals).sum(1, keepdim=True), rim)
    prior = lighting_prior if lighting_prior is not None else load_lighting_prior(device=lighting.device)
    light = lighting_prior_energy(lighting, prior.to(lighting.device, lighting.dtype))
    total = photometric + cfg.normal_weight * normal_prior + cfg.contour_weight * contour + cfg.lighting_weight * light
    return RefinementLoss(total, photometric, normal_prior, contour, light)


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
) -> Refinement:
    """Fit an integrable surface and the SH lighting to one image, from a first guess.

    Args:
        image: :math:`(B, 3, H, W)` linear RGB in [0, 1].
        mask: :math:`(B, 1, H, W)` bool or 0/1 object pixels.
        normals: :math:`(B, 3, H, W)` camera-frame unit normals to start from and to
            stay near (e.g. the forest's prediction).
        lighting: :math:`(B, 3, 9)` SH lighting to start from (camera frame).
        confidence: :math:`(B, 1, H, W)` non-negative per-pixel confidence of
            ``normals`` (e.g. the forest's kappa); ``None``: uniform.
        focal, principal_point: camera; ``focal=None`` is orthographic.
        config: :class:`RefineConfig`.
        lighting_prior: natural-lighting prior (``None``: the packaged one).

    Returns:
        :class:`Refinement`. The optimisation itself is not differentiated through.

    Raises:
        ValueError: wrong shapes, non-finite values, negative confidence, bad options.
    """
    cfg = config or RefineConfig()
    check_refine_config(cfg)
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
    if confidence is None:
        confidence = mask.to(image.dtype)
    check_shape(confidence, "confidence", "B 1 H W")
    check_finite(confidence, "confidence")
    if bool((confidence < 0).any()):
        raise ValueError("confidence must be non-negative")

    prior = (lighting_prior or load_lighting_prior()).to(image.device, image.dtype)
    mf = mask.to(image.dtype)
    mean_conf = (confidence * mf).flatten(1).sum(1) / mf.flatten(1).sum(1)
    weights = (confidence / mean_conf.clamp_min(1e-12)[:, None, None, None]).clamp_max(MAX_CONFIDENCE_WEIGHT) * mf
    rim_normals = coarse_normals(mask, focal, principal_point).to(image.dtype) * rim_pixels(mask)
    # one image at a time: a batched line search (and the integration's batch-wide
    # stopping rule) would couple the images
    parts = [
        _optimise(lighting[b : b + 1].to(image.dtype), image[b : b + 1], mask[b : b + 1], normals[b : b + 1],
                  weights[b : b + 1], rim_normals[b : b + 1], focal, principal_point, cfg, prior)
        for b in range(image.shape[0])
    ]
    field, light, before, after = (torch.cat(x) for x in zip(*parts))
    m = mask[:, 0]
    with torch.no_grad():
        depth = field if focal is None else torch.where(m, torch.exp(field), 0.0)
        out_normals = field_normals(field, m, focal, principal_point)
    return Refinement(depth=depth[:, None] * mf, normals=out_normals, lighting=light,
                      loss_before=before, loss_after=after)


def _optimise(lighting, image, mask, normals, weights, rim_normals, focal, principal_point, cfg, prior):
    """L-BFGS on one image from the integrated normals: the field, the lighting, the loss before and after."""
    m = mask[:, 0]
    with torch.no_grad():
        surface = integrate_normals(normals, mask, method="l2", weights=weights, focal=focal,
                                    principal_point=principal_point)
    start = surface.depth[:, 0] if focal is None else torch.log(torch.where(m, surface.depth[:, 0], 1.0))
    pyramid = _Pyramid(torch.where(m, start, 0.0), cfg.levels)
    light = lighting.detach().clone().requires_grad_(cfg.optimise_lighting)
    params = pyramid.levels + ([light] if cfg.optimise_lighting else [])

    def loss_of(f: Tensor, l: Tensor) -> Tensor:
        return refinement_loss(f, l, image, mask, normals, weights, rim_normals, focal=focal,
                               principal_point=principal_point, config=cfg, lighting_prior=prior).total

    with torch.no_grad():
        start_field = pyramid.field()
        before = loss_of(start_field, light)
    start_light = light.detach().clone()
    if cfg.iterations > 0 and bool(torch.isfinite(before).all()):
        optimiser = torch.optim.LBFGS(params, lr=1.0, max_iter=cfg.iterations, history_size=20,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12)

        def closure() -> Tensor:
            optimiser.zero_grad()
            loss = loss_of(pyramid.field(), light).sum()
            loss.backward()
            return loss

        try:
            with torch.enable_grad():
                optimiser.step(closure)
        except RuntimeError as err:  # a line search that ran off to overflow
            log.warning("photometric refinement diverged (%s); keeping its start", err)
    with torch.no_grad():
        field = pyramid.field()
        after = loss_of(field, light)
    # never return something worse than the start (or non-finite)
    if not bool(torch.isfinite(after).all()) or bool((after > before).any()):
        return start_field, start_light, before, before
    return field, light.detach(), before, after


class _Pyramid:
    """A field as the sum of upsampled coarser levels: plain gradient steps on per-pixel
    values fix smooth errors very slowly, steps on coarse levels fix them at once."""

    def __init__(self, start: Tensor, n_levels: int):
        h, w = start.shape[-2:]
        self.size = (h, w)
        self.levels = [start.clone().requires_grad_(True)]
        for level in range(1, n_levels):
            shape = (max(1, h >> level), max(1, w >> level))
            self.levels.append(torch.zeros(start.shape[0], *shape, dtype=start.dtype, device=start.device,
                                           requires_grad=True))

    def field(self) -> Tensor:
        out = self.levels[0]
        for coarse in self.levels[1:]:
            out = out + F.interpolate(coarse[:, None], size=self.size, mode="bilinear", align_corners=False)[:, 0]
        return out


class PhotometricRefiner(nn.Module):
    """Module form of :func:`refine_shape_and_lighting` with a fixed camera and config."""

    def __init__(self, config: Optional[RefineConfig] = None, focal: Optional[float] = None,
                 principal_point: Optional[Sequence[float]] = None):
        super().__init__()
        self.config = config or RefineConfig()
        self.focal, self.principal_point = focal, principal_point
        prior = load_lighting_prior()
        self.register_buffer("prior_mean", prior.mean)
        self.register_buffer("prior_precision", prior.precision)

    def forward(self, image: Tensor, mask: Tensor, normals: Tensor, lighting: Tensor,
                confidence: Optional[Tensor] = None) -> Refinement:
        return refine_shape_and_lighting(
            image, mask, normals, lighting, confidence=confidence, focal=self.focal,
            principal_point=self.principal_point, config=self.config,
            lighting_prior=LightingPrior(self.prior_mean, self.prior_precision),
        )
