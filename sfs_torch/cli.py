"""The ``sfs-torch`` command (a Hydra app).

``sfs-torch`` alone runs the built-in demo end to end: an evaluation shape (never
used for training) rendered under a natural lighting, estimated in unknown
illumination, with outputs and a summary figure. ``sfs-torch image=... mask=...``
runs on the user's files; ``sfs-torch input_dir=... out=...`` on every item folder of
``input_dir`` (a batch, ``docs/batch.md``). Overrides are Hydra's ``key=value``.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Tuple

from ._openmp import short_openmp_waits

# the command owns its process, so it chooses how idle OpenMP threads wait before torch starts
short_openmp_waits()

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.core.config_store import ConfigStore  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from . import io  # noqa: E402
from ._app import exit_unless_writable, output_folder, parse_device  # noqa: E402
from ._checks import is_integer, is_number  # noqa: E402
from .denoise import DenoiseConfig  # noqa: E402
from .figures import confidence_display_max, summary_figure  # noqa: E402
from .forest import ForestConfig  # noqa: E402
from .geometry_db import DatabaseConfig, evaluation_shapes  # noqa: E402
from .integrability import depth_to_mesh  # noqa: E402
from .lighting import natural_lightings, render_sh, render_sphere  # noqa: E402
from .metrics import lmse, normal_metrics  # noqa: E402
from .model import ShapeFromShading  # noqa: E402
from .novel_view import NovelViewConfig, render_novel_view  # noqa: E402
from .pipeline import Estimate, PipelineConfig, TrainingConfig, estimate, moved_option_hint, resolve_config  # noqa: E402
from .preview import RendererChoice, choose_renderer, gl_context, renderer_name  # noqa: E402
from .reflectance_map import ReflectanceMapConfig  # noqa: E402
from .rendering import random_view_rotations, render_normals  # noqa: E402
from .silhouette import SilhouetteConfig, coarse_normals  # noqa: E402
from .texton import TextonConfig  # noqa: E402

log = logging.getLogger("sfs_torch")


@dataclass
class DemoConfig:
    """The built-in demo: which evaluation shape, lighting and view.

    Attributes:
        shape: index into the held-out evaluation shapes of ``database`` (6: a dog phalanx
            bone of the default collection; any index works).
        lighting: one of :func:`sfs_torch.lighting.natural_lightings`.
        albedo: scales the lighting so that the image stays within [0, 1].
        resolution: image size in pixels.
        view_seed: seed of the random viewpoint.
        noise_sigma: image noise, as in the paper's synthetic experiments.
    """

    shape: int = 6
    lighting: str = "grace_cathedral"
    albedo: float = 0.7
    resolution: int = 256
    view_seed: int = 0
    noise_sigma: float = 0.001


@dataclass
class AppConfig(PipelineConfig):
    """Command-line configuration: the pipeline's options plus inputs and outputs."""

    image: Optional[str] = None
    mask: Optional[str] = None
    lighting: Optional[str] = None
    image_srgb: bool = True
    out: Optional[str] = None
    # a batch: every item folder <input_dir>/<item>/ (image + mask, optional ground truth)
    # into <out>/<item>/, with <out>/summary.csv (docs/batch.md)
    input_dir: Optional[str] = None
    # batch: skip an item whose folder in out already holds every file this run would write
    skip_done: bool = True
    device: str = "cpu"
    # mesh files written when there is a depth map: any of io.MESH_FORMATS ("ply", "obj",
    # "glb"); [] for none. Typed Any so that a bad value reaches _mesh_formats' one-line error.
    mesh_formats: Any = field(default_factory=lambda: ["ply"])
    # novel_view.png (with a depth map): renderer auto | pyrender | embree, viewpoint, size (docs/rendering.md)
    novel_view: NovelViewConfig = field(default_factory=NovelViewConfig)
    demo: DemoConfig = field(default_factory=DemoConfig)


_store = ConfigStore.instance()
_store.store(name="sfs_torch_schema", node=AppConfig)
# The groups whose one option is the stage's config class as it is (``database=default`` ...):
# their values live in the classes alone. The other groups' options are the YAML files of
# conf/ (features/, integrate/, camera/, refine/, database/blobby.yaml), which override them.
STAGE_GROUPS = {"database": DatabaseConfig, "denoise": DenoiseConfig, "silhouette": SilhouetteConfig,
                "texton": TextonConfig, "reflectance_map": ReflectanceMapConfig, "training": TrainingConfig,
                "forest": ForestConfig}
for _group, _node in STAGE_GROUPS.items():
    _store.store(group=_group, name="default", node=_node)
# hydra.run.dir is `out` when given, else a dated folder (oc.select keeps a null value).
OmegaConf.register_new_resolver("sfs_torch_or", lambda value, default: default if value is None else value, replace=True)


def _pipeline_config(cfg: DictConfig) -> PipelineConfig:
    """The pipeline's options of the app's config, every one checked (:func:`~sfs_torch.pipeline.resolve_config`)."""
    keep = set(PipelineConfig.__dataclass_fields__)
    return resolve_config(OmegaConf.create({k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k in keep}))


def _check_demo_config(demo: DictConfig) -> None:
    """``ValueError`` naming the first bad ``demo.*`` option; cheap, so it runs before the
    meshes are fetched (the shape index is checked against the shapes once they are known)."""
    if not is_integer(demo.shape, 0):
        raise ValueError(f"demo.shape must be an integer >= 0, got {demo.shape!r}")
    names = sorted(natural_lightings())
    if demo.lighting not in names:
        raise ValueError(f"demo.lighting must be one of {names}, got {demo.lighting!r}")
    # a non-positive albedo renders a black image, which the pipeline would fit without complaint
    if not is_number(demo.albedo, 0, strict=True):
        raise ValueError(f"demo.albedo must be a number > 0, got {demo.albedo!r}")
    if not is_integer(demo.resolution, 8):
        raise ValueError(f"demo.resolution must be an integer >= 8, got {demo.resolution!r}")
    if not is_integer(demo.view_seed):
        raise ValueError(f"demo.view_seed must be an integer, got {demo.view_seed!r}")
    if not is_number(demo.noise_sigma, 0):
        raise ValueError(f"demo.noise_sigma must be a number >= 0, got {demo.noise_sigma!r}")


def _demo_inputs(cfg: DictConfig, device: torch.device) -> Dict[str, Any]:
    """Render the demo scene: an evaluation shape under a natural lighting."""
    shapes = evaluation_shapes(OmegaConf.to_object(cfg.database))
    if not 0 <= cfg.demo.shape < len(shapes):
        raise ValueError(f"demo.shape must be in [0, {len(shapes) - 1}], got {cfg.demo.shape}")
    lights = natural_lightings(cfg.demo.albedo)
    shape = shapes[cfg.demo.shape]
    generator = torch.Generator().manual_seed(cfg.demo.view_seed)
    view = render_normals(shape.mesh, random_view_rotations(1, generator)[0], cfg.demo.resolution)
    sh = lights[cfg.demo.lighting]
    normals = view.normals[None]
    mask = view.mask[None]
    image = render_sh(normals, sh[None]) * mask
    noise = cfg.demo.noise_sigma * torch.randn(image.shape, generator=generator)
    image = (image + noise).clamp(0, 1) * mask
    return {"image": image[0].to(device), "mask": mask[0].to(device), "normals": normals[0], "lighting": sh, "name": shape.name}


# written only by some runs: a rerun into the same folder without them removes them
OPTIONAL_OUTPUTS = ("depth.npy", "depth.png", "depth.json", *(f"mesh.{kind}" for kind in io.MESH_FORMATS), "novel_view.png")


def _mesh_formats(value: Any) -> Tuple[str, ...]:
    """Validate ``mesh_formats`` (a list of io.MESH_FORMATS, or one name); return them in order, once each."""
    allowed = ", ".join(io.MESH_FORMATS)
    example = "(e.g. mesh_formats=[ply,glb], [] for none)"
    names = [value] if isinstance(value, str) else value
    if OmegaConf.is_list(names):
        names = OmegaConf.to_container(names)
    if not isinstance(names, (list, tuple)) or not all(isinstance(name, str) for name in names):
        raise ValueError(f"mesh_formats must be a list of {allowed} {example}, got {value!r}")
    unknown = [name for name in names if name.lower() not in io.MESH_FORMATS]
    if unknown:
        raise ValueError(f"mesh_formats may hold {allowed} {example}, got {unknown[0]!r}")
    return tuple(dict.fromkeys(name.lower() for name in names))


@dataclass(frozen=True)
class _NovelView:
    """``novel_view`` checked: the viewpoint, and the renderer resolved (``None`` when no novel view is drawn)."""

    choice: Optional[RendererChoice]
    azimuth_deg: float
    elevation_deg: float
    resolution: int


def _novel_view(cfg: DictConfig, pipeline_cfg: PipelineConfig, given: Optional[bool] = None) -> _NovelView:
    """Validate ``novel_view`` and resolve its renderer, before any work.

    The renderer is resolved (an OpenGL context made, ~1 s) only when a novel view may be
    drawn, i.e. when the call returns a depth map (:func:`_returns_depth`) for a lighting
    that is ``given`` or not (``None``: a batch, whose items may be either); its name is
    checked always.
    """
    view = cfg.get("novel_view") or OmegaConf.structured(NovelViewConfig)
    try:
        azimuth, elevation, resolution = float(view.azimuth_deg), float(view.elevation_deg), view.resolution
    except (TypeError, ValueError):
        raise ValueError(f"novel_view.azimuth_deg and elevation_deg must be numbers, got {view.azimuth_deg!r}, "
                         f"{view.elevation_deg!r}") from None
    if not (np.isfinite(azimuth) and np.isfinite(elevation)):
        raise ValueError(f"novel_view.azimuth_deg and elevation_deg must be finite, got {azimuth}, {elevation}")
    if not is_integer(resolution, 1):
        raise ValueError(f"novel_view.resolution must be a positive integer, got {resolution!r}")
    name = renderer_name(view.renderer, "novel_view.renderer")
    kinds = (False, True) if given is None else (given,)
    if not any(_returns_depth(pipeline_cfg, kind) for kind in kinds):  # no depth map, no novel view
        return _NovelView(None, azimuth, elevation, resolution)
    choice = choose_renderer(name, None if name == "embree" else gl_context(), key="novel_view.renderer")
    log.info("novel view renderer: %s", choice.reason)
    return _NovelView(choice, azimuth, elevation, resolution)


def _write_outputs(out: Path, est: Estimate, camera: Any, mesh_formats: Tuple[str, ...],
                   novel_view: Optional[_NovelView] = None) -> None:
    normals = est.normals.cpu()
    io.write_normals_npy(out / "normals.npy", normals)
    io.write_normals_png(out / "normals.png", normals)
    io.write_lighting(out / "lighting.json", est.lighting.cpu())
    io.write_image(out / "reflectance_map.png", render_sphere(est.lighting.cpu(), 256).clamp(0, 1))
    kappa = est.confidence.cpu()
    scale = confidence_display_max(kappa, est.mask.cpu())
    io.write_image(out / "confidence.png", (kappa[0] / scale).clamp(0, 1), srgb=False)
    if est.depth is not None:
        depth, mask = est.depth.cpu()[0], est.mask.cpu()[0]
        np.save(out / "depth.npy", depth.numpy().astype("float32"))
        decode = io.write_depth_png(out / "depth.png", depth, mask)
        (out / "depth.json").write_text(json.dumps(_depth_description(decode, camera), indent=2) + "\n")
        mesh = depth_to_mesh(depth, mask, camera.focal, camera.principal_point)
        # vertex k is the k-th mask pixel in row-major order: its normal is the estimate there
        vertex_normals = est.normals.cpu()[:, mask].T
        for kind in mesh_formats:
            io.write_mesh(out / f"mesh.{kind}", mesh, vertex_normals=vertex_normals)
        view = novel_view or _NovelView(None, 35.0, 20.0, 256)
        renderer = "embree" if view.choice is None else view.choice.name
        image = render_novel_view(mesh, est.lighting.cpu(), azimuth_deg=view.azimuth_deg, elevation_deg=view.elevation_deg,
                                  resolution=view.resolution, renderer=renderer)
        io.write_image(out / "novel_view.png", image)


def _depth_description(decode: Dict[str, float], camera: Any) -> Dict[str, Any]:
    """``depth.json``: how ``depth.png`` decodes to the values of ``depth.npy``, and what they mean."""
    if camera.focal is None:
        meaning = "orthographic: height towards the viewer (camera-frame z, larger = nearer) in pixels, up to an offset"
    else:
        meaning = "perspective: distance d along the optical axis (the point d (u/f, v/f, -1)), up to a global scale"
    principal_point = None if camera.principal_point is None else list(camera.principal_point)
    return {
        "file": "depth.png",
        "decode": "depth = scale * code + offset where code > 0; code 0 is outside the mask",
        **decode,
        "depth": meaning,
        "focal": camera.focal,
        "principal_point": principal_point,
    }


def _publish(staging: Path, out: Path) -> None:
    """Move every finished file into ``out`` (atomic renames) and drop a previous run's extras."""
    for name in OPTIONAL_OUTPUTS:
        if not (staging / name).exists():
            (out / name).unlink(missing_ok=True)
    for path in sorted(staging.iterdir()):
        os.replace(path, out / path.name)


def _device(name: str) -> torch.device:
    return parse_device(name)


def _output_folder(cfg: DictConfig) -> Path:
    return output_folder(cfg, "sfs-torch")


def run(cfg: DictConfig) -> Dict[str, float]:
    """Run the app on one image (or the demo); returns the key numbers (also written as JSON).

    Raises:
        ValueError: bad options or inputs; ``input_dir`` is set (a batch: :func:`run_batch`).
        FileNotFoundError: an input file is missing.
    """
    if cfg.get("input_dir") is not None:
        raise ValueError("input_dir is a batch run: call sfs_torch.cli.run_batch (the command does)")
    pipeline_cfg = _pipeline_config(cfg)
    device = _device(cfg.device)
    mesh_formats = _mesh_formats(cfg.mesh_formats)
    if cfg.image is None:
        _check_demo_config(cfg.demo)
    out = _output_folder(cfg)
    novel_view = _novel_view(cfg, pipeline_cfg, given=cfg.image is not None and bool(cfg.lighting))
    true_normals = true_lighting = None
    if cfg.image is None:
        if cfg.mask is not None:
            raise ValueError("mask was given without image: pass image=PATH too (or neither for the demo)")
        demo = _demo_inputs(cfg, device)
        image, mask, known = demo["image"], demo["mask"], None
        true_normals, true_lighting = demo["normals"], demo["lighting"]
        title = f"sfs-torch: demo {demo['name']}"
        log.info("demo: evaluation shape %r under %s", demo["name"], cfg.demo.lighting)
    else:
        loaded = io.read_image_and_mask(cfg.image, cfg.mask, srgb=cfg.image_srgb)
        image, mask = loaded.image.to(device), loaded.mask.to(device)
        known = io.read_lighting(cfg.lighting) if cfg.lighting else None
        title = f"sfs-torch: {cfg.image}"
    numbers = _estimate_and_publish(
        out, image, mask, known, pipeline_cfg, mesh_formats, title, true_normals=true_normals, true_lighting=true_lighting,
        novel_view=novel_view,
    )
    for key, value in numbers.items():
        log.info("%-32s %.4g", key, value)
    log.info("outputs written to %s", out.resolve())
    return numbers


def _estimate_and_publish(
    out: Path, image: torch.Tensor, mask: torch.Tensor, known: Optional[torch.Tensor], pipeline_cfg: PipelineConfig,
    mesh_formats: Tuple[str, ...], title: str, *, true_normals: Optional[torch.Tensor] = None,
    true_lighting: Optional[torch.Tensor] = None, progress: bool = True, novel_view: Optional[_NovelView] = None,
    model: Optional[ShapeFromShading] = None,
) -> Dict[str, float]:
    """Estimate one image and publish its outputs into ``out``; return the key numbers.

    The single-image path of the command, shared by the demo, ``image=`` and every item of
    a batch. ``image`` is :math:`(3, H, W)`, ``mask`` :math:`(1, H, W)`; ``true_normals``
    :math:`(3, H, W)` and ``true_lighting`` :math:`(3, 9)`, when known, are scored;
    ``novel_view`` (:func:`_novel_view`) draws ``novel_view.png`` (default: the ray caster);
    ``model`` holds the example-geometry database of ``pipeline_cfg.database`` across the
    calls of a batch (:meth:`~sfs_torch.model.ShapeFromShading.database`), ``None``: this
    call loads it.
    """
    database = None if model is None else model.database(image.device)
    start = time.perf_counter()
    est = estimate(image, mask, lighting=known, config=pipeline_cfg, progress=progress, database=database)
    seconds = time.perf_counter() - start
    # every file is written under a hidden staging folder first and renamed into place
    # when all are complete: a killed run leaves no half-written file under a final name
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".sfs-torch-partial-", dir=out))
    try:
        _write_outputs(staging, est, pipeline_cfg.camera, mesh_formats, novel_view)
        numbers = _finish(staging, est, seconds, image, mask, title, true_normals, true_lighting,
                          pipeline_cfg.silhouette)
        _publish(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return numbers


def _finish(out: Path, est: Estimate, seconds: float, image, mask, title: str, true_normals, true_lighting,
            silhouette: Optional[SilhouetteConfig] = None) -> Dict[str, float]:
    """Write the key numbers (``metrics.json``) and the summary figure; return the numbers.

    ``seconds`` is the call's wall time: its stages nest (the final round holds a forest's
    training), so their sum would count some time twice."""
    # the database's first build or reload is a one-off, not part of a call
    numbers: Dict[str, float] = {"time per call (s)": seconds - est.timings.get("database", 0.0)}
    for stage, stage_seconds in est.timings.items():
        numbers[f"time {stage} (s)"] = stage_seconds
    if true_normals is not None:
        truth = true_normals.cpu()[None]
        metrics = normal_metrics(est.normals[None].cpu(), truth, mask[None].cpu())
        baseline = normal_metrics(coarse_normals(mask[None].cpu(), config=silhouette), truth, mask[None].cpu())
        scores = {
            "median error (deg)": float(metrics.median[0]),
            "mean error (deg)": float(metrics.mean[0]),
            "< 22.5 deg": float(metrics.under_22_5[0]),
            "silhouette-only median (deg)": float(baseline.median[0]),
        }
        if true_lighting is not None:
            scores["lighting lMSE"] = float(lmse(est.lighting[None].cpu(), true_lighting.cpu()[None])[0])
        numbers = {**scores, **numbers}
    summary_numbers = {k: v for k, v in numbers.items() if not k.startswith("time ") or k == "time per call (s)"}
    summary_figure(
        out / "summary.png", image.cpu(), mask.cpu(), est.normals.cpu(), est.lighting.cpu(),
        true_normals=None if true_normals is None else true_normals.cpu(),
        true_lighting=None if true_lighting is None else true_lighting.cpu(),
        confidence=est.confidence.cpu(), depth=None if est.depth is None else est.depth.cpu(),
        numbers=summary_numbers, title=title,
    )
    (out / "metrics.json").write_text(json.dumps(numbers, indent=2))
    return numbers


# ------------------------------------------------------------------------------------------
# Batch: every item folder of input_dir (docs/batch.md)

# written by every run; the depth outputs, meshes and novel view also with a depth map (_returns_depth)
REQUIRED_OUTPUTS = ("normals.npy", "normals.png", "lighting.json", "reflectance_map.png", "confidence.png",
                    "summary.png", "metrics.json")
SUMMARY_COLUMNS = ("item", "status", "seconds", "error", "median_error_deg")


@dataclass(frozen=True)
class BatchItem:
    """One row of ``summary.csv``.

    Attributes:
        item: the item folder's name (its outputs are in ``<out>/<item>/``).
        status: ``"ok"``, ``"failed"`` or ``"skipped"`` (its outputs were complete).
        seconds: wall-clock seconds this run spent on the item (reading, estimating, writing).
        error: the failure in one line; ``""`` unless failed.
        median_error_deg: median angular error against the item's ground-truth normals
            (``normals.npy`` / ``normals.png``), ``None`` without them or when failed; a
            skipped item's comes from its ``metrics.json``.
    """

    item: str
    status: str
    seconds: float
    error: str = ""
    median_error_deg: Optional[float] = None


@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` did: one :class:`BatchItem` per item folder, in name order.

    Attributes:
        items: the rows of ``summary.csv``.
        summary: the path of ``summary.csv``.
    """

    items: Tuple[BatchItem, ...]
    summary: Path

    def count(self, status: str) -> int:
        """How many items have ``status`` (``"ok"``, ``"failed"`` or ``"skipped"``)."""
        return sum(item.status == status for item in self.items)


def run_batch(cfg: DictConfig) -> BatchResult:
    """Run the app on every item folder of ``cfg.input_dir``, one after the other.

    Every item ``<input_dir>/<item>/`` holds ``image.png`` (or ``image.npy``) and
    ``mask.png`` (or ``mask.npy``), optionally ``normals``, ``lighting.json`` and
    ``camera.json``: the ``folder`` layout of :func:`sfs_torch.dataset_loaders.load_folder`.
    Its outputs, those of a single-image run, go to ``<out>/<item>/``. An item that fails is
    logged in one line and the batch goes on; one whose outputs are complete is skipped
    (unless ``skip_done=false``). ``<out>/summary.csv`` is rewritten after every item. The
    example-geometry database is loaded once, at the first item estimated, and kept on
    ``device`` for the others.

    Returns:
        :class:`BatchResult`.

    Raises:
        ValueError: bad options; ``input_dir`` is not a folder, holds no item folder, or
            holds ``out``; ``image``, ``mask`` or ``lighting`` is given too. All are
            checked before any item is read.
        FileNotFoundError: ``input_dir`` does not exist.
    """
    pipeline_cfg = _pipeline_config(cfg)
    _device(cfg.device)
    mesh_formats = _mesh_formats(cfg.mesh_formats)
    out = _output_folder(cfg)
    folders = _batch_folders(cfg, out)
    novel_view = _novel_view(cfg, pipeline_cfg)
    # holds the example-geometry database, loaded at the first item that is estimated, for all the others
    model = ShapeFromShading(pipeline_cfg, progress=False)
    out.mkdir(parents=True, exist_ok=True)
    summary = out / "summary.csv"
    rows: List[BatchItem] = []
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    bar = tqdm(folders, desc="sfs-torch", unit="item", dynamic_ncols=True)
    with _quiet_stages(), logging_redirect_tqdm(), bar:
        for folder in bar:
            bar.set_postfix_str(", ".join([*_counts(rows), folder.name]))
            rows.append(_batch_item(cfg, folder, out / folder.name, pipeline_cfg, mesh_formats, model, novel_view))
            _write_summary(summary, rows)
        bar.set_postfix_str(", ".join(_counts(rows)))
    result = BatchResult(tuple(rows), summary)
    log.info("%d ok, %d failed, %d skipped; summary in %s", result.count("ok"), result.count("failed"),
             result.count("skipped"), summary.resolve())
    return result


def _counts(rows: List[BatchItem]) -> List[str]:
    return [f"{n} {s}" for s in ("ok", "failed", "skipped") if (n := sum(r.status == s for r in rows))]


def _batch_folders(cfg: DictConfig, out: Path) -> List[Path]:
    """Check the batch options and ``input_dir``; return its item folders, sorted by name."""
    given = [name for name in ("image", "mask", "lighting") if cfg[name] is not None]
    if given:
        raise ValueError(
            f"input_dir runs every item folder of {cfg.input_dir}, so {given[0]}= cannot be given too: each item holds "
            "its own image.png, mask.png and optional lighting.json (docs/batch.md)"
        )
    if not cfg.image_srgb:
        raise ValueError(
            "image_srgb=false does not apply to input_dir: an item's image.png is read as sRGB; store linear "
            "images as image.npy (float (H, W, 3) in [0, 1]; docs/batch.md)"
        )
    root = Path(cfg.input_dir)
    if not root.exists():
        raise FileNotFoundError(f"input_dir: no such folder '{root}'")
    if not root.is_dir():
        raise ValueError(f"input_dir must be a folder of item folders, got the file '{root}'")
    folders = [p for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith((".", "_"))]
    if not folders:
        raise ValueError(
            f"input_dir '{root}' holds no item folder: expected '{root}/<item>/image.png' (or image.npy) with "
            "mask.png (or mask.npy) beside it (docs/batch.md)"
        )
    try:
        inside = out.resolve().relative_to(root.resolve()).parts
    except ValueError:
        inside = None
    if inside is not None and (not inside or not inside[0].startswith((".", "_"))):
        raise ValueError(
            f"out={out} is inside input_dir={root}: the outputs would mix with the items (name.png files, a "
            "normals.npy read as ground truth); write them elsewhere"
        )
    return folders


def _returns_depth(pipeline_cfg: PipelineConfig, given: bool) -> bool:
    """Whether :func:`~sfs_torch.pipeline.estimate` with these options returns a depth map
    (``Estimate.depth``), for a given (``given``) or an estimated lighting, without running it.

    The rule of ``estimate``: integrability gives one; otherwise the photometric refinement
    does when it runs (``refine.when``) with the surface model, which ``refine.model="auto"``
    picks when the lighting is optimised (never a given one).
    """
    if pipeline_cfg.integrate.method != "none":
        return True
    refine = pipeline_cfg.refine
    if not (refine.when == "always" or (refine.when == "known" and given)):
        return False
    if refine.model == "auto":
        return refine.optimise_lighting and not given
    return refine.model == "surface"


def _expected_outputs(pipeline_cfg: PipelineConfig, mesh_formats: Tuple[str, ...], given: bool) -> Tuple[str, ...]:
    """The files a run with these options writes for an item whose lighting is ``given``
    (its ``lighting.json``) or estimated: with a depth map, :func:`_write_outputs` adds the
    depth files, the meshes and the novel view."""
    names = list(REQUIRED_OUTPUTS)
    if _returns_depth(pipeline_cfg, given):
        names += ["depth.npy", "depth.png", "depth.json", "novel_view.png", *(f"mesh.{kind}" for kind in mesh_formats)]
    return tuple(names)


def _batch_item(cfg: DictConfig, folder: Path, target: Path, pipeline_cfg: PipelineConfig,
                mesh_formats: Tuple[str, ...], model: ShapeFromShading,
                novel_view: Optional[_NovelView] = None) -> BatchItem:
    """Run one item (``model``: the batch's, which holds the database); a failure becomes a
    ``failed`` row (and one log line), never an exception."""
    start = time.perf_counter()
    # an item's lighting.json (read by _read_item) makes its lighting given: no refined surface by default
    expected = _expected_outputs(pipeline_cfg, mesh_formats, given=(folder / "lighting.json").is_file())
    if cfg.skip_done and all((target / name).is_file() for name in expected):
        return BatchItem(folder.name, "skipped", time.perf_counter() - start,
                         median_error_deg=_median_error(target / "metrics.json"))
    try:
        device = torch.device(cfg.device)
        scene = _read_item(folder)
        item_cfg = pipeline_cfg
        camera = {key: value for key, value in (("focal", scene.focal), ("principal_point", scene.principal_point))
                  if value is not None}
        if camera:  # camera.json overrides camera.focal / camera.principal_point for this item
            item_cfg = resolve_config(OmegaConf.merge(pipeline_cfg, {"camera": {k: list(v) if isinstance(v, tuple) else v
                                                                                for k, v in camera.items()}}))
        known = scene.lighting[0] if scene.lighting_name == "given" else None
        true_normals = None if scene.normals is None else scene.normals[0]
        numbers = _estimate_and_publish(
            target, scene.image[0].to(device), scene.mask[0].to(device), known, item_cfg, mesh_formats,
            f"sfs-torch: {folder}", true_normals=true_normals, progress=False, novel_view=novel_view, model=model,
        )
    except Exception as err:  # one item's failure, whatever it is, must not stop the batch
        message = " ".join(str(err).split())
        if not isinstance(err, (ValueError, FileNotFoundError)):
            message = f"{type(err).__name__}: {message}"
        log.error("%s: failed: %s", folder.name, message)
        log.debug("%s: traceback", folder.name, exc_info=True)
        return BatchItem(folder.name, "failed", time.perf_counter() - start, error=message)
    seconds = time.perf_counter() - start
    median = numbers.get("median error (deg)")
    log.info("%s: ok in %.1f s%s", folder.name, seconds, "" if median is None else f", median error {median:.2f} deg")
    return BatchItem(folder.name, "ok", seconds, median_error_deg=median)


def _read_item(folder: Path):
    """One item in the ``folder`` layout, read and checked as :func:`~sfs_torch.dataset_loaders.load_folder` does."""
    from .dataset_loaders import _folder_scene, _one_of

    image = _one_of(folder, ("image.png", "image.npy"), required=True)
    mask = _one_of(folder, ("mask.png", "mask.npy"), required=True)
    normals = _one_of(folder, ("normals.npy", "normals.png"), required=False)
    lighting, camera = folder / "lighting.json", folder / "camera.json"
    return _folder_scene(folder, image, mask, normals, lighting if lighting.is_file() else None,
                         camera if camera.is_file() else None)


def _median_error(metrics_path: Path) -> Optional[float]:
    try:
        value = json.loads(metrics_path.read_text()).get("median error (deg)")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, (int, float)) else None


def _write_summary(path: Path, rows: List[BatchItem]) -> None:
    """``summary.csv``, replaced atomically: one row per item, columns :data:`SUMMARY_COLUMNS`."""
    import csv

    partial = path.with_name(f".{path.name}.partial")
    with open(partial, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(SUMMARY_COLUMNS)
        for row in rows:
            median = "" if row.median_error_deg is None else f"{row.median_error_deg:.4f}"
            writer.writerow([row.item, row.status, f"{row.seconds:.2f}", row.error, median])
    os.replace(partial, path)


@contextmanager
def _quiet_stages() -> Iterator[None]:
    """During a batch the pipeline's per-stage log lines and Python warnings go through logging (and
    so clear of the progress bar); the stages only at WARNING."""
    logger = logging.getLogger("sfs_torch.pipeline")
    level = logger.level
    logger.setLevel(logging.WARNING)
    logging.captureWarnings(True)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        logger.setLevel(level)


@hydra.main(version_base="1.3", config_path="pkg://sfs_torch.conf", config_name="config")
def _main(cfg: DictConfig) -> None:
    try:
        if cfg.get("input_dir") is not None:
            result = run_batch(cfg)
            if result.count("failed"):
                sys.exit(1)  # the batch ran to the end, but not every item succeeded
        else:
            run(cfg)
    except (ValueError, FileNotFoundError) as err:
        # A user error gets one clear line, not a stack trace.
        log.error("%s", err)
        sys.exit(2)


def _check_out_argument(args: list) -> None:
    """Fail with one line when ``out=`` cannot be written, before Hydra sets up its log file there,
    or when an option is given under the key it had before it moved (``MOVED_OPTIONS``)."""
    for arg in args:
        if arg.startswith("out=") and arg[4:] not in ("", "null"):
            exit_unless_writable(Path(arg[4:]), f"sfs-torch: cannot write to out={arg[4:]}")
        hint = moved_option_hint(arg)
        if hint:
            print(f"sfs-torch: {hint}", file=sys.stderr)
            sys.exit(2)


def main() -> None:
    _check_out_argument(sys.argv[1:])
    _main()
