"""Evaluation scenes: held-out shapes rendered under natural lightings, exactly or realistically.

One generator serves the benchmarks and the tests. Shapes come from the evaluation side
of the database's shape split (never trained on), divided once more: the even-indexed
ones are the **test** side every reported figure uses, the odd-indexed ones the
**validation** side options are tuned on. Lightings: Ramamoorthi & Hanrahan's probes
(:func:`evaluation_lightings`, for reporting only) or the Poly Haven environments under
random hand-held camera orientations (:func:`validation_lightings`, for tuning).

The image formation is set by :class:`FormationConfig`: the default is the paper's
(exact 9-term SH shading, Gaussian noise sigma 0.001, clipped to [0, 1]);
:data:`DEGRADATIONS` names each realistic departure alone and all of them combined
(:mod:`sfs_torch.image_formation`).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, replace
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import torch
import trimesh
from torch import Tensor

from . import image_formation as formation_ops
from ._checks import check_mask, check_same_size, check_shape, is_integer, is_number
from .camera import pixel_grid
from .geometry_db import DatabaseConfig, _mesh_root, database_split, evaluation_shapes
from .lighting import natural_lightings, render_sh, render_sphere, rotate_sh
from .natural_lighting import environment_maps, random_camera_rotations
from .rendering import NormalRender, random_view_rotations, render_normals
from .shapes import COLLECTIONS, Shape, collection_names, drawable_count, load_shape, normalize_mesh

__all__ = ["FormationConfig", "DEGRADATIONS", "Scene", "evaluation_lightings", "validation_lightings", "scene_lightings",
           "scene_shapes", "view_visibility", "camera_gains", "form_image", "synthetic_scenes", "EVALUATION_LIGHTINGS"]

EVALUATION_LIGHTINGS = ("grace_cathedral", "campus_sunset", "uffizi_gallery", "eucalyptus_grove",
                        "st_peters_basilica", "galileos_tomb", "funston_beach_sunset")


@dataclass(frozen=True)
class FormationConfig:
    """How an image is formed from a normal map and an SH lighting.

    Attributes:
        shadows: integrate the lighting's radiance over the visible hemisphere of each
            point, with cast shadows (ray traced), instead of exact SH shading.
        directions: number of lighting directions of that integral.
        specular: peak of a Blinn-Phong lobe from the lighting's dominant direction, as a
            fraction of the diffuse intensity of a surface facing that light; 0 for none.
        shininess: the lobe's exponent.
        exposure_stops: the exposure error is uniform in +- this many stops (log2).
        white_balance: standard deviation of the log of each channel's gain.
        noise: standard deviation of the Gaussian (read) noise.
        shot_noise: intensity of one photo-electron (Poisson noise of variance
            ``shot_noise * I``); 0 for none.
        bits: store as an sRGB file of this depth and read it back; ``None`` keeps floats.
    """

    shadows: bool = False
    directions: int = 400
    specular: float = 0.0
    shininess: float = 40.0
    exposure_stops: float = 0.0
    white_balance: float = 0.0
    noise: float = 0.001
    shot_noise: float = 0.0
    bits: Optional[int] = None

    def __post_init__(self) -> None:
        for name in ("specular", "shininess", "exposure_stops", "white_balance", "noise", "shot_noise"):
            value = getattr(self, name)
            if not is_number(value, 0):
                raise ValueError(f"FormationConfig.{name} must be a finite non-negative number, got {value!r}")
        if not is_integer(self.directions, 1):
            raise ValueError(f"FormationConfig.directions must be a positive integer, got {self.directions!r}")
        if self.bits is not None and not is_integer(self.bits, 1, formation_ops.MAX_BITS):
            raise ValueError(f"FormationConfig.bits must be None or an integer in [1, {formation_ops.MAX_BITS}], "
                             f"got {self.bits!r}")


_EXACT = FormationConfig()
DEGRADATIONS: Dict[str, FormationConfig] = {
    "exact": _EXACT,
    "shadows": replace(_EXACT, shadows=True),
    "specular": replace(_EXACT, specular=0.3),
    "exposure": replace(_EXACT, exposure_stops=0.5, white_balance=0.1),
    "sensor": replace(_EXACT, noise=0.002, shot_noise=2e-4, bits=8),
}
DEGRADATIONS["all"] = replace(DEGRADATIONS["shadows"], specular=0.3, exposure_stops=0.5, white_balance=0.1,
                              noise=0.002, shot_noise=2e-4, bits=8)


@dataclass(frozen=True)
class Scene:
    """One evaluation image.

    Attributes:
        name: ``shape|lighting`` (unique within one generator call).
        image: :math:`(1, 3, H, W)` linear RGB in [0, 1], 0 outside the mask.
        mask: :math:`(1, 1, H, W)` bool.
        normals: :math:`(1, 3, H, W)` true camera-frame normals.
        lighting: :math:`(1, 3, 9)` the true lighting of the image: the source lighting
            times the camera's exposure and white-balance gains. Shadows and highlights are
            departures from it, not part of it.
        source_lighting: :math:`(1, 3, 9)` the lighting the image was rendered with.
        focal: the camera's focal length in pixels, ``None`` for orthographic.
        principal_point: the camera's ``(cx, cy)`` in pixels (SPEC convention), ``None``
            for the image centre.

    Cases loaded from disk (:mod:`sfs_torch.dataset_loaders`) may lack ground truth:
    ``normals`` is then ``None``, and ``lighting`` / ``source_lighting`` are ``None``
    when no lighting is known either; scores that need them must skip such cases.
    """

    name: str
    shape: str
    lighting_name: str
    image: Tensor
    mask: Tensor
    normals: Optional[Tensor]
    lighting: Optional[Tensor]
    source_lighting: Optional[Tensor]
    focal: Optional[float]
    principal_point: Optional[Tuple[float, float]] = None


def evaluation_lightings(n: int = 3, albedo: float = 0.8) -> List[Tuple[str, Tensor]]:
    """The first ``n`` R&H probes of :data:`EVALUATION_LIGHTINGS` (report on these; tune on none)."""
    if not is_integer(n, 1, len(EVALUATION_LIGHTINGS)):
        raise ValueError(f"n must be an integer in [1, {len(EVALUATION_LIGHTINGS)}], got {n!r}")
    probes = natural_lightings(albedo)
    return [(name, probes[name]) for name in EVALUATION_LIGHTINGS[:n]]


def validation_lightings(n: int, seed: int = 0, exposure: Optional[float] = None) -> List[Tuple[str, Tensor]]:
    """``n`` Poly Haven lightings under random hand-held camera orientations (tune on these).

    Each is scaled so that the 95th percentile of a lit sphere is ``exposure``, by default
    0.9 (a well exposed image; the R&H probes of :func:`evaluation_lightings` sit at 0.10-0.35).
    """
    if not is_integer(n, 0):
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    exposure = 0.9 if exposure is None else exposure
    if not is_number(exposure, 0, strict=True):
        raise ValueError(f"exposure must be a number > 0, got {exposure}")
    env = environment_maps()
    rotations = random_camera_rotations(n, torch.Generator().manual_seed(seed)).float()
    out = []
    for i in range(n):
        sh = rotate_sh(env.sh[i % len(env.names)], rotations[i])
        sphere = render_sphere(sh[None], 64)[0]
        out.append((f"{env.names[i % len(env.names)]}_{i}", sh * exposure / torch.quantile(sphere[sphere > 0], 0.95)))
    return out


SCENE_SIDES = ("test", "validation", "spare")


def scene_lightings(n: int, side: str = "test", seed: int = 0,
                    exposure: Optional[float] = None) -> List[Tuple[str, Tensor]]:
    """The ``n`` lightings of one side: the R&H probes on ``"test"``
    (:func:`evaluation_lightings`), Poly Haven maps on the tuning sides ``"validation"`` and
    ``"spare"`` (:func:`validation_lightings` with ``seed`` and ``exposure``).

    Raises:
        ValueError: an unknown ``side``; ``seed`` or ``exposure`` on the test side, whose probes
            keep their own orientation and exposure; a bad ``n`` or ``exposure``.
    """
    if side not in SCENE_SIDES:
        raise ValueError(f"side must be one of {', '.join(map(repr, SCENE_SIDES))}, got {side!r}")
    if side != "test":
        return validation_lightings(n, seed=seed, exposure=exposure)
    if seed != 0 or exposure is not None:
        raise ValueError("seed and exposure are for the tuning sides (validation, spare): the test side's R&H "
                         "probes keep their own orientation and exposure")
    return evaluation_lightings(n)


def scene_shapes(n: Optional[int], side: str = "test", database: DatabaseConfig = DatabaseConfig(),
                 sphere: bool = False) -> List[Shape]:
    """``n`` shapes of one side of ``database``'s shapes.

    ``"test"`` and ``"validation"`` are the two halves of its evaluation split, ``n`` spread
    over each (``None``: all of the half). ``"spare"`` is a larger tuning pool: the next
    ``n`` shapes the split would draw for training after its ``n_shapes`` (by the same group
    weights), so neither its forests' database nor, for the default database, the learnt
    relief prior has seen them.

    With ``sphere=True`` a unit sphere comes first (the shape Eq. 10's silhouette prior is exact for).

    Raises:
        ValueError: an unknown ``side``; ``n`` not an integer, or more shapes than the side holds.
    """
    if side not in SCENE_SIDES:
        raise ValueError(f"side must be one of {', '.join(map(repr, SCENE_SIDES))}, got {side!r}")
    if side == "spare":
        chosen = _spare_shapes(n, database)
    else:
        pool = evaluation_shapes(database)[0 if side == "test" else 1 :: 2]
        n = len(pool) if n is None else n
        if not is_integer(n, 0, len(pool)):
            raise ValueError(f"n must be an integer in [0, {len(pool)}] on the {side} side, got {n!r}")
        chosen = pool[:: max(1, len(pool) // max(n, 1))][:n]
    if sphere:
        chosen = [Shape("sphere", normalize_mesh(trimesh.creation.icosphere(subdivisions=5)))] + chosen
    return chosen


def _spare_shapes(n: int, database: DatabaseConfig) -> List[Shape]:
    """The next ``n`` training shapes of ``database``'s split after its own (see :func:`scene_shapes`)."""
    root = _mesh_root(database.collection)
    drawable = drawable_count(collection_names(database.collection, root), COLLECTIONS[database.collection])
    available = drawable - database.n_shapes - database.n_eval_shapes
    if not is_integer(n, 0, available):
        raise ValueError(f"n must be an integer in [0, {available}] on the spare side, got {n!r}")
    trained = set(database_split(database).train)
    more = database_split(replace(database, n_shapes=database.n_shapes + n)).train
    return [load_shape(name, root) for name in more if name not in trained]


def view_visibility(view: NormalRender, mesh: trimesh.Trimesh, rotation: Tensor, config: FormationConfig) -> Tensor:
    """The shadow rays of one view for :func:`form_image`: :math:`(N, K)` bool over its mask's pixels."""
    inside = view.mask[0]
    return formation_ops.shadow_visibility(mesh, view.points.permute(1, 2, 0)[inside],
                                           view.normals.permute(1, 2, 0)[inside].double(),
                                           formation_ops.sphere_directions(config.directions), rotation)


def camera_gains(config: FormationConfig, generator: torch.Generator) -> Tensor:
    """One image's exposure times white-balance gain per channel, :math:`(3,)` (ones when both are off).

    The white-balance gains have a geometric mean of 1, so the exposure alone sets the brightness.
    """
    if config.exposure_stops == 0 and config.white_balance == 0:
        return torch.ones(3, dtype=torch.float64)
    stops = config.exposure_stops * (2 * torch.rand((), generator=generator, dtype=torch.float64) - 1)
    log_gains = config.white_balance * torch.randn(3, generator=generator, dtype=torch.float64)
    return 2.0 ** stops * (log_gains - log_gains.mean()).exp()


def form_image(normals: Tensor, mask: Tensor, sh: Tensor, config: FormationConfig, generator: torch.Generator, *,
               gains: Optional[Tensor] = None, visibility: Optional[Tensor] = None,
               focal: Optional[float] = None) -> Tensor:
    """Render one image: :math:`(1, 3, H, W)` normals, :math:`(1, 1, H, W)` mask, :math:`(1, 3, 9)` lighting -> :math:`(1, 3, H, W)`.

    ``gains`` are the :func:`camera_gains` (default: none); shadows need the view's
    :func:`view_visibility`; the specular lobe's view vectors need ``focal`` for a
    perspective camera. ``generator`` draws the noise.

    Raises:
        ValueError: wrong shapes, sizes that differ, or a mask not all 0 and 1 (a soft
            mask would scale the image).
    """
    check_shape(normals, "normals", "1 3 H W")
    check_shape(sh, "sh", "1 3 9")
    mask = check_mask(mask, "mask", allow_full=True, allow_empty=True)
    check_same_size(normals, "normals", mask, "mask")
    inside = mask[0, 0]
    n = normals[0].permute(1, 2, 0)[inside].double()  # (N, 3)
    light = sh[0].double()
    if config.shadows:
        if visibility is None or visibility.shape != (n.shape[0], config.directions):
            raise ValueError(f"shadows need the view's visibility, ({n.shape[0]}, {config.directions}) bool")
        directions = formation_ops.sphere_directions(config.directions)
        shading = formation_ops.shade_environment(n, directions, formation_ops.sh_radiance(directions, light), visibility)
    else:
        shading = render_sh(normals.double(), light[None])[0].permute(1, 2, 0)[inside]
    if config.specular > 0:
        direction, colour = formation_ops.dominant_light(light)
        if focal is None:
            view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        else:
            uv = pixel_grid(*mask.shape[-2:], dtype=torch.float64).permute(1, 2, 0)[inside]
            view = torch.cat([-uv, torch.full_like(uv[:, :1], float(focal))], 1)
            view = view / view.norm(dim=1, keepdim=True)
        shading = shading + formation_ops.blinn_phong(n, view, direction, config.specular * colour.clamp_min(0),
                                                      config.shininess)
    image = torch.zeros(1, 3, *mask.shape[-2:], dtype=torch.float64)
    image[0].permute(1, 2, 0)[inside] = shading
    if gains is not None:
        image = formation_ops.expose(image, gains)
    image = formation_ops.poisson_gaussian_noise(image, config.shot_noise, config.noise, generator).clamp(0, 1)
    if config.bits is not None:
        image = formation_ops.quantise_srgb(image, config.bits)
    return (image * mask).float()


def _generator(seed: int, name: str) -> torch.Generator:
    return torch.Generator().manual_seed(seed * 1_000_003 + zlib.crc32(name.encode()))


def synthetic_scenes(
    shapes: Sequence[Shape],
    lightings: Sequence[Tuple[str, Tensor]],
    *,
    resolution: int = 256,
    focal: Optional[float] = None,
    formation: FormationConfig = FormationConfig(),
    lights_per_shape: Optional[int] = None,
    seed: int = 0,
) -> Iterator[Scene]:
    """Each shape seen from one random view under each lighting (or its own ``lights_per_shape`` of them).

    Each shape's view depends on ``seed`` and its name only, and each image's random
    degradations on ``seed`` and the image's name, so two formations score the same views
    and a shape is seen the same way whichever other shapes are asked for.

    Args:
        shapes: from :func:`scene_shapes`.
        lightings: ``(name, (3, 9))`` pairs, from :func:`evaluation_lightings` or
            :func:`validation_lightings`.
        resolution: image size.
        focal: perspective focal length in pixels; ``None`` for orthographic.
        formation: the image formation.
        lights_per_shape: shape ``k`` gets lightings ``k m .. (k + 1) m - 1`` (cycling);
            ``None`` gives every shape every lighting. At most ``len(lightings)``, so that
            a shape never gets a lighting twice (scene names are unique).

    Raises:
        ValueError: no lightings, or ``lights_per_shape`` not an integer in ``[1, len(lightings)]``.
    """
    # checked here, not on the first next() of the generator
    lightings = list(lightings)
    if not lightings:
        raise ValueError("lightings must hold at least one (name, (3, 9)) pair, got none")
    if lights_per_shape is not None and not is_integer(lights_per_shape, 1, len(lightings)):
        raise ValueError(f"lights_per_shape must be an integer in [1, {len(lightings)}] (the number of "
                         f"lightings), got {lights_per_shape!r}")
    return _synthetic_scenes(shapes, lightings, resolution, focal, formation, lights_per_shape, seed)


def _synthetic_scenes(shapes: Sequence[Shape], lightings: List[Tuple[str, Tensor]], resolution: int,
                      focal: Optional[float], formation: FormationConfig, lights_per_shape: Optional[int],
                      seed: int) -> Iterator[Scene]:
    for k, shape in enumerate(shapes):
        rotation = random_view_rotations(1, _generator(seed, shape.name))[0]
        view = render_normals(shape.mesh, rotation, resolution, focal=focal)
        normals, mask = view.normals[None], view.mask[None]
        visibility = view_visibility(view, shape.mesh, rotation, formation) if formation.shadows else None
        if lights_per_shape is None:
            chosen = lightings
        else:
            chosen = [lightings[(k * lights_per_shape + i) % len(lightings)] for i in range(lights_per_shape)]
        for light_name, sh in chosen:
            name = f"{shape.name}|{light_name}"
            generator = _generator(seed, name)
            gains = camera_gains(formation, generator)
            image = form_image(normals, mask, sh[None], formation, generator, gains=gains, visibility=visibility,
                               focal=focal)
            yield Scene(name, shape.name, light_name, image, mask, normals, (sh * gains[:, None]).float()[None],
                        sh[None].float(), focal)
