"""The whole method (paper Fig. 2): one image and its mask in, normals, lighting, confidence out.

0. a noisy image denoised (:mod:`sfs_torch.denoise`, not in the paper): for every stage
   with a given lighting, for the forest's colour feature with an estimated one;
1. silhouette features of the test mask (:mod:`sfs_torch.silhouette`);
2. reflectance map estimated from the silhouette (:mod:`sfs_torch.reflectance_map`),
   unless the lighting is given;
3. training set for this lighting: the cached example-geometry patches
   (:mod:`sfs_torch.geometry_db`) shaded with it, noised and clipped, with colour,
   texton and silhouette features computed exactly as on the test image;
4. a von Mises-Fisher regression forest trained on it (:mod:`sfs_torch.forest`),
   cached by lighting, predicts every object pixel independently; with an estimated
   lighting, the lighting is then refitted to the image from these normals and a
   forest trained for it predicts again (``refine_rounds``, default 1;
   an addition to the paper that measurably helps, see docs/pipeline.md);
5. perspective: the normals, predicted in the object's orthographic frame, rotated
   into the camera frame (:mod:`sfs_torch.camera`);
6. photometric refinement (:mod:`sfs_torch.refine`, not in the paper): the normals fitted
   to the image, per pixel under a given lighting, and an estimated lighting refined
   jointly with an integrable surface (``refine.when``, default ``"always"``), then once
   more from an unjittered forest trained for the refined lighting (``final_round``;
   ``final_round_jitter`` keeps part of the jitter), and an estimated surface corrected
   by the bas-relief transform a learnt prior on shapes in their poses reads off it
   (:mod:`sfs_torch.relief_prior`, ``relief_prior_passes``, not in the paper; a
   perspective one in its centroid's frame, refined again and kept where it explains the
   image at least as well; optionally first deepened by a factor, ``relief_scale``,
   ``relief_slope_power``; orthographic only, optionally a second such round from the
   corrected surface, the two surfaces averaged, ``relief_rounds``; then, orthographic
   only, the joint refinement once more from the corrected surface, its height in units
   of the image's side so that it converges, ``relief_refinements``); last, the estimated
   normals refined per pixel under their lighting, as a given lighting's are
   (``pixel_refinement``);
7. optional integrability refinement (:mod:`sfs_torch.integrability`).
"""
from __future__ import annotations

import logging
import os
import time
import warnings
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Dict, Iterator, Optional, Sequence, Union

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from torch import Tensor

from ._checks import check_finite, check_mask, check_same_size, is_integer, is_number, to_batch
from .camera import CameraConfig, _check_camera, _positive_focal, centroid_rotation, rotate_normals_to_camera
from .denoise import DenoiseConfig, check_denoise_config, denoise_image
from .forest import VMF, ForestConfig, VMFForest, sample_vmf
from .forest_cache import CACHE_POLICIES, evict_forests, forest_path, load_forest, save_forest
from .geometry_db import DatabaseConfig, GeometryDatabase, load_database
from .geometry_db import _check_config as _check_database_config
from .image_formation import estimate_noise_sigma
from .integrability import (
    METHODS,
    IntegrabilityConfig,
    Integrator,
    _gradients,
    _unit,
    check_integrability_config,
    median_slope,
)
from .lighting import fit_sh_vectors, render_sh, rotate_sh, sh_basis_vectors
from .reflectance_map import (
    VALIDITY_DIRECTIONS,
    ReflectanceMapConfig,
    check_reflectance_map_config,
    estimate_lighting,
    hemisphere_directions,
    refit_lighting,
)
from .refine import (
    RefineConfig,
    _unclipped_pixels,
    check_refine_config,
    free_lighting_residual,
    photometric_residual,
    refine_shape_and_lighting,
)
from .relief_prior import ReliefTransform, apply_relief, compose_relief, load_relief_net, predict_relief, relief_depth
from .silhouette import SilhouetteConfig, check_silhouette_config, coarse_normals, silhouette_features
from .texton import N_TEXTON_FILTERS, TextonConfig, _check_kernel_size, texton_features

__all__ = ["FeatureConfig", "TrainingConfig", "PipelineConfig", "Estimate", "estimate", "resolve_config", "training_set",
           "pixel_features"]

log = logging.getLogger(__name__)

# integrate.method: "none" (the pipeline does not integrate) or a solver of IntegrabilityConfig
INTEGRATION_METHODS = ("none", *METHODS)
NORMAL_ROTATIONS = ("centroid", "pixel")
# options that were in a stage's config until they moved to the pipeline's own: old key -> new key
MOVED_OPTIONS = {
    "reflectance_map.refine_rounds": "refine_rounds",
    "reflectance_map.valid_refit": "valid_refit",
    "reflectance_map.keep_prior": "keep_prior",
    "camera.normal_rotation": "normal_rotation",
    "training.conv_samples_per_tree": "conv_samples_per_tree",
}


@dataclass
class FeatureConfig:
    """Which per-pixel features the forest sees (the paper's Table 1a ablation)."""

    rgb: bool = True
    silhouette: bool = True
    texton: bool = True


@dataclass
class TrainingConfig:
    """How the per-lighting training set is made (Sec. 5, 9.1).

    Attributes:
        noise_sigma: std of the Gaussian noise added to the shaded patches before
            clipping to [0, 1] (the paper: 0.001).
        noise_from_image: use the test image's own noise level instead when it is higher
            (:func:`sfs_torch.image_formation.estimate_noise_sigma`), so that the forest
            learns the noise it will see (a camera's shot noise and 8-bit steps).
        brightness_jitter: std of a per-patch log-brightness factor applied before the
            noise, which makes the forest tolerant of an estimated lighting whose overall
            brightness is off (0: off). Only used when the lighting is estimated: a
            given lighting is trusted exactly.
        colour_jitter: std of an additional per-patch, per-channel log-gain (an
            estimated lighting whose colour balance is off); likewise only for an
            estimated lighting.
        seed: seed of that noise.
        cache_forests: which trained forests are kept on disk (:mod:`sfs_torch.forest_cache`),
            keyed by lighting and configuration: ``"given"`` those for a lighting the
            caller gave (the ones that are reused), ``"always"`` also those for
            estimated lightings (reused only when the same image comes again), ``"never"``.
        max_cached_forests: the most forests kept on disk; the least recently used
            beyond it are deleted.
    """

    noise_sigma: float = 0.001
    noise_from_image: bool = True
    brightness_jitter: float = 0.3
    colour_jitter: float = 0.05
    seed: int = 0
    cache_forests: str = "given"
    max_cached_forests: int = 64


@dataclass
class PipelineConfig:
    """Every option of :func:`estimate`: each stage's options (its config class, beside its
    code; a Hydra group of ``sfs-torch``) and the pipeline's own.

    Attributes:
        database: the example geometry (:class:`~sfs_torch.geometry_db.DatabaseConfig`).
        silhouette: the silhouette features of the test image, the lighting estimate, the
            prior check and the refinement's rim
            (:class:`~sfs_torch.silhouette.SilhouetteConfig`).
        denoise: whether and for which stages a noisy image is denoised
            (:class:`~sfs_torch.denoise.DenoiseConfig`).
        texton, reflectance_map, features, training, forest, camera, refine: the other
            stages' options.
        integrate: whether and how the normals are integrated into a surface (``depth``):
            ``integrate.method`` is ``"none"`` (the default: the per-pixel normals are
            kept) or a solver, ``"l2"``, ``"l1"`` or ``"conv"``, built from these options
            (:class:`~sfs_torch.integrability.IntegrabilityConfig`, whose own default is
            ``"l2"``); the other keys are the solver's, checked always and unused with
            ``"none"``. ``estimate(..., integrate=...)`` chooses the method for one call.
        refine_rounds: when the lighting is estimated, this many times it is refitted to
            the image from the forest's normals (:func:`~sfs_torch.reflectance_map.refit_lighting`)
            and a forest trained for it predicts again; a round whose normals explain the
            image worse than the round before is dropped. 0 is the paper's method; each
            round costs one more forest.
        valid_refit: constrain those refits to a physically valid lighting (``refit_lighting``'s
            ``valid``), and start them from the valid lighting nearest the silhouette
            estimate (which can shade parts of the hemisphere negative).
        keep_prior: return the silhouette prior (Eq. 10's coarse normals with their own
            refitted lighting, or with the given lighting) instead of the forest's normals
            when it explains the image better (:func:`sfs_torch.refine.photometric_residual`);
            with an estimated lighting, asked again after the joint refinement, against the
            refined surface, each under its own best smooth shading
            (:func:`sfs_torch.refine.free_lighting_residual`).
        prior_check_highlight: in that check after the refinement, pixels brighter than a
            field's fitted shading by more than this (relative to the mean image value), and
            by more than 95 % of the other pixels fall below it, count as a specular
            highlight, at a fixed cost whatever the normals (``free_lighting_residual``'s
            ``highlight``); ``None`` scores them like the others.
        prior_check_tie: in that check, on perspective images, a near tie: where the
            refined surface's score is at least this fraction of the prior's (it explains
            the image less than ``1 / prior_check_tie`` times better), the prior is refined
            the same way (from Eq. 10's normals and their refitted lighting) and returned if
            that surface explains the image better than the refined one. The refinement
            fits a surface to the image, highlights included, which the unrefined prior
            cannot: in perspective a refined sphere out-scored even its true normals.
            Orthographic images are left out: there the rule took one bone back to its
            prior and no sphere (docs/pipeline.md). One more joint refinement for each
            near tie; ``None``: never.
        final_round: with an estimated lighting, after the joint refinement: the
            lighting refitted to the refined normals, a forest trained for it without
            the brightness/colour jitter (``final_round_jitter``), and the joint
            refinement again from that forest's normals, whose surface, lighting and
            confidence are returned (one more forest and refinement; measured in
            docs/pipeline.md).
        final_round_jitter: the final round's forest's jitter, as a fraction of
            ``training.brightness_jitter`` and ``training.colour_jitter``. 0 (the
            default) trains it unjittered, as for a given lighting. 0.5 helped where the
            refined lighting stays far off (shapes no choice had used, under the tuning
            lightings) and made the held-out test images worse (docs/pipeline.md).
        relief_scale: with an estimated lighting, after the joint refinement (and
            ``final_round``): the refined surface's depth is multiplied
            by a factor, ``relief_scale`` for a surface of median slope 0.8 (below), a
            bas-relief transform (its normals ``(s n_x, s n_y, n_z)`` normalised, the
            lighting refitted to them), which changes the image's shading only through an
            albedo factor. 1 with ``relief_slope_power=0`` (the defaults) leaves the
            surface as refined: the learnt prior (``relief_prior_passes``) sets the
            transform alone, and on the tuning side the rule before it changed no image by
            more than 1 deg (docs/pipeline.md). Without the prior, ``relief_scale=1.22``
            and ``relief_slope_power=0.5`` correct the estimate's measured flattening (the
            rule chosen on the tuning side). Images the prior check returns to the
            silhouette prior keep Eq. 10's normals.
        relief_slope_power: makes the relief scale grow with the refined surface's own
            median slope ``s`` (of ``|(n_x, n_y)| / n_z`` over the object): each image is
            scaled by ``relief_scale * (s / 0.8) ** relief_slope_power``: on the tuning
            images the steep estimates came out the flattest, so they are deepened more and
            flat ones less; 0 scales every image alike.
        relief_prior_passes: after ``relief_scale``, on the same images: how many passes
            of the learnt prior on shapes in their poses (:mod:`sfs_torch.relief_prior`)
            correct the surface by a bas-relief transform, scale and tilt, that it reads
            off the normal field (the lighting refitted once to the result); 0 leaves it
            off. A perspective surface is corrected in its centroid's frame, then refined
            jointly from there, and kept only where that explains the image at least as well
            as the surface before it (:func:`sfs_torch.refine.photometric_residual`): a
            perspective image tells transforms apart. Measured in docs/pipeline.md.
        relief_refinements: after the learnt prior and the prior check after it, on the
            orthographic images the relief stage corrected and the check did not return to
            the prior: how many times the joint refinement runs again from the corrected
            surface (pulled towards its normals by the final round's confidence, its lighting
            fitted with it), its height held in ``relief_refinement_unit``. The prior fixes
            the bas-relief transform the refinement cannot see; from the corrected surface a
            refinement that converges fixes much of what is left. 1 (the default) costs one
            refinement; 0 keeps the prior's surface. Measured in docs/pipeline.md.
        relief_refinement_unit: the height unit of those refinements, in image sides
            (``max(H, W)`` pixels; ``refine.height_unit``, in pixels, is the other
            refinements'). About one side (the default) lets them converge; at 1 px they
            barely move the surface (docs/refine.md, "The orthographic height's unit").
        relief_refinement_prior: whether the learnt prior corrects the surface again
            after each of those refinements (``False``, the default: the refined surface
            is the estimate).
        relief_rounds: how many surfaces the relief stage (``relief_scale`` and
            ``relief_prior_passes``) averages, orthographic images only. Each round after
            the first starts from the previous round's corrected surface: the lighting
            refitted to it, the final round's forest and refinement, then the
            learnt prior again (the
            relief scale deepens the first round's surface only). The estimate is the mean
            of the rounds' surfaces (their depths; the normals of their mean slopes), its
            lighting refitted, its confidence the first round's. 1 (the default) keeps the
            first round's surface; each round more costs one forest and one refinement.
            Two rounds helped exact renders on both sides of the split and cost the
            realistic test images 0.6 deg of median (docs/pipeline.md).
        pixel_refinement: with an estimated lighting, last: on the images not left at
            the silhouette prior, the normals refined per pixel under the estimate's lighting
            held fixed (the pixel model, as a given lighting's are, ``refine.pixel_smoothness``
            included), pulled towards the surface's normals by the final round's confidence.
            The integrable surface cannot follow the image's local detail; per pixel the
            normals can. ``Estimate.depth`` stays the surface's (``integrate=l2`` integrates
            the refined normals). One more refinement, per pixel (measured in
            docs/pipeline.md).
        relief_prior_weights: the learnt prior's weights: ``None`` for those that ship
            with the package, or the path of an ``.npz`` that
            ``tools/build_relief_prior.py --out`` wrote (a prior trained otherwise).
        normal_rotation: how normals predicted in an orthographic frame are turned into
            a perspective camera's frame: ``"centroid"``, the one rotation of the object's
            centroid (the frame its training lighting is expressed in), or ``"pixel"``, each
            pixel's own :func:`~sfs_torch.camera.perspective_rotation` (the paper's Sec. 8
            rule); docs/pipeline.md has the measurements behind the default.
        conv_samples_per_tree: samples drawn from each tree's leaf as the candidates of
            ``integrate="conv"``.
    """

    database: DatabaseConfig = field(default_factory=DatabaseConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    silhouette: SilhouetteConfig = field(default_factory=SilhouetteConfig)
    texton: TextonConfig = field(default_factory=TextonConfig)
    reflectance_map: ReflectanceMapConfig = field(default_factory=ReflectanceMapConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    forest: ForestConfig = field(default_factory=ForestConfig)
    integrate: IntegrabilityConfig = field(default_factory=lambda: IntegrabilityConfig(method="none"))
    camera: CameraConfig = field(default_factory=CameraConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    refine_rounds: int = 1
    valid_refit: bool = True
    keep_prior: bool = True
    prior_check_highlight: Optional[float] = 0.1
    prior_check_tie: Optional[float] = 0.5
    final_round: bool = True
    final_round_jitter: float = 0.0
    relief_scale: float = 1.0
    relief_slope_power: float = 0.0
    relief_prior_passes: int = 2
    relief_prior_weights: Optional[str] = None
    relief_refinements: int = 1
    relief_refinement_unit: float = 1.0
    relief_refinement_prior: bool = False
    relief_rounds: int = 1
    pixel_refinement: bool = True
    normal_rotation: str = "centroid"
    conv_samples_per_tree: int = 1


@dataclass(frozen=True)
class Estimate:
    """Result of :func:`estimate`.

    Attributes:
        normals: :math:`(B, 3, H, W)` camera-frame unit normals, 0 outside the mask.
        confidence: :math:`(B, 1, H, W)` forest concentration (vMF kappa), 0 outside.
        lighting: :math:`(B, 3, 9)` SH lighting, camera frame: the given one, or the
            estimate after ``refine_rounds`` refits (the one the
            final forest was trained for), refined jointly with the surface by the
            photometric refinement (``refine.when="always"``, the default).
        depth: :math:`(B, 1, H, W)` from integrability (``integrate=``) or from the
            photometric refinement's surface model (by default with an estimated
            lighting; ``refine.model=surface`` with a given one), else ``None``.
        mask: :math:`(B, 1, H, W)` the object mask used.
        timings: seconds spent per stage, summed over the batch. Stages nest: ``final
            round`` (and ``relief rounds``) include their own ``lighting refinement``,
            ``shade database + features`` and ``train forest``, which count in those
            stages' totals too, so the values do not sum to the call's time.
    """

    normals: Tensor
    confidence: Tensor
    lighting: Tensor
    depth: Optional[Tensor]
    mask: Tensor
    timings: Dict[str, float]


class _Timer:
    def __init__(self) -> None:
        self.seconds: Dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        start = time.perf_counter()
        yield
        self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - start


def resolve_config(config: Union[None, PipelineConfig, DictConfig, Dict[str, Any]]) -> PipelineConfig:
    """Merge a partial config (dataclass, dict or omegaconf) onto the defaults and validate every option.

    The checks are cheap (no database, no forest), so :func:`estimate`, the commands and
    :class:`~sfs_torch.model.ShapeFromShading` call this before any work.

    Raises:
        ValueError: an unknown key, a value of the wrong type or out of range; the message
            names the key (e.g. ``forest.n_trees``, ``refine_rounds``), and for a key that
            moved to the pipeline's own options (:data:`MOVED_OPTIONS`) its new name.
    """
    base = OmegaConf.structured(PipelineConfig)
    if config is None:
        cfg = OmegaConf.to_object(base)
    else:
        try:
            override = config if isinstance(config, (dict, DictConfig)) else OmegaConf.structured(config)
            cfg = OmegaConf.to_object(OmegaConf.merge(base, override))
        except OmegaConfBaseException as err:
            raise ValueError(f"config does not fit the pipeline's options: {moved_option_hint(config) or err}") from None
    _check_config(cfg)  # type: ignore[arg-type]
    return cfg  # type: ignore[return-value]


def moved_option_hint(config: Any, prefix: str = "") -> Optional[str]:
    """``"<old> is now <new>, ..."`` for the first key of :data:`MOVED_OPTIONS` that a (nested) dict,
    omegaconf config or ``key=value`` override string uses under its old name (``prefix`` in front
    of both, e.g. ``"pipeline."`` for ``sfs-torch-eval``), or for the old ``integrate.method=None``
    (now ``"none"``); else ``None``."""
    for old, new in MOVED_OPTIONS.items():
        group, key = old.split(".")
        if isinstance(config, str):
            used = config.lstrip("+~").partition("=")[0] == prefix + old
        else:
            node = config.get(group) if isinstance(config, (dict, DictConfig)) else None
            used = isinstance(node, (dict, DictConfig)) and key in node
        if used:
            return f"{prefix}{old} is now {prefix}{new}, an option of the pipeline itself, not of the {group} stage"
    if isinstance(config, str):
        old_none = config.lstrip("+~") == f"{prefix}integrate.method=null"
    else:
        node = config.get("integrate") if isinstance(config, (dict, DictConfig)) else getattr(config, "integrate", None)
        method = node.get("method", "") if isinstance(node, (dict, DictConfig)) else getattr(node, "method", "")
        old_none = method is None
    if old_none:
        return (f"{prefix}integrate.method=None is now {prefix}integrate.method='none' ({prefix}integrate=none): "
                "the pipeline does not integrate")
    return None


@contextmanager
def _named(group: str) -> Iterator[None]:
    """Put a stage's group in front of its check's message (``n_trees must ...`` -> ``forest.n_trees must ...``)."""
    try:
        yield
    except ValueError as err:
        message = str(err)
        raise ValueError(message if message.startswith(f"{group}.") else f"{group}.{message}") from None


def _check_config(cfg: PipelineConfig) -> None:
    """Validate every option of a merged config; ``ValueError`` naming the first bad key."""
    with _named("database"):
        _check_database_config(cfg.database)
    check_silhouette_config(cfg.silhouette, prefix="silhouette.")
    if cfg.features.silhouette and cfg.silhouette != SilhouetteConfig():
        default = asdict(SilhouetteConfig())
        key, value = next((k, v) for k, v in asdict(cfg.silhouette).items() if v != default[k])
        raise ValueError(
            f"silhouette.{key}={value!r} needs features.silhouette=false: the example-geometry database's silhouette "
            "features are computed with the default silhouette options, and the forest must see the same features "
            "in the test image (the other uses of silhouette.*, the lighting estimate, the prior check and the "
            "refinement's rim, take any value)"
        )
    with _named("texton"):
        _check_kernel_size(cfg.texton.kernel_size)
    if cfg.features.texton and cfg.texton.kernel_size != cfg.database.patch_size:
        raise ValueError(
            f"texton.kernel_size ({cfg.texton.kernel_size}) must equal database.patch_size ({cfg.database.patch_size}) "
            "with features.texton: a training patch is filtered whole for its centre pixel's response"
        )
    with _named("reflectance_map"):
        check_reflectance_map_config(cfg.reflectance_map)
    if not (cfg.features.rgb or cfg.features.silhouette or cfg.features.texton):
        raise ValueError("features enables no feature: set at least one of features.rgb, features.silhouette, "
                         "features.texton")
    _check_training_config(cfg.training)
    _check_forest_config(cfg)
    if cfg.integrate.method not in INTEGRATION_METHODS:
        raise ValueError(f"integrate.method must be one of {INTEGRATION_METHODS} (e.g. integrate=l2), "
                         f"got {cfg.integrate.method!r}")
    # the solver's options are checked with "none" too (no solver is built then): as those of the default solver
    check_integrability_config(replace(cfg.integrate, method=IntegrabilityConfig.method), prefix="integrate.")
    with _named("camera"):
        _check_focal(cfg.camera.focal)
        _check_principal_point(cfg.camera.principal_point, cfg.camera.focal, warn=False)
    check_refine_config(cfg.refine)
    check_denoise_config(cfg.denoise)
    if not is_integer(cfg.refine_rounds, 0):
        raise ValueError(f"refine_rounds must be an integer >= 0, got {cfg.refine_rounds!r}")
    if cfg.normal_rotation not in NORMAL_ROTATIONS:
        raise ValueError(f"normal_rotation must be one of {NORMAL_ROTATIONS}, got {cfg.normal_rotation!r}")
    if not is_number(cfg.relief_scale, 0, strict=True):
        raise ValueError(f"relief_scale must be a number > 0, got {cfg.relief_scale!r}")
    if not is_number(cfg.relief_slope_power):
        raise ValueError(f"relief_slope_power must be a number, got {cfg.relief_slope_power!r}")
    if not is_number(cfg.final_round_jitter, 0):
        raise ValueError(f"final_round_jitter must be a number >= 0, got {cfg.final_round_jitter!r}")
    if not is_integer(cfg.relief_prior_passes, 0):
        raise ValueError(f"relief_prior_passes must be an integer >= 0, got {cfg.relief_prior_passes!r}")
    if not is_integer(cfg.relief_refinements, 0):
        raise ValueError(f"relief_refinements must be an integer >= 0, got {cfg.relief_refinements!r}")
    if not is_number(cfg.relief_refinement_unit, 0, strict=True):
        raise ValueError(f"relief_refinement_unit must be a number > 0, got {cfg.relief_refinement_unit!r}")
    if not is_integer(cfg.relief_rounds, 1):
        raise ValueError(f"relief_rounds must be an integer >= 1, got {cfg.relief_rounds!r}")
    weights = cfg.relief_prior_weights
    if weights is not None:
        if not (isinstance(weights, (str, os.PathLike)) and os.path.isfile(weights)):
            raise ValueError(f"relief_prior_weights must be null (the shipped prior) or the path of an .npz that "
                             f"tools/build_relief_prior.py wrote, got {weights!r}: no such file")
        try:  # a file that is no network fails here, not after the forest (~20 ms)
            load_relief_net(weights)
        except ValueError as error:
            raise ValueError(f"relief_prior_weights: {error}") from None
    highlight = cfg.prior_check_highlight
    if highlight is not None and not is_number(highlight, 0, strict=True):
        raise ValueError(f"prior_check_highlight must be a number > 0 or null, got {highlight!r}")
    tie = cfg.prior_check_tie
    if tie is not None and not (is_number(tie, 0, strict=True) and tie <= 1):
        raise ValueError(f"prior_check_tie must be a number in (0, 1] or null, got {tie!r}")
    if not is_integer(cfg.conv_samples_per_tree, 1):
        raise ValueError(f"conv_samples_per_tree must be an integer >= 1, got {cfg.conv_samples_per_tree!r}")


def _check_training_config(cfg: TrainingConfig) -> None:
    for name in ("noise_sigma", "brightness_jitter", "colour_jitter"):
        value = getattr(cfg, name)
        if not is_number(value, 0):
            raise ValueError(f"training.{name} must be a finite number >= 0, got {value!r}")
    if cfg.cache_forests not in CACHE_POLICIES:
        raise ValueError(f"training.cache_forests must be one of {CACHE_POLICIES}, got {cfg.cache_forests!r}")
    if not is_integer(cfg.seed, 0):
        raise ValueError(f"training.seed must be an integer >= 0, got {cfg.seed!r}")
    if not is_integer(cfg.max_cached_forests, 1):
        raise ValueError(f"training.max_cached_forests must be an integer >= 1, got {cfg.max_cached_forests!r}")


def pixel_features(image: Tensor, mask: Tensor, features: FeatureConfig, texton_cfg: TextonConfig,
                   silhouette_cfg: Optional[SilhouetteConfig] = None, colour: Optional[Tensor] = None) -> Tensor:
    """Per-pixel forest features of a test image, in the same order as :func:`training_set`.

    Args:
        image: :math:`(B, 3, H, W)` linear RGB.
        mask: :math:`(B, 1, H, W)` bool.
        silhouette_cfg: options of the silhouette features; default
            :class:`~sfs_torch.silhouette.SilhouetteConfig` (the database's).
        colour: :math:`(B, 3, H, W)` the image the colour feature is read from (a denoised
            copy, :mod:`sfs_torch.denoise`); default ``image``. The textons read ``image``.

    Returns:
        :math:`(B, F, H, W)` features (rgb, silhouette, texton; as enabled).
    """
    parts = []
    if features.rgb:
        parts.append((image if colour is None else colour) * mask)
    if features.silhouette:
        parts.append(silhouette_features(mask, silhouette_cfg).to(image.dtype))
    if features.texton:
        parts.append(texton_features(image, mask, kernel_size=texton_cfg.kernel_size))
    if not parts:
        raise ValueError("config.features enables no feature: set at least one of rgb, silhouette, texton")
    return torch.cat(parts, 1)


@dataclass(frozen=True)
class TrainingSet:
    """Forest training data for one lighting: ``features (N, F)``, ``normals (N, 3)``."""

    features: Tensor
    normals: Tensor


def training_set(
    db: GeometryDatabase,
    sh: Tensor,
    features: FeatureConfig,
    texton_cfg: TextonConfig,
    noise_sigma: float,
    seed: int,
    brightness_jitter: float = 0.0,
    colour_jitter: float = 0.0,
) -> TrainingSet:
    """Shade the database patches with one lighting and compute their features (Sec. 5).

    The patches are shaded, noised, clipped to [0, 1] and their background set to 0,
    then filtered with the same texton bank and background rule as the test image
    (``padding="valid"`` on a patch gives the centre pixel's response).

    Args:
        db: example-geometry patches, ``normals (N, 3, P, P)``, ``masks (N, 1, P, P)``.
        sh: :math:`(3, 9)` lighting in the (orthographic) frame of the patches.

    Returns:
        :class:`TrainingSet` with features in the order of :func:`pixel_features`.
    """
    normals = db.normals.to(sh.device)
    masks = db.masks.to(sh.device)
    shaded = render_sh(normals, sh.expand(normals.shape[0], -1, -1))
    generator = torch.Generator(device=sh.device).manual_seed(seed)
    if brightness_jitter > 0 or colour_jitter > 0:
        n = len(shaded)
        log_gain = brightness_jitter * torch.randn(n, 1, 1, 1, generator=generator, device=sh.device)
        log_gain = log_gain + colour_jitter * torch.randn(n, 3, 1, 1, generator=generator, device=sh.device)
        shaded.mul_(log_gain.exp().to(shaded.dtype))
    # in place: each (N, 3, P, P) temporary costs about as much as the arithmetic on it
    noise = torch.randn(shaded.shape, generator=generator, device=sh.device, dtype=shaded.dtype)
    patches = noise.mul_(noise_sigma).add_(shaded).clamp_(0, 1).mul_(masks)
    centre = db.normals.shape[-1] // 2
    parts = []
    if features.rgb:
        parts.append(patches[:, :, centre, centre])
    if features.silhouette:
        parts.append(db.silhouette.to(sh.device, patches.dtype))
    if features.texton:
        parts.append(texton_features(patches, masks, kernel_size=texton_cfg.kernel_size, padding="valid")[:, :, 0, 0])
    if not parts:
        raise ValueError("config.features enables no feature: set at least one of rgb, silhouette, texton")
    return TrainingSet(torch.cat(parts, 1), normals[:, :, centre, centre])


def _trained_forest(sh: Tensor, db: GeometryDatabase, cfg: PipelineConfig, timer: _Timer, given: bool) -> VMFForest:
    """Train (or fetch from the cache) the forest for one lighting (``given``: the user's, not estimated)."""
    policy = cfg.training.cache_forests
    cached = policy == "always" or (policy == "given" and given)
    options = {
        "database": asdict(cfg.database), "features": asdict(cfg.features), "texton": asdict(cfg.texton),
        "training": {k: v for k, v in asdict(cfg.training).items() if k not in ("cache_forests", "max_cached_forests")},
        # n_jobs only says how many trees grow at once: the forest is the same for any value
        "forest": {k: v for k, v in asdict(cfg.forest).items() if k != "n_jobs"},
    }
    path = forest_path(sh, options)
    forest = load_forest(path, sh.device) if cached else None
    if forest is None:
        with timer("shade database + features"):
            data = training_set(
                db, sh, cfg.features, cfg.texton, cfg.training.noise_sigma, cfg.training.seed,
                cfg.training.brightness_jitter, cfg.training.colour_jitter,
            )
        with timer("train forest"):
            forest = _forest(cfg.forest, sh.device).fit(data.features, data.normals)
        if cached:
            save_forest(forest, path)
            evict_forests(path.parent, cfg.training.max_cached_forests)
    return forest


def _forest(cfg: ForestConfig, device: Optional[torch.device] = None) -> VMFForest:
    """The unfitted forest that ``cfg`` describes: ``hydra.utils.instantiate`` of its ``_target_``,
    :class:`~sfs_torch.forest.VMFForest` or a subclass (the forest cache stores and reads
    ``VMFForest`` tensors)."""
    from hydra.utils import instantiate

    return instantiate(cfg, device=device)


def _integrator(cfg: IntegrabilityConfig, method: str, focal: Optional[float],
                principal_point: Optional[tuple]) -> Integrator:
    """The integrability module that ``cfg`` describes (its ``_target_``, instantiated) with the solver
    ``method`` (``cfg.method`` or :func:`estimate`'s ``integrate``; never ``"none"``)."""
    from hydra.utils import instantiate

    return instantiate(cfg, method=method, focal=focal, principal_point=principal_point, _convert_="all")


def _as_image_tensor(image: Any) -> Tensor:
    if isinstance(image, np.ndarray):
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValueError(f"image as a numpy array must have shape (H, W, 3), got {image.shape}")
        return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor or numpy array, got {type(image).__name__}")
    return image


def _as_mask_tensor(mask: Any, image: Tensor, single: bool) -> Tensor:
    if isinstance(mask, np.ndarray):
        mask = torch.from_numpy(np.ascontiguousarray(mask))
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask must be a torch.Tensor or numpy array, got {type(mask).__name__}")
    if mask.ndim == 2:
        mask = mask[None, None]
    elif mask.ndim == 3:
        mask = mask[None] if single else mask[:, None]
    if mask.ndim != 4 or mask.shape[1] != 1:
        raise ValueError(f"mask must have shape (H, W), (1, H, W) or (B, 1, H, W), got {tuple(mask.shape)}")
    return mask.to(image.device)


def estimate(
    image: Any,
    mask: Any,
    focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None,
    lighting: Optional[Tensor] = None,
    integrate: Optional[str] = None,
    config: Union[None, PipelineConfig, DictConfig, Dict[str, Any]] = None,
    *,
    progress: bool = True,
    database: Optional[GeometryDatabase] = None,
) -> Estimate:
    """Estimate normals, lighting and confidence of a diffuse object from one image.

    Args:
        image: linear RGB in [0, 1]: :math:`(3, H, W)` or :math:`(B, 3, H, W)` tensor, or
            an :math:`(H, W, 3)` numpy array.
        mask: object pixels, :math:`(H, W)`, :math:`(1, H, W)` or :math:`(B, 1, H, W)`,
            bool or {0, 1}.
        focal: focal length in pixels for a perspective camera; ``None``: orthographic
            (or ``config.camera.focal``).
        principal_point: ``(cx, cy)`` in pixels; default the image centre.
        lighting: known SH lighting :math:`(3, 9)` / :math:`(B, 3, 9)` in the camera
            frame; skips the reflectance-map estimate.
        integrate: ``"none"``, ``"l2"``, ``"l1"`` or ``"conv"`` for this call; ``None``:
            ``config.integrate.method`` (whose default is ``"none"``).
        config: partial configuration merged onto the defaults (see ``conf/``).
        progress: show progress bars (database build).
        database: the example-geometry database of ``config.database``, already loaded
            (and ideally on the image's device), used instead of
            :func:`~sfs_torch.geometry_db.load_database`, which reads and verifies the
            cached file on every call. :class:`~sfs_torch.model.ShapeFromShading` holds
            one per device and passes it here. It must be the one ``config.database``
            describes: what its tensors show of that is checked (patch size, at most
            ``n_shapes`` shapes and ``n_shapes * n_views * samples_per_view`` patches).

    Returns:
        :class:`Estimate`; tensors without the batch axis for unbatched input. Not
        differentiable (the forest's splits are hard thresholds): an ``image`` or
        ``lighting`` that requires grad is read as a constant, and no output carries a
        gradient.

    Raises:
        ValueError: bad shapes, dtypes, values, empty or full masks, unknown options,
            a ``database`` that does not fit ``config.database``.
        TypeError: a ``database`` that is not a :class:`~sfs_torch.geometry_db.GeometryDatabase`.
    """
    cfg = resolve_config(config)  # every option checked here, before any work
    if database is not None:
        _check_database(database, cfg.database)
    focal = _check_focal(cfg.camera.focal if focal is None else focal)
    principal_point = _check_principal_point(
        cfg.camera.principal_point if principal_point is None else principal_point, focal
    )
    integrate = cfg.integrate.method if integrate is None else integrate
    if integrate not in INTEGRATION_METHODS:
        raise ValueError(f"integrate must be one of {INTEGRATION_METHODS} (or None: config.integrate.method), "
                         f"got {integrate!r}")
    image_b, mask_b, single = _checked_image_and_mask(image, mask, principal_point)
    known_lighting = None if lighting is None else _checked_lighting(lighting, image_b, mask_b)

    timer = _Timer()
    denoising = cfg.denoise.given if known_lighting is not None else cfg.denoise.estimated
    colour = image_b
    if denoising != "none":
        with timer("denoise"):
            colour = _denoised(image_b, mask_b, cfg.denoise)
        if denoising == "image":
            image_b = colour
    with timer("lighting"):
        if known_lighting is None:
            sh = estimate_lighting(image_b, mask_b, focal=focal, principal_point=principal_point, config=cfg.reflectance_map,
                                   silhouette=cfg.silhouette)
            if cfg.valid_refit:
                sh = _nearest_valid_lighting(sh)
        else:
            sh = known_lighting.to(image_b.device)
    with timer("database"):
        db = load_database(cfg.database, progress=progress) if database is None else database
    with timer("test features"):
        feats = pixel_features(image_b, mask_b, cfg.features, cfg.texton, cfg.silhouette, colour=colour)

    given = known_lighting is not None
    train_cfg = cfg
    if given:
        train_cfg = replace(cfg, training=replace(cfg.training, brightness_jitter=0.0, colour_jitter=0.0))
    sh = sh.clone()
    normals = torch.zeros_like(image_b)
    confidence = torch.zeros_like(mask_b, dtype=image_b.dtype)
    candidates, kept, per_image = [], [], []
    for b in range(image_b.shape[0]):
        image_1, mask_1, m = image_b[b : b + 1], mask_b[b : b + 1], mask_b[b, 0]
        rows = feats[b].permute(1, 2, 0)[m]
        centroid = centroid_rotation(mask_1, focal, principal_point)[0] if focal is not None else None
        image_cfg = _with_image_noise(train_cfg, image_1, mask_1)
        per_image.append((rows, centroid, image_cfg))
        found = _forest_rounds(image_1, mask_1, rows, sh[b], db, image_cfg, timer,
                               given=given, centroid=centroid, focal=focal, principal_point=principal_point)
        normals[b], confidence[b], sh[b] = found.normals[0], found.confidence[0], found.lighting
        prior = None
        if cfg.keep_prior:
            with timer("prior check"):
                prior = _better_prior(image_1, mask_1, normals[b : b + 1], sh[b : b + 1], focal, principal_point,
                                      refit=not given, valid=cfg.valid_refit, forest_score=found.residual,
                                      silhouette=cfg.silhouette)
            if prior is not None:
                normals[b], sh[b] = prior[0][0], prior[1][0]
                # the prior carries no per-pixel confidence: the forest's median everywhere
                confidence[b, 0][m] = confidence[b, 0][m].median()
        kept.append(prior is not None)
        if integrate == "conv":
            candidates.append(normals[b : b + 1].clone() if prior is not None else
                              _conv_candidates(found.forest, rows, m, cfg, centroid, focal, principal_point))
    normals = normals * mask_b

    depth = None
    if cfg.refine.when == "always" or (cfg.refine.when == "known" and given):
        with timer("photometric refinement"):
            # measured for the joint refinement only; a given lighting's normals are still refined
            skip = torch.tensor(kept, device=image_b.device) & (cfg.refine.skip_prior and not given)
            depth, normals, sh = _refine(image_b, mask_b, normals, sh, confidence, skip, cfg, given, focal,
                                         principal_point)
        if cfg.final_round and not given and depth is not None:
            with timer("final round"):
                depth, normals, sh, confidence = _final_rounds(image_b, mask_b, (depth, normals, sh, confidence), ~skip,
                                                               per_image, db, timer, focal, principal_point)
        relief = cfg.relief_scale != 1 or cfg.relief_slope_power != 0 or cfg.relief_prior_passes > 0
        corrected = torch.zeros_like(skip)  # the images the relief stage corrects
        if relief and not given and depth is not None:
            corrected = ~skip
            with timer("relief scale and prior"):
                if focal is None:
                    depth, normals, sh = _scaled_relief(image_b, mask_b, depth, normals, sh, corrected, cfg)
                else:
                    depth, normals, sh, corrected = _perspective_relief(
                        image_b, mask_b, (depth, normals, sh, confidence), corrected, cfg, focal, principal_point)
            if cfg.relief_rounds > 1 and focal is None:
                with timer("relief rounds"):
                    depth, normals, sh = _relief_rounds(image_b, mask_b, (depth, normals, sh, confidence), corrected,
                                                        per_image, db, cfg, timer)
        back = torch.zeros_like(skip)  # the images the check after the refinement returns to the prior
        if cfg.keep_prior and not given and depth is not None:
            with timer("prior check after refinement"):
                back = _prior_explains_better(image_b, mask_b, normals, ~skip, focal, principal_point, cfg)
                corrected &= ~back
                if bool(back.any()):
                    depth, normals, sh = _back_to_prior(image_b, mask_b, depth, normals, sh, confidence, back, cfg,
                                                        focal, principal_point)
                    if integrate == "conv":
                        candidates = [normals[b : b + 1].clone() if back[b] else c for b, c in enumerate(candidates)]
        # after the check, which weighs the prior against the surface as the prior corrected it: refined
        # again, a wrong surface fits the image better, and before the check it beat spheres' exact prior
        if cfg.relief_refinements > 0 and focal is None and bool(corrected.any()):
            with timer("refinement after the relief prior"):
                depth, normals, sh = _refined_relief(image_b, mask_b, (depth, normals, sh, confidence), corrected, cfg)
        refined = ~(skip | back)  # the images not at the silhouette prior
        if cfg.pixel_refinement and not given and depth is not None and bool(refined.any()):
            with timer("pixel refinement"):
                normals = _pixel_refined(image_b, mask_b, normals, sh, confidence, refined, cfg, focal,
                                         principal_point)
    if integrate != "none":
        with timer(f"integrate ({integrate})"):
            integrator = _integrator(cfg.integrate, integrate, focal, principal_point)
            surface = integrator(torch.stack(candidates) if integrate == "conv" else normals, mask_b, weights=confidence)
        depth, normals = surface.depth, surface.normals
    for stage, seconds in timer.seconds.items():
        log.info("%-28s %7.3f s", stage, seconds)

    def out(x: Optional[Tensor]) -> Optional[Tensor]:
        return x[0] if (single and x is not None) else x

    return Estimate(
        normals=out(normals), confidence=out(confidence), lighting=out(sh), depth=out(depth), mask=out(mask_b),
        timings=dict(timer.seconds),
    )


def _refine(image: Tensor, mask: Tensor, normals: Tensor, sh: Tensor, confidence: Tensor, skip: Optional[Tensor],
            cfg: PipelineConfig, given: bool, focal: Optional[float], principal_point: Optional[tuple]) -> tuple:
    """``(depth or None, normals, lighting)`` after the photometric refinement of the
    images not in ``skip`` (B,) bool (``None``: every image); those in it keep their normals
    and lighting, and get the refinement's starting surface as their depth (the L2
    integration of the normals)."""
    skip = torch.zeros(len(image), dtype=torch.bool, device=image.device) if skip is None else skip
    # a given lighting is trusted exactly, never refined
    config = replace(cfg.refine, optimise_lighting=cfg.refine.optimise_lighting and not given)
    normals, sh, depth = normals.clone(), sh.clone(), None
    for items, refining in ((~skip).nonzero()[:, 0], True), (skip.nonzero()[:, 0], False):
        if len(items) == 0:
            continue
        refined = refine_shape_and_lighting(
            image[items], mask[items], normals[items], sh[items], confidence=confidence[items], focal=focal,
            principal_point=principal_point, config=config if refining else replace(config, iterations=0),
            silhouette=cfg.silhouette,
        )
        if refining:
            normals[items], sh[items] = refined.normals, refined.lighting
        if refined.depth is not None:
            depth = torch.zeros_like(mask, dtype=image.dtype) if depth is None else depth
            depth[items] = refined.depth
    return depth, normals, sh


def _pixel_refined(image: Tensor, mask: Tensor, normals: Tensor, sh: Tensor, confidence: Tensor, among: Tensor,
                   cfg: PipelineConfig, focal: Optional[float], principal_point: Optional[tuple]) -> Tensor:
    """The batch's ``normals`` with its images in ``among`` (B,) bool refined per pixel under
    their lighting held fixed (the pixel model, as a given lighting's are), pulled towards the
    normals they have by ``confidence``."""
    items = among.nonzero()[:, 0]
    normals = normals.clone()
    normals[items] = refine_shape_and_lighting(
        image[items], mask[items], normals[items], sh[items], confidence=confidence[items], focal=focal,
        principal_point=principal_point, config=replace(cfg.refine, model="pixel"), silhouette=cfg.silhouette,
    ).normals
    return normals


def _final_round(image: Tensor, mask: Tensor, normals: Tensor, rows: Tensor, db: GeometryDatabase,
                 cfg: PipelineConfig, timer: _Timer, centroid: Optional[Tensor], focal: Optional[float],
                 principal_point: Optional[tuple]) -> tuple:
    """``(depth, normals, lighting, confidence)`` of one image (a batch of 1, each with its
    batch axis) after ``cfg.final_round`` (see :class:`PipelineConfig`), from its refined ``normals``."""
    with timer("lighting refinement"):
        sh = refit_lighting(image, mask, normals, valid=cfg.valid_refit)[0].to(normals.dtype)
    part, training = cfg.final_round_jitter, cfg.training
    final = replace(cfg, refine_rounds=0, training=replace(training, brightness_jitter=part * training.brightness_jitter,
                                                           colour_jitter=part * training.colour_jitter))
    found = _forest_rounds(image, mask, rows, sh, db, final, timer, given=False, centroid=centroid, focal=focal,
                           principal_point=principal_point)
    depth, normals, sh = _refine(image, mask, found.normals, found.lighting[None], found.confidence, None, cfg,
                                 False, focal, principal_point)
    return depth, normals, sh, found.confidence


def _final_rounds(image: Tensor, mask: Tensor, surface: tuple, among: Tensor, per_image: list, db: GeometryDatabase,
                  timer: _Timer, focal: Optional[float], principal_point: Optional[tuple]) -> tuple:
    """``surface``, ``(depth, normals, lighting, confidence)`` of the batch, with each image in
    ``among`` (B,) bool replaced by its :func:`_final_round` from its normals; the others keep theirs."""
    out = tuple(x.clone() for x in surface)
    for b in among.nonzero()[:, 0].tolist():
        rows, centroid, image_cfg = per_image[b]
        last = _final_round(image[b : b + 1], mask[b : b + 1], out[1][b : b + 1], rows, db, image_cfg, timer, centroid,
                            focal, principal_point)
        for x, y in zip(out, last):
            x[b] = y[0]
    return out


def _relief_transform(normals: Tensor, mask: Tensor, cfg: PipelineConfig) -> ReliefTransform:
    """The transform of each orthographic normal field (B, 3, H, W): its :func:`_relief_factor`,
    then ``cfg.relief_prior_passes`` passes of the learnt relief prior."""
    scale = torch.tensor([_relief_factor(n, m, cfg) for n, m in zip(normals, mask)], device=normals.device)
    transform = ReliefTransform(scale, torch.zeros_like(scale), torch.zeros_like(scale))
    if cfg.relief_prior_passes > 0:
        net = load_relief_net(cfg.relief_prior_weights, device=normals.device)
        learnt = predict_relief(apply_relief(normals, mask, transform), mask, net, cfg.relief_prior_passes)
        transform = compose_relief(transform, learnt)
    return transform


def _scaled_relief(image: Tensor, mask: Tensor, depth: Tensor, normals: Tensor, sh: Tensor, among: Tensor,
                   cfg: PipelineConfig) -> tuple:
    """``(depth, normals, lighting)`` with the orthographic surfaces of the images in
    ``among`` (B,) bool corrected by their :func:`_relief_transform`, their lighting refitted."""
    items = among.nonzero()[:, 0]
    if len(items) == 0:
        return depth, normals, sh
    depth, normals, sh = depth.clone(), normals.clone(), sh.clone()
    m = mask[items]
    transform = _relief_transform(normals[items], m, cfg)
    normals[items] = apply_relief(normals[items], m, transform).to(normals.dtype)
    depth[items] = relief_depth(depth[items], m, transform).to(depth.dtype)
    sh[items] = refit_lighting(image[items], m, normals[items], valid=cfg.valid_refit).to(sh.dtype)
    return depth, normals, sh


def _perspective_relief(image: Tensor, mask: Tensor, surface: tuple, among: Tensor, cfg: PipelineConfig,
                        focal: float, principal_point: Optional[tuple]) -> tuple:
    """``(depth, normals, lighting, corrected)`` of the batch whose ``surface`` is the final
    round's ``(depth, normals, lighting, confidence)``, its perspective images in ``among`` (B,)
    bool corrected by their :func:`_relief_transform` in their centroid's frame (where the
    object is seen about as an orthographic one is), refined jointly from there, and kept
    where that surface explains the image at least as well as the one before it
    (``corrected`` (B,) bool: those kept). Unlike an orthographic one, a perspective image
    tells bas-relief transforms apart, so it may refuse the prior's."""
    depth, normals, sh, confidence = surface
    items = among.nonzero()[:, 0]
    if len(items) == 0:
        return depth, normals, sh, among
    m = mask[items]
    rotation = centroid_rotation(m, focal, principal_point).to(normals.dtype)
    local = torch.einsum("bji,bjhw->bihw", rotation, normals[items])
    turned = torch.einsum("bij,bjhw->bihw", rotation, apply_relief(local, m, _relief_transform(local, m, cfg)))
    start = refit_lighting(image[items], m, turned, valid=cfg.valid_refit).to(sh.dtype)
    refined = _refine(image[items], m, turned.to(normals.dtype), start, confidence[items], None, cfg, False, focal,
                      principal_point)
    keep = (photometric_residual(refined[1], refined[2], image[items], m)
            <= photometric_residual(normals[items], sh[items], image[items], m))
    depth, normals, sh, corrected = depth.clone(), normals.clone(), sh.clone(), torch.zeros_like(among)
    for x, y in zip((depth, normals, sh), refined):
        x[items[keep]] = y[keep].to(x.dtype)
    corrected[items[keep]] = True
    return depth, normals, sh, corrected


def _prior_alone(cfg: PipelineConfig) -> PipelineConfig:
    """``cfg`` for the relief stage's later corrections: the learnt prior without the relief
    scale, which deepens the first corrected surface alone."""
    return replace(cfg, relief_scale=1.0, relief_slope_power=0.0)


def _refined_relief(image: Tensor, mask: Tensor, surface: tuple, among: Tensor, cfg: PipelineConfig) -> tuple:
    """``(depth, normals, lighting)`` of the batch whose ``surface`` is the relief stage's
    ``(depth, normals, lighting, confidence)``, its images in ``among`` (B,) bool put
    ``cfg.relief_refinements`` times through the joint refinement from their corrected
    surface, its height in ``cfg.relief_refinement_unit`` image sides, each followed by
    the learnt prior (no relief scale) if ``cfg.relief_refinement_prior``."""
    depth, normals, sh, confidence = surface
    items = among.nonzero()[:, 0]
    if len(items) == 0:
        return depth, normals, sh
    depth, normals, sh = depth.clone(), normals.clone(), sh.clone()
    m = mask[items]
    converging = replace(cfg, refine=_converging_refine(cfg, mask))
    for _ in range(cfg.relief_refinements):
        refined = _refine(image[items], m, normals[items], sh[items], confidence[items], None, converging, False, None,
                          None)
        if cfg.relief_refinement_prior:
            refined = _scaled_relief(image[items], m, *refined, torch.ones_like(items, dtype=torch.bool),
                                     _prior_alone(cfg))
        depth[items], normals[items], sh[items] = refined
    return depth, normals, sh


def _converging_refine(cfg: PipelineConfig, mask: Tensor) -> RefineConfig:
    """``cfg.refine`` with the orthographic height held in ``cfg.relief_refinement_unit``
    sides of the image of ``mask`` (..., H, W), as the refinement after the prior check holds it."""
    return replace(cfg.refine, height_unit=cfg.relief_refinement_unit * max(mask.shape[-2:]))


def _relief_rounds(image: Tensor, mask: Tensor, surface: tuple, among: Tensor, per_image: list,
                   db: GeometryDatabase, cfg: PipelineConfig, timer: _Timer) -> tuple:
    """``(depth, normals, lighting)`` of the batch whose ``surface`` is the relief stage's
    ``(depth, normals, lighting, confidence)``, its orthographic images in ``among`` (B,) bool
    the mean of ``cfg.relief_rounds`` surfaces: the first the stage's, each later one a final
    round and the relief stage from the one before."""
    depth, normals, sh, _ = surface
    items = among.nonzero()[:, 0]
    if len(items) == 0:
        return depth, normals, sh
    m = mask[items]
    later = _prior_alone(cfg)
    depths, fields = [depth[items]], [normals[items]]
    for _ in range(cfg.relief_rounds - 1):
        surface = _final_rounds(image, mask, surface, among, per_image, db, timer, None, None)
        corrected = _scaled_relief(image, mask, *surface[:3], among, later)
        surface = (*corrected, surface[3])
        depths.append(corrected[0][items])
        fields.append(corrected[1][items])
    depth, normals, sh = depth.clone(), normals.clone(), sh.clone()
    depth[items] = torch.stack(depths).mean(0)
    # the mean of the rounds' gradients is the mean surface's: its normals are the mean depth's
    gu, gv, _ = _gradients(torch.stack(fields), None, None, 1e-6)
    gu, gv = gu.mean(0), gv.mean(0)
    normals[items] = _unit(torch.stack([-gu, -gv, torch.ones_like(gu)], 1)) * m
    sh[items] = refit_lighting(image[items], m, normals[items], valid=cfg.valid_refit).to(sh.dtype)
    return depth, normals, sh


RELIEF_REFERENCE_SLOPE = 0.8  # about the median slope of the tuning images' refined surfaces


def _relief_factor(normals: Tensor, mask: Tensor, cfg: PipelineConfig) -> float:
    """``relief_scale * (s / 0.8) ** relief_slope_power`` for one image's ``(3, H, W)``
    normals and ``(1, H, W)`` mask, ``s`` their :func:`~sfs_torch.integrability.median_slope`."""
    if cfg.relief_slope_power == 0:
        return cfg.relief_scale
    slope = float(median_slope(normals, mask))
    return cfg.relief_scale * (slope / RELIEF_REFERENCE_SLOPE) ** cfg.relief_slope_power


FREE_FIT_MAX_CLIPPED = 0.25


def _prior_explains_better(image: Tensor, mask: Tensor, normals: Tensor, among: Tensor, focal: Optional[float],
                           principal_point: Optional[tuple], cfg: PipelineConfig) -> Tensor:
    """``(B,)`` bool: of the images in ``among`` (B,) bool, those that Eq. 10's coarse
    normals explain better than ``normals``, each field under its own best smooth shading
    (:func:`~sfs_torch.refine.free_lighting_residual`), or, in a perspective near tie
    (``cfg.prior_check_tie``), that Eq. 10's normals refined like ``normals`` explain better.

    Asked after the joint refinement, so both fields are smooth and integrable. Under a
    strong sun no 9-term lighting shades even the true normals like the image, so the prior
    check before the refinement (9-term lightings) can prefer a forest's normals, trained
    for the refit, that bend to fit it. Only for images with at most
    ``FREE_FIT_MAX_CLIPPED`` of the object's pixels clipped at 0 or 1: the shading is
    fitted to the others and unbounded on them. ``cfg.prior_check_highlight`` is
    ``free_lighting_residual``'s ``highlight``: a surface bent to reproduce a specular
    highlight gains at most the threshold's penalty on each of its pixels.
    """
    clipped = (mask & ~_unclipped_pixels(image, mask)).flatten(1).sum(1)
    items = (among & (clipped <= FREE_FIT_MAX_CLIPPED * mask.flatten(1).sum(1))).nonzero()[:, 0]
    better = torch.zeros_like(among)
    if len(items) > 0:
        image, mask, normals = image[items], mask[items], normals[items]
        coarse = coarse_normals(mask, focal=focal, principal_point=principal_point, config=cfg.silhouette).to(normals.dtype)
        score = free_lighting_residual(normals, image, mask, highlight=cfg.prior_check_highlight)
        prior = free_lighting_residual(coarse, image, mask, highlight=cfg.prior_check_highlight)
        better[items] = prior < score
        if cfg.prior_check_tie is not None and focal is not None:
            tied = (prior >= score) & (score >= cfg.prior_check_tie * prior)
            if bool(tied.any()):
                better[items[tied]] = _refined_prior_explains_better(image[tied], mask[tied], coarse[tied], score[tied],
                                                                     cfg, focal, principal_point)
    for b in better.nonzero()[:, 0].tolist():
        log.info("image %d: the silhouette prior explains it better than the refined surface under a free smooth "
                 "shading; keeping the prior", b)
    return better


def _refined_prior_explains_better(image: Tensor, mask: Tensor, coarse: Tensor, score: Tensor, cfg: PipelineConfig,
                                   focal: Optional[float], principal_point: Optional[tuple]) -> Tensor:
    """``(N,)`` bool: whether Eq. 10's normals ``coarse`` (N, 3, H, W), refined from their
    own refitted lighting like the surface they are weighed against (the prior's
    confidence uniform), explain the images better than that surface's ``score`` (N,)."""
    sh = refit_lighting(image, mask, coarse, valid=cfg.valid_refit)
    _, refined, _ = _refine(image, mask, coarse, sh, mask.to(image.dtype), None, cfg, False, focal, principal_point)
    better = free_lighting_residual(refined, image, mask, highlight=cfg.prior_check_highlight) < score
    log.info("near ties with the silhouette prior: its refined surface explains %d of %d better", int(better.sum()),
             len(better))
    return better


def _back_to_prior(image: Tensor, mask: Tensor, depth: Tensor, normals: Tensor, sh: Tensor, confidence: Tensor,
                   back: Tensor, cfg: PipelineConfig, focal: Optional[float],
                   principal_point: Optional[tuple]) -> tuple:
    """``(depth, normals, lighting)`` with the images in ``back`` (B,) bool returned to the
    silhouette prior, as the prior check returns it: Eq. 10's normals, their own refitted
    lighting, the forest's median confidence everywhere (``confidence`` is updated in
    place) and, as depth, their L2 integration."""
    items = back.nonzero()[:, 0]
    m = mask[items]
    coarse, prior_sh = _silhouette_prior(image[items], m, normals.dtype, focal, principal_point, cfg.silhouette,
                                         cfg.valid_refit)
    for b in items.tolist():
        confidence[b, 0][mask[b, 0]] = confidence[b, 0][mask[b, 0]].median()
    everything = torch.ones_like(items, dtype=torch.bool)
    prior_depth, _, _ = _refine(image[items], m, coarse, prior_sh, confidence[items], everything, cfg, False, focal,
                                principal_point)
    depth, normals, sh = depth.clone(), normals.clone(), sh.clone()
    depth[items], normals[items], sh[items] = prior_depth, coarse * m, prior_sh
    return depth, normals, sh


def _checked_image_and_mask(image: Any, mask: Any, principal_point: Optional[tuple]) -> tuple:
    """``(image (B, 3, H, W) float32, mask (B, 1, H, W) bool, single)`` from :func:`estimate`'s
    arguments, checked (shape, dtype, range, finiteness, size), with the warnings for input
    outside the method's assumptions; ``single``: the input had no batch axis."""
    image_t = _as_image_tensor(image)
    image_b, single = to_batch(image_t, "image", 3)
    if image_b.shape[1] != 3:
        raise ValueError(f"image must have 3 colour channels (3, H, W) or (B, 3, H, W), got {tuple(image_t.shape)}")
    if not image_b.is_floating_point():
        raise ValueError(f"image must be floating point linear RGB in [0, 1], got {image_b.dtype}")
    check_finite(image_b, "image")
    if bool((image_b < 0).any()) or bool((image_b > 1).any()):
        raise ValueError("image must hold linear RGB values in [0, 1]; rescale it (or decode 8/16-bit integers first)")
    # a numpy (H, W, 3) view gives the same sums as a tensor; no gradient flows through
    # the forest's splits, so an image that requires grad is read as a constant
    image_b = image_b.detach().float().contiguous()
    mask_b = check_mask(_as_mask_tensor(mask, image_b, single))
    check_same_size(image_b, "image", mask_b, "mask")
    _warn_outside_assumptions(image_b, mask_b, principal_point)
    return image_b, mask_b, single


def _checked_lighting(lighting: Any, image: Tensor, mask: Tensor) -> Tensor:
    """A given lighting as ``(B, 3, 9)``, rejected when it is not physical, with a warning when
    its scale does not fit the image."""
    sh = _as_lighting(lighting, image.shape[0])
    shading = _hemisphere_shading(sh)
    _check_physical_lighting(shading)
    _warn_lighting_scale(shading, image, mask)
    return sh


@dataclass(frozen=True)
class _ForestRounds:
    """What :func:`_forest_rounds` keeps: ``normals (1, 3, H, W)`` camera frame,
    ``confidence (1, 1, H, W)``, the ``lighting (3, 9)`` the forest was trained for, the
    forest, and the pair's photometric residual (``None`` without refit rounds)."""

    normals: Tensor
    confidence: Tensor
    lighting: Tensor
    forest: VMFForest
    residual: Optional[float]


def _forest_rounds(image: Tensor, mask: Tensor, rows: Tensor, sh: Tensor, db: GeometryDatabase, cfg: PipelineConfig,
                   timer: _Timer, *, given: bool, centroid: Optional[Tensor], focal: Optional[float],
                   principal_point: Optional[tuple]) -> _ForestRounds:
    """Train a forest for ``sh`` and predict ``rows (N, F)``, the features of the object pixels of
    one image ``(1, 3, H, W)``; for an estimated lighting then ``cfg.refine_rounds`` times refit the
    lighting to the image from those normals and predict again, dropping a round whose normals
    explain the image worse than the round before."""
    rounds = 0 if given else cfg.refine_rounds
    m = mask[0, 0]
    best: Optional[_ForestRounds] = None
    for round_ in range(rounds + 1):
        if round_ > 0:
            with timer("lighting refinement"):  # from the normals of the round before
                sh = refit_lighting(image, mask, best.normals, valid=cfg.valid_refit)[0].to(sh.dtype)
        # Perspective: train in the object's own orthographic frame (the lighting seen from
        # its centroid), then rotate the predictions to the camera frame.
        local_sh = sh if centroid is None else rotate_sh(sh, centroid.T.to(sh.dtype))
        forest = _trained_forest(local_sh, db, cfg, timer, given=given)
        with timer("predict"):
            pred: VMF = forest.predict(rows)
        normals = torch.zeros_like(image)
        normals[0].permute(1, 2, 0)[m] = pred.mean.to(normals.dtype)
        confidence = torch.zeros_like(mask, dtype=image.dtype)
        confidence[0, 0][m] = pred.kappa.to(confidence.dtype)
        if centroid is not None:
            normals = _to_camera(normals, centroid, focal, principal_point, cfg.normal_rotation)
        if rounds == 0:
            return _ForestRounds(normals, confidence, sh, forest, None)
        residual = float(photometric_residual(normals, sh[None], image, mask)[0])
        if best is not None and residual >= best.residual:
            return best
        best = _ForestRounds(normals, confidence, sh, forest, residual)
    return best


def _conv_candidates(forest: VMFForest, rows: Tensor, m: Tensor, cfg: PipelineConfig, centroid: Optional[Tensor],
                     focal: Optional[float], principal_point: Optional[tuple]) -> Tensor:
    """``(S, 3, H, W)`` candidate normal fields for ``integrate="conv"``: ``cfg.conv_samples_per_tree``
    samples from each tree's leaf of every object pixel (mask ``m (H, W)``), camera frame."""
    leaves = forest.predict_leaves(rows)
    generator = torch.Generator(device=rows.device).manual_seed(cfg.training.seed)
    samples = sample_vmf(leaves, cfg.conv_samples_per_tree, generator).flatten(1, 2)  # (N, S, 3)
    cand = torch.zeros(samples.shape[1], 3, *m.shape, dtype=rows.dtype, device=rows.device)
    cand.permute(2, 3, 0, 1)[m] = samples.to(cand.dtype)
    if centroid is not None:
        cand = _to_camera(cand, centroid, focal, principal_point, cfg.normal_rotation)
    return cand


def _check_database(database: Any, cfg: DatabaseConfig) -> None:
    """A database given to :func:`estimate` must fit ``cfg`` as far as its tensors show.

    A :class:`~sfs_torch.geometry_db.GeometryDatabase` does not record its config, so this
    catches the mistakes visible in the tensors (another patch size, more shapes or
    patches than ``cfg`` draws), not e.g. another seed; no host sync, no file read.
    """
    if not isinstance(database, GeometryDatabase):
        raise TypeError(f"database must be a GeometryDatabase (sfs_torch.geometry_db.load_database), "
                        f"got {type(database).__name__}")
    n, p = database.normals.shape[0], cfg.patch_size
    shapes = {"normals": (database.normals, (n, 3, p, p)), "masks": (database.masks, (n, 1, p, p)),
              "silhouette": (database.silhouette, (n, 3))}
    for name, (tensor, expected) in shapes.items():
        if tuple(tensor.shape) != expected:
            raise ValueError(f"database does not match config.database (patch_size={p}): database.{name} must be "
                             f"{expected}, got {tuple(tensor.shape)}")
    most = cfg.n_shapes * cfg.n_views * cfg.samples_per_view
    if len(database.shape_names) > cfg.n_shapes or n > most:
        raise ValueError(f"database does not match config.database: {len(database.shape_names)} shapes and {n} "
                         f"patches, but n_shapes={cfg.n_shapes}, n_views={cfg.n_views}, "
                         f"samples_per_view={cfg.samples_per_view} draw at most {cfg.n_shapes} and {most}")


def _denoised(image: Tensor, mask: Tensor, cfg: DenoiseConfig) -> Tensor:
    """``image`` with the items whose estimated noise is above ``cfg.min_noise`` denoised."""
    noisy = estimate_noise_sigma(image, mask) > cfg.min_noise
    if not bool(noisy.any()):
        return image
    log.info("denoising %d of %d images (noise above denoise.min_noise %g)", int(noisy.sum()), len(noisy),
             cfg.min_noise)
    out = image.clone()
    out[noisy] = denoise_image(image[noisy], mask[noisy], cfg.sigma)
    return out


def _with_image_noise(cfg: PipelineConfig, image: Tensor, mask: Tensor) -> PipelineConfig:
    """``cfg`` with the training noise raised to the image's own noise level (``training.noise_from_image``)."""
    if not cfg.training.noise_from_image:
        return cfg
    sigma = float(estimate_noise_sigma(image, mask)[0])
    if sigma <= cfg.training.noise_sigma:
        return cfg
    log.info("training with the image's noise level: sigma %.4f (training.noise_sigma %.4f)", sigma,
             cfg.training.noise_sigma)
    return replace(cfg, training=replace(cfg.training, noise_sigma=round(sigma, 5)))


def _silhouette_prior(image: Tensor, mask: Tensor, dtype: torch.dtype, focal: Optional[float],
                      principal_point: Optional[tuple], silhouette: Optional[SilhouetteConfig], valid: bool,
                      given: Optional[Tensor] = None) -> tuple:
    """``(normals, lighting)``: Eq. 10's coarse normals of each ``mask`` (B, 1, H, W) as
    ``(B, 3, H, W)`` of ``dtype``, and their lighting (B, 3, 9): the ``given`` one, or the
    one :func:`refit_lighting` fits to them with ``valid``."""
    coarse = coarse_normals(mask, focal=focal, principal_point=principal_point, config=silhouette).to(dtype)
    return coarse, given if given is not None else refit_lighting(image, mask, coarse, valid=valid)


def _better_prior(image: Tensor, mask: Tensor, normals: Tensor, sh: Tensor, focal: Optional[float],
                  principal_point: Optional[tuple], *, refit: bool, valid: bool,
                  forest_score: Optional[float] = None,
                  silhouette: Optional[SilhouetteConfig] = None) -> Optional[tuple]:
    """The silhouette prior ``(normals, lighting)`` if it explains the image better than the forest's pair, else ``None``.

    The prior is Eq. 10's coarse normal field with, for an estimated lighting, its own
    :func:`refit_lighting` (for a given lighting, that lighting); both pairs are scored by
    :func:`photometric_residual` (the forest pair's ``forest_score`` when the refit rounds
    already computed it). A blob-like object (a sphere above all) is the prior's case: there
    the forest's colour cue only adds error.
    """
    coarse, prior_sh = _silhouette_prior(image, mask, normals.dtype, focal, principal_point, silhouette, valid,
                                         given=None if refit else sh)
    if forest_score is None:
        forest_score = float(photometric_residual(normals, sh, image, mask)[0])
    prior_score = float(photometric_residual(coarse, prior_sh, image, mask)[0])
    if prior_score < forest_score:
        log.info("keeping the silhouette prior: it explains the image better (residual %.4f vs %.4f)",
                 prior_score, forest_score)
        return coarse, prior_sh
    return None


def _to_camera(normals: Tensor, centroid: Tensor, focal: float, principal_point, rule: str) -> Tensor:
    """Rotate normals predicted in the centroid's orthographic frame to the camera frame."""
    if rule == "pixel":
        return rotate_normals_to_camera(normals, focal, principal_point)
    if rule == "centroid":
        return torch.einsum("ij,bjhw->bihw", centroid.to(normals.dtype), normals)
    raise ValueError(f"normal_rotation must be one of {NORMAL_ROTATIONS}, got {rule!r}")


def _as_lighting(lighting: Any, batch: int) -> Tensor:
    """A given lighting as ``(B, 3, 9)`` float32 (shape, type and finiteness checked)."""
    try:
        sh = torch.as_tensor(lighting, dtype=torch.float32).detach()
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(
            f"lighting must be SH coefficients of shape (3, 9) or ({batch}, 3, 9), got {type(lighting).__name__} "
            f"{lighting!r:.60}"
        ) from None
    if sh.ndim == 2:
        sh = sh[None].expand(batch, -1, -1)
    if sh.ndim != 3 or sh.shape[1:] != (3, 9) or sh.shape[0] != batch:
        raise ValueError(f"lighting must have shape (3, 9) or ({batch}, 3, 9), got {tuple(sh.shape)}")
    check_finite(sh, "lighting")
    return sh


def _nearest_valid_lighting(sh: Tensor) -> Tensor:
    """Lightings ``(B, 3, 9)`` that shade the visible hemisphere non-negatively: each one that
    does unchanged, any other replaced by the least-squares nearest in its shading there.

    The silhouette estimate is a fit to colours of the hemisphere matched to the image's
    statistics, which can shade parts of it negative (6-9 % of the peak on saturated images);
    every later refit is constrained, and the estimate that a dropped refit round falls back
    to is then constrained too.
    """
    directions = hemisphere_directions(VALIDITY_DIRECTIONS, device=sh.device, dtype=torch.float64)
    shading = _hemisphere_shading(sh.double(), directions)  # (B, M, 3)
    valid = (shading >= 0).flatten(1).all(1)
    if bool(valid.all()):
        return sh
    nearest = fit_sh_vectors(directions.expand(sh.shape[0], -1, -1), shading, nonnegative=directions)
    return torch.where(valid[:, None, None], sh, nearest.to(sh.dtype))


def _hemisphere_shading(sh: Tensor, directions: Optional[Tensor] = None) -> Tensor:
    """What lightings ``(B, 3, 9)`` render on the visible hemisphere (``directions``, default
    the ``VALIDITY_DIRECTIONS`` ones): ``(B, M, 3)``."""
    if directions is None:
        directions = hemisphere_directions(VALIDITY_DIRECTIONS, device=sh.device, dtype=sh.dtype)
    return sh_basis_vectors(directions) @ sh.transpose(1, 2)


def _check_physical_lighting(shading: Tensor) -> None:
    """Reject a given lighting (its :func:`_hemisphere_shading`) that cannot be a physical one."""
    peak, low = shading.amax(1), shading.amin(1)
    if bool((peak <= 0).any()):
        raise ValueError(
            f"lighting renders no light on the visible hemisphere (largest shading per channel "
            f"{peak.tolist()}): a zero or negative lighting is not physical"
        )
    if bool((low < -NEGATIVE_LIGHT_TOLERANCE * peak).any()):
        raise ValueError(
            f"lighting renders strongly negative light on part of the visible hemisphere (shading from "
            f"{low.min():.3g} to {peak.max():.3g}): not a physical lighting; check its coefficient order and "
            "frame (docs/conventions.md)"
        )


# a fitted SH lighting may ring slightly below zero; this share of its peak is allowed
NEGATIVE_LIGHT_TOLERANCE = 0.25
TINY_OBJECT_PIXELS = 64


def _check_focal(focal: Any) -> Optional[float]:
    return None if focal is None else _positive_focal(focal)


def _check_principal_point(principal_point: Any, focal: Optional[float], warn: bool = True) -> Optional[tuple]:
    if principal_point is None:
        return None
    _, values = _check_camera(None, principal_point)
    if focal is None and warn:
        warnings.warn("principal_point is ignored without a focal length (the camera is orthographic)", stacklevel=3)
    return values


def _check_forest_config(cfg: PipelineConfig) -> None:
    """Build the unfitted forest from ``cfg.forest`` and check its options against the feature count."""
    from hydra.errors import InstantiationException

    n_features = 3 * cfg.features.rgb + 3 * cfg.features.silhouette + N_TEXTON_FILTERS * cfg.features.texton
    with _named("forest"):
        try:
            forest = _forest(cfg.forest)
        except InstantiationException as err:
            cause = err.__cause__
            if isinstance(cause, ValueError):
                raise cause from None
            reason = " ".join(str(err).split(", set env var HYDRA_FULL_ERROR")[0].split())
            raise ValueError(f"_target_={cfg.forest._target_!r} could not be built: {reason}") from None
        if hasattr(forest, "_validate_params"):
            forest._validate_params(max(n_features, 1))


def _warn_outside_assumptions(image: Tensor, mask: Tensor, principal_point: Optional[tuple]) -> None:
    """Warn (not fail) for inputs the method runs on but was not designed for."""
    height, width = mask.shape[-2:]
    for b in range(mask.shape[0]):
        m = mask[b, 0]
        pixels = int(m.sum())
        where = f" (batch element {b})" if mask.shape[0] > 1 else ""
        if pixels < TINY_OBJECT_PIXELS:
            warnings.warn(f"the object has only {pixels} pixels{where}: the features and the lighting estimate "
                          "assume objects of hundreds of pixels or more", stacklevel=3)
        if bool(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()):
            warnings.warn(f"the object touches the image border{where}: the silhouette there is not its "
                          "occluding contour, which the silhouette features and the lighting estimate assume",
                          stacklevel=3)
        colours = image[b].permute(1, 2, 0)[m]
        if pixels > 1 and float(colours.std(0).max()) < 1e-4:
            warnings.warn(f"the image is constant on the object{where}: there is no shading to read", stacklevel=3)
        saturated = float((colours >= 1).any(1).float().mean())
        if saturated > 0.5:
            warnings.warn(f"{saturated:.0%} of the object's pixels are saturated{where}: their shading is lost",
                          stacklevel=3)
    if principal_point is not None:
        cx, cy = principal_point
        if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
            warnings.warn(f"principal_point {principal_point} lies far outside the {width}x{height} image",
                          stacklevel=3)


def _warn_lighting_scale(shading: Tensor, image: Tensor, mask: Tensor) -> None:
    """Warn when a given lighting (its :func:`_hemisphere_shading`) is far brighter than
    anything in the image (albedo forgotten?)."""
    for b in range(image.shape[0]):
        brightest = float(torch.quantile(image[b].permute(1, 2, 0)[mask[b, 0]].max(1).values, 0.99))
        peak = float(shading[b].max())
        if brightest < 0.98 and peak > 4 * max(brightest, 1e-6):
            warnings.warn(
                f"the given lighting renders up to {peak:.3g} but the image's brightest pixels are {brightest:.3g}: "
                "is its scale (albedo times intensity) right?", stacklevel=3,
            )
