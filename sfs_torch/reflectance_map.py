"""Reflectance-map (lighting) estimation from the silhouette alone (paper Sec. 7, 8).

Every object pixel is mapped to a direction on the visible hemisphere by its
silhouette features (relative distance to the contour and direction to the contour),
which turns the image into a rough "calibration sphere". The colour of a set of
hemisphere directions is the mean colour of the ``k`` pixels mapped nearest to it
(Eq. 9), a low-pass that suppresses badly mapped pixels; 9 SH coefficients per channel
are fitted to these colours in closed form, and finally the brightness and contrast
of the estimate are matched to the image.

:func:`refit_lighting` goes the other way: given normals for the object (the forest's
prediction, in :func:`sfs_torch.estimate`), it fits the lighting that shades them into
the image, which the pipeline uses to refine the silhouette estimate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Mapping
from typing import Optional, Sequence, Union

import torch
from torch import Tensor, nn

from ._checks import check_finite, check_mask, check_same_size, check_shape, check_unit_vectors, is_integer
from .camera import _check_camera, centroid_rotation
from .lighting import fit_sh, fit_sh_vectors, rotate_sh, sh_basis_vectors
from .silhouette import SilhouetteConfig, silhouette_distances

__all__ = [
    "ReflectanceMapConfig",
    "check_reflectance_map_config",
    "LightingEstimator",
    "LightingRefit",
    "sphere_mapping",
    "estimate_lighting",
    "refit_lighting",
    "hemisphere_directions",
]

PROFILES = ("sphere", "linear")
# directions of the visible hemisphere on which a refitted lighting must shade >= 0
VALIDITY_DIRECTIONS = 400


@dataclass
class ReflectanceMapConfig:
    """Options of :func:`estimate_lighting`.

    Attributes:
        profile: out-of-plane profile of the pixel-to-sphere mapping. ``"sphere"`` is
            Eq. 10 (``n_z = sqrt(1 - (1 - d_rel)^2)``, exact for a sphere); ``"linear"``
            is Eq. 8 (polar angle ``arccos d_rel``, i.e. ``n_z = d_rel``).
        n_directions: hemisphere directions whose colour is estimated (Eq. 9).
        knn_fraction: ``k`` as a share of the object's pixel count (k grows with size).
        min_k: smallest ``k``.
        max_pixels: object pixels used at most (an even subsample beyond that), which
            bounds the cost of the k-NN search on large images.
        match_statistics: match the mean and standard deviation of the estimate's
            shading to the image per channel (the paper's final step).

    How :func:`sfs_torch.estimate` refits the lighting afterwards (``refine_rounds``,
    ``valid_refit``, ``keep_prior``) is the pipeline's, in
    :class:`sfs_torch.pipeline.PipelineConfig`.
    """

    profile: str = "sphere"
    n_directions: int = 400
    knn_fraction: float = 0.01
    min_k: int = 4
    max_pixels: int = 20000
    match_statistics: bool = True


def check_reflectance_map_config(cfg: ReflectanceMapConfig) -> None:
    """``ValueError`` naming the first bad option of ``cfg`` by its field name (callers put
    the group in front: ``reflectance_map.`` in the pipeline, ``config.`` in :class:`LightingEstimator`)."""
    if cfg.profile not in PROFILES:
        raise ValueError(f"profile must be one of {PROFILES}, got {cfg.profile!r}")
    for name, minimum in (("n_directions", 9), ("min_k", 1), ("max_pixels", 1)):
        if not is_integer(getattr(cfg, name), minimum):
            raise ValueError(f"{name} must be an integer >= {minimum}, got {getattr(cfg, name)!r}")
    if not 0 < cfg.knn_fraction <= 1:
        raise ValueError(f"knn_fraction must be in (0, 1], got {cfg.knn_fraction!r}")


def _checked_config(config: Union[None, ReflectanceMapConfig, Mapping]) -> ReflectanceMapConfig:
    """A ``config`` argument as a checked :class:`ReflectanceMapConfig`: ``None`` gives the
    defaults, a mapping its fields; a bad option is named as ``config.<key>``."""
    if config is None:
        return ReflectanceMapConfig()
    if isinstance(config, Mapping):
        try:
            config = ReflectanceMapConfig(**config)
        except TypeError as err:
            raise ValueError(f"config does not fit ReflectanceMapConfig: {err}") from None
    elif not isinstance(config, ReflectanceMapConfig):
        raise TypeError(f"config must be a ReflectanceMapConfig, a mapping or None, got {type(config).__name__}")
    try:
        check_reflectance_map_config(config)
    except ValueError as err:
        raise ValueError(f"config.{err}") from None
    return config


def hemisphere_directions(n: int, *, device=None, dtype=torch.float32) -> Tensor:
    """``n`` nearly uniform directions on the visible hemisphere ``z > 0`` (Fibonacci lattice).

    Returns:
        :math:`(n, 3)` unit vectors.
    """
    i = torch.arange(n, device=device, dtype=torch.float64) + 0.5
    z = 1 - i / n
    phi = math.pi * (1 + math.sqrt(5)) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1).to(dtype)


def sphere_mapping(mask: Tensor, profile: str = "sphere", silhouette: Optional[SilhouetteConfig] = None) -> Tensor:
    """Map each object pixel to the sphere by its silhouette features (Eq. 8 / Eq. 10).

    Args:
        mask: :math:`(B, 1, H, W)` bool.
        profile: ``"sphere"`` (Eq. 10) or ``"linear"`` (Eq. 8).
        silhouette: options of the silhouette features; default :class:`SilhouetteConfig`.

    Returns:
        :math:`(B, 3, H, W)` unit directions in the orthographic camera frame, 0 outside.
    """
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {PROFILES}, got {profile!r}")
    mask = check_mask(mask)
    dist = silhouette_distances(mask, silhouette)
    d_rel = dist.d_rel.clamp(0, 1)
    nz = torch.sqrt(1 - (1 - d_rel) ** 2) if profile == "sphere" else d_rel
    in_plane = torch.sqrt((1 - nz * nz).clamp_min(0))
    n = torch.cat([in_plane * torch.cos(dist.beta), in_plane * torch.sin(dist.beta), nz], 1)
    return n * mask


def _knn_colours(directions: Tensor, pixel_dirs: Tensor, pixel_colours: Tensor, k: int, chunk: int = 128) -> Tensor:
    """Mean colour of the ``k`` pixels mapped nearest to each direction (Eq. 9)."""
    out = []
    for start in range(0, directions.shape[0], chunk):
        cos = directions[start : start + chunk] @ pixel_dirs.T  # nearest = largest cosine
        idx = cos.topk(k, dim=1).indices
        out.append(pixel_colours[idx].mean(1))
    return torch.cat(out)


def estimate_lighting(
    image: Tensor,
    mask: Tensor,
    *,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    config: Union[None, ReflectanceMapConfig, Mapping] = None,
    silhouette: Optional[SilhouetteConfig] = None,
) -> Tensor:
    """Estimate SH lighting from one image and its silhouette (paper Sec. 7; Sec. 8 with ``focal``).

    Args:
        image: linear RGB, :math:`(B, 3, H, W)`.
        mask: object pixels, :math:`(B, 1, H, W)` bool.
        focal: focal length in pixels; the hemisphere is then rotated by the rotation
            for the object's centroid (Sec. 8).
        principal_point: ``(cx, cy)``; default image centre.
        config: a :class:`ReflectanceMapConfig`, a mapping of its fields, or ``None`` for
            the defaults; checked (:func:`check_reflectance_map_config`).
        silhouette: options of the silhouette features the pixels are mapped by;
            default :class:`~sfs_torch.silhouette.SilhouetteConfig`.

    Returns:
        :math:`(B, 3, 9)` SH lighting in the camera frame.
    """
    cfg = _checked_config(config)
    check_shape(image, "image", "B 3 H W")
    mask = check_mask(mask)
    check_same_size(image, "image", mask, "mask")
    check_finite(image, "image")
    dirs_map = sphere_mapping(mask, cfg.profile, silhouette).to(image.dtype)
    hemisphere = hemisphere_directions(cfg.n_directions, device=image.device, dtype=image.dtype)
    lightings = []
    # One object at a time: object sizes differ, so k and the pixel sets do too.
    for b in range(image.shape[0]):
        m = mask[b, 0]
        pixel_dirs = dirs_map[b].permute(1, 2, 0)[m]  # (N, 3)
        pixel_colours = image[b].permute(1, 2, 0)[m]  # (N, 3)
        if pixel_dirs.shape[0] > cfg.max_pixels:
            keep = torch.linspace(0, pixel_dirs.shape[0] - 1, cfg.max_pixels, device=image.device).long()
            pixel_dirs, pixel_colours = pixel_dirs[keep], pixel_colours[keep]
        n_pixels = pixel_dirs.shape[0]
        k = min(n_pixels, max(cfg.min_k, round(cfg.knn_fraction * n_pixels)))
        colours = _knn_colours(hemisphere, pixel_dirs, pixel_colours, k)
        sh = fit_sh_vectors(hemisphere[None], colours[None])[0]
        if cfg.match_statistics:
            sh = _match_statistics(sh, pixel_dirs, pixel_colours)
        lightings.append(sh)
    sh = torch.stack(lightings)
    if focal is not None:
        sh = rotate_sh(sh, centroid_rotation(mask, focal, principal_point).to(sh.dtype))
    return sh


def refit_lighting(image: Tensor, mask: Tensor, normals: Tensor, *, valid: bool = True) -> Tensor:
    """SH lighting that best shades ``normals`` into ``image`` (least squares, Lambertian).

    Pixels clipped at 0 or 1 in any channel are left out, since their shading is not
    what the image shows; if every object pixel is clipped, all are used. The fit is
    constrained to a physically valid lighting (``valid=True``): its shading is
    non-negative on the visible hemisphere (``n_z >= 0``;
    :func:`sfs_torch.lighting.fit_sh_vectors`), which an unconstrained fit to few or
    one-sided pixels can violate.

    Args:
        image: linear RGB, :math:`(B, 3, H, W)`.
        mask: object pixels, :math:`(B, 1, H, W)` bool.
        normals: camera-frame unit normals, :math:`(B, 3, H, W)`, e.g. predicted ones;
            unit length (within 1e-3) on the mask.

    Returns:
        :math:`(B, 3, 9)` SH lighting in the camera frame.

    Raises:
        ValueError: bad shapes, an empty or full mask, NaN or inf, or normals that are
            not unit vectors on the mask.
    """
    check_shape(image, "image", "B 3 H W")
    check_shape(normals, "normals", "B 3 H W")
    mask = check_mask(mask)
    check_same_size(image, "image", mask, "mask")
    check_same_size(image, "image", normals, "normals")
    check_finite(image, "image")
    check_finite(normals, "normals")
    # an image passed as normals (the two swapped) fits just as well, to a wrong lighting
    check_unit_vectors(normals.permute(0, 2, 3, 1)[mask[:, 0]], "normals", " on the mask")
    unclipped = mask & ((image > 0) & (image < 1)).all(1, keepdim=True)
    usable = unclipped.flatten(1).any(1)[:, None, None, None]
    hemisphere = hemisphere_directions(VALIDITY_DIRECTIONS, device=image.device, dtype=torch.float64) if valid else None
    return fit_sh(normals, image, torch.where(usable, unclipped, mask), nonnegative=hemisphere)


def _match_statistics(sh: Tensor, pixel_dirs: Tensor, pixel_colours: Tensor) -> Tensor:
    """Affinely adjust ``sh`` per channel so its shading of the mapped pixels has the image's mean and std."""
    shading = sh_basis_vectors(pixel_dirs) @ sh.T  # (N, 3)
    # population std: a one-pixel object gets gain 0, a constant (ambient) lighting, not NaN; so
    # does a shading flat up to rounding (k covers every pixel of an object of <= min_k pixels),
    # whose float32 noise a gain would otherwise amplify into the lighting
    spread = shading.std(0, unbiased=False)
    flat = spread <= 1e-5 * shading.abs().mean(0)
    gain = torch.where(flat, 0.0, pixel_colours.std(0, unbiased=False) / spread.clamp_min(1e-8))
    offset = pixel_colours.mean(0) - gain * shading.mean(0)
    matched = sh * gain[:, None]
    matched[:, 0] = matched[:, 0] + offset / sh_basis_vectors(pixel_dirs[:1])[0, 0]
    return matched


class LightingEstimator(nn.Module):
    """Lighting from one image and its silhouette (module form of :func:`estimate_lighting`).

    Stores the options: a :class:`ReflectanceMapConfig`, the silhouette features' options
    and, like :class:`sfs_torch.integrability.Integrator`, the camera.

    Differentiable in ``image``: which pixels are averaged for a hemisphere direction
    (the k nearest, Eq. 9) depends on the mask alone, and the rest is linear least
    squares and the mean / std matching. Not in the mask (boolean).

    Args:
        config: a :class:`ReflectanceMapConfig`, a mapping of its fields, or ``None``
            for the defaults.
        focal: focal length in pixels (Sec. 8: the estimate is rotated by the rotation of
            the object's centroid); ``None`` for an orthographic camera.
        principal_point: ``(cx, cy)`` in pixels; default the image centre.
        silhouette: a :class:`~sfs_torch.silhouette.SilhouetteConfig`; ``None`` for the defaults.

    ``forward(image, mask)``: image :math:`(B, 3, H, W)` linear RGB, mask
    :math:`(B, 1, H, W)` bool; returns :math:`(B, 3, 9)` SH lighting in the camera frame.
    """

    def __init__(
        self,
        config: Union[None, ReflectanceMapConfig, Mapping] = None,
        *,
        focal: Optional[float] = None,
        principal_point: Optional[Sequence[float]] = None,
        silhouette: Optional[SilhouetteConfig] = None,
    ):
        super().__init__()
        self.config = _checked_config(config)
        self.focal, self.principal_point = _check_camera(focal, principal_point)
        self.silhouette = silhouette

    def forward(self, image: Tensor, mask: Tensor) -> Tensor:
        return estimate_lighting(
            image, mask, focal=self.focal, principal_point=self.principal_point, config=self.config,
            silhouette=self.silhouette,
        )

    def extra_repr(self) -> str:
        return f"config={self.config}, focal={self.focal}, principal_point={self.principal_point}"


class LightingRefit(nn.Module):
    """Lighting that best shades given normals into the image (module form of :func:`refit_lighting`).

    Args:
        valid: constrain the fit to a physically valid lighting (non-negative shading on
            the visible hemisphere), as :func:`refit_lighting` does by default.

    ``forward(image, mask, normals)``: image and normals :math:`(B, 3, H, W)`, mask
    :math:`(B, 1, H, W)` bool; returns :math:`(B, 3, 9)`.
    """

    def __init__(self, valid: bool = True):
        super().__init__()
        self.valid = bool(valid)

    def forward(self, image: Tensor, mask: Tensor, normals: Tensor) -> Tensor:
        return refit_lighting(image, mask, normals, valid=self.valid)

    def extra_repr(self) -> str:
        return f"valid={self.valid}"
