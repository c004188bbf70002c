"""The ``sfs-torch-eval`` command: score every case of a dataset with every method.

``sfs-torch-eval dataset=<synthetic|folder|mit_berkeley|diligent> dataset.root=<dir> out=<dir>``
runs each method (:data:`METHODS`) on each case (:class:`~sfs_torch.datasets.Scene`) and
writes into ``out``:

- ``cases.csv``: one row per case and method (:data:`COLUMNS`); error columns are empty
  where the case has no ground truth. Each finished case's rows are appended and flushed
  at once, so an interrupted run loses only the case in progress, and a rerun into the
  same ``out`` skips every (case, method) already there (``resume=true``);
- ``summary.json`` and ``report.md``: per method, the median over cases of the per-case
  median error, the means of the other scores, and the time per case;
- ``figures/<case>.png``: the input and each method's angular-error map (the paper's
  Fig. 7 and 9), via :func:`sfs_torch.figures.error_map_figure`;
- ``eval_config.json``: what the scores depend on, checked when a run is resumed.

The scoring is plain functions (:func:`run_method`, :func:`score`, :func:`summarise`,
:func:`report_markdown`, :func:`evaluate`); the Hydra entry point only composes the
config (``conf/eval.yaml``, group ``conf/dataset/``) and turns user errors into one line
on stderr and exit code 2. The options are documented in ``docs/evaluation.md``.
"""
from __future__ import annotations

import csv
import hashlib
import io as _io
import json
import logging
import os
import re
import shlex
import statistics
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Set, Tuple

from ._openmp import short_openmp_waits

short_openmp_waits()  # as sfs-torch does, before torch starts

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.config_store import ConfigStore  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402
from torch import Tensor  # noqa: E402

from ._app import exit_unless_writable, output_folder, parse_device  # noqa: E402
from ._checks import is_integer, is_number  # noqa: E402
from .datasets import DEGRADATIONS, EVALUATION_LIGHTINGS, Scene  # noqa: E402
from .geometry_db import GeometryDatabase, load_database  # noqa: E402
from .metrics import lmse, normal_metrics  # noqa: E402
from .pipeline import FeatureConfig, PipelineConfig, TrainingConfig, moved_option_hint, resolve_config  # noqa: E402
from .refine import RefineConfig, check_refine_config  # noqa: E402

__all__ = [
    "METHODS", "BASE_METHODS", "DATASETS", "COLUMNS", "EvalConfig", "SyntheticDatasetConfig", "FolderDatasetConfig",
    "MitBerkeleyDatasetConfig", "DiligentDatasetConfig", "MethodResult", "CaseScores", "Cases", "run_method",
    "score", "score_case", "summarise", "report_markdown", "load_cases", "read_rows", "evaluate", "main",
]

log = logging.getLogger("sfs_torch.evaluate")

PROGRAM = "sfs-torch-eval"
DATASETS = ("synthetic", "folder", "mit_berkeley", "diligent")
BASE_METHODS = ("silhouette", "flat", "estimated_lighting", "known_lighting", "classical")
COLUMNS = ("case", "method", "shape", "lighting", "pixels", "focal", "mae_deg", "median_deg", "mean_deg",
           "under_11_25", "under_22_5", "under_30", "nmse", "lmse", "time_s")
SCORE_COLUMNS = ("mae_deg", "median_deg", "mean_deg", "under_11_25", "under_22_5", "under_30", "nmse", "lmse")


# ------------------------------------------------------------------------------------------
# Configuration (defaults here; conf/eval.yaml and conf/dataset/*.yaml only select them)


@dataclass
class SyntheticDatasetConfig:
    """Held-out shapes rendered under natural lightings (:mod:`sfs_torch.datasets`).

    Attributes:
        shapes: how many shapes of ``side`` (``None``: all of them, on the test and
            validation sides, which are the evaluation split of ``pipeline.database``, never
            trained on).
        lights: how many lightings: the first R&H probes on the test side, Poly Haven
            lightings under random camera rotations on the tuning sides.
        side: ``"test"`` (report on it), ``"validation"`` (tune on it) or ``"spare"`` (tune on
            a larger pool: training-draw shapes neither the database nor the relief prior has
            seen, ``shapes`` of them, under the validation side's lightings).
        degradation: a key of :data:`sfs_torch.datasets.DEGRADATIONS` (``exact`` is the paper's).
        focal: perspective focal length in pixels; ``None``: orthographic.
        resolution: image size in pixels.
        sphere: add a unit sphere as the first shape.
        lights_per_shape: each shape under its own this many lightings; ``None``: every lighting.
        seed: of the views and the noise.
        root: unused (synthetic scenes need no files).
    """

    name: str = "synthetic"
    shapes: Optional[int] = None
    lights: int = 3
    side: str = "test"
    degradation: str = "exact"
    focal: Optional[float] = None
    resolution: int = 256
    sphere: bool = False
    lights_per_shape: Optional[int] = None
    seed: int = 0
    root: Optional[str] = None


@dataclass
class FolderDatasetConfig:
    """Our plain layout, one folder per case (:func:`sfs_torch.dataset_loaders.load_folder`)."""

    name: str = "folder"
    root: Optional[str] = None


@dataclass
class MitBerkeleyDatasetConfig:
    """MIT-Berkeley Intrinsic Images, natural light (:func:`~sfs_torch.dataset_loaders.load_mit_berkeley`).

    Attributes:
        objects: object names; ``None``: all.
    """

    name: str = "mit_berkeley"
    root: Optional[str] = None
    objects: Optional[List[str]] = None


@dataclass
class DiligentDatasetConfig:
    """DiLiGenT, one case per object and light (:func:`~sfs_torch.dataset_loaders.load_diligent`).

    Attributes:
        objects: object names; ``None``: all.
        lights: light indices (0-based); ``None``: all 96.
        perspective: use the calibrated camera (``False``: orthographic).
    """

    name: str = "diligent"
    root: Optional[str] = None
    objects: Optional[List[str]] = None
    lights: Optional[List[int]] = None
    perspective: bool = True


def _eval_pipeline() -> PipelineConfig:
    # forests are not cached: every estimate's time_s then includes its training (Table 1b)
    return PipelineConfig(training=TrainingConfig(cache_forests="never"))


def _classical() -> RefineConfig:
    # optimisation-based SfS: an integrable surface fitted to the image under the known
    # lighting, held fixed, with no pull towards any learnt normals
    return RefineConfig(when="known", model="surface", normal_weight=0.0, optimise_lighting=False)


@dataclass
class EvalConfig:
    """The ``sfs-torch-eval`` options (``docs/evaluation.md``).

    Attributes:
        dataset: one of the ``dataset`` group (:data:`DATASETS`).
        out: output folder; ``None``: ``outputs/eval/<date>/<time>``; in a sweep one subfolder per job.
        methods: which of :data:`METHODS` to run, in this order.
        pipeline: options of :func:`sfs_torch.estimate` (as ``sfs-torch`` takes them).
        classical: the ``classical`` method's :class:`~sfs_torch.refine.RefineConfig`.
        figures: write ``figures/<case>.png``.
        progress: show a progress bar.
        resume: skip the (case, method) rows already in ``out/cases.csv``; ``False`` starts over.
        limit: score only the first this many cases; ``None``: all.
        log_stages: log the seconds of every stage of every :func:`sfs_torch.estimate` call.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
    """

    dataset: Any = None
    out: Optional[str] = None
    methods: List[str] = field(default_factory=lambda: list(BASE_METHODS))
    pipeline: PipelineConfig = field(default_factory=_eval_pipeline)
    classical: RefineConfig = field(default_factory=_classical)
    figures: bool = True
    progress: bool = True
    resume: bool = True
    limit: Optional[int] = None
    log_stages: bool = False
    device: str = "cpu"


_store = ConfigStore.instance()
_store.store(name="sfs_torch_eval_schema", node=EvalConfig)
_store.store(group="dataset", name="synthetic_schema", node=SyntheticDatasetConfig)
_store.store(group="dataset", name="folder_schema", node=FolderDatasetConfig)
_store.store(group="dataset", name="mit_berkeley_schema", node=MitBerkeleyDatasetConfig)
_store.store(group="dataset", name="diligent_schema", node=DiligentDatasetConfig)
if not OmegaConf.has_resolver("sfs_torch_or"):  # the one sfs-torch's config uses (sfs_torch.cli)
    OmegaConf.register_new_resolver("sfs_torch_or", lambda value, default: default if value is None else value)


# ------------------------------------------------------------------------------------------
# Methods


@dataclass(frozen=True)
class MethodResult:
    """What one method made of one case.

    Attributes:
        normals: :math:`(1, 3, H, W)` camera-frame normals on the CPU, 0 outside the mask.
        lighting: :math:`(1, 3, 9)` the lighting the method estimated, ``None`` when it
            estimates none or was given the case's own (no lMSE is then scored).
        seconds: wall time of the method, without loading the example-geometry database.
    """

    normals: Tensor
    lighting: Optional[Tensor]
    seconds: float


@dataclass(frozen=True)
class _Method:
    needs_lighting: bool
    uses_forest: bool
    run: Callable[["_Context", Scene], Tuple[Tensor, Optional[Tensor], float]]
    description: str


@dataclass(frozen=True)
class _Context:
    pipeline: PipelineConfig
    classical: RefineConfig
    device: torch.device
    database: Optional[GeometryDatabase]


def _on_device(scene: Scene, device: torch.device) -> Tuple[Tensor, Tensor]:
    return scene.image.to(device), scene.mask.to(device)


def _silhouette(ctx: _Context, scene: Scene):
    from .silhouette import coarse_normals

    _, mask = _on_device(scene, ctx.device)
    return coarse_normals(mask, focal=scene.focal, principal_point=scene.principal_point), None, 0.0


def _flat(ctx: _Context, scene: Scene):
    normals = torch.zeros(scene.mask.shape[0], 3, *scene.mask.shape[-2:])
    normals[:, 2] = 1.0
    return normals * scene.mask, None, 0.0


def _estimator(*, known: bool, integrate: Optional[str] = None,
               features: Optional[FeatureConfig] = None, forest_only: bool = False):
    def run(ctx: _Context, scene: Scene):
        from .pipeline import estimate

        cfg = ctx.pipeline
        if features is not None:
            cfg = replace(cfg, features=features)
        if forest_only:
            cfg = replace(cfg, refine=replace(cfg.refine, when="never"))
        image, mask = _on_device(scene, ctx.device)
        lighting = scene.lighting.to(ctx.device) if known else None
        est = estimate(image, mask, focal=scene.focal, principal_point=scene.principal_point, lighting=lighting,
                       integrate=integrate, config=cfg, progress=False, database=ctx.database)
        # a given lighting is the case's own: nothing to score
        return est.normals, None if known else est.lighting, est.timings.get("database", 0.0)

    return run


def _classical_sfs(ctx: _Context, scene: Scene):
    from .refine import refine_shape_and_lighting
    from .silhouette import coarse_normals

    image, mask = _on_device(scene, ctx.device)
    start = coarse_normals(mask, focal=scene.focal, principal_point=scene.principal_point)
    refined = refine_shape_and_lighting(image, mask, start, scene.lighting.to(ctx.device), focal=scene.focal,
                                        principal_point=scene.principal_point,
                                        config=replace(ctx.classical, optimise_lighting=False))
    return refined.normals, None, 0.0


METHODS: Dict[str, _Method] = {
    "silhouette": _Method(False, False, _silhouette,
                          "silhouette-only coarse normals (Eq. 10; perspective with a focal)"),
    "flat": _Method(False, False, _flat, "the constant normal (0, 0, 1)"),
    "estimated_lighting": _Method(False, True, _estimator(known=False), "sfs_torch.estimate, lighting estimated"),
    "known_lighting": _Method(True, True, _estimator(known=True), "sfs_torch.estimate with the case's lighting"),
    "classical": _Method(True, False, _classical_sfs,
                         "optimisation-based SfS: refine_shape_and_lighting (surface model, no forest prior, "
                         "lighting fixed) from the silhouette normals"),
    # Table 1a: the forest alone (no photometric refinement) in known lighting, by features
    "known_lighting_forest": _Method(True, True, _estimator(known=True, forest_only=True),
                                     "known lighting, forest only (Table 1a: +Silh+Tex)"),
    "known_lighting_rgb": _Method(True, True, _estimator(known=True, forest_only=True,
                                                         features=FeatureConfig(True, False, False)),
                                  "known lighting, forest only, RGB features (Table 1a: RGB)"),
    "known_lighting_rgb_silh": _Method(True, True, _estimator(known=True, forest_only=True,
                                                              features=FeatureConfig(True, True, False)),
                                       "known lighting, forest only, RGB + silhouette (Table 1a: +Silh)"),
    "known_lighting_rgb_tex": _Method(True, True, _estimator(known=True, forest_only=True,
                                                             features=FeatureConfig(True, False, True)),
                                      "known lighting, forest only, RGB + texton (Table 1a: +Tex)"),
    # Table 1b (the paper's setting): integrability refinements of the forest alone in known lighting
    "known_lighting_l2": _Method(True, True, _estimator(known=True, integrate="l2", forest_only=True),
                                 "known lighting, forest only + L2 integrability (Table 1b: l2)"),
    "known_lighting_l1": _Method(True, True, _estimator(known=True, integrate="l1", forest_only=True),
                                 "known lighting, forest only + L1 integrability (Table 1b: l1)"),
    "known_lighting_conv": _Method(True, True, _estimator(known=True, integrate="conv", forest_only=True),
                                   "known lighting, forest only + convex combination of leaf samples "
                                   "(Table 1b: l2, conv.)"),
    # integrability refinements of the unknown-lighting estimate
    "estimated_lighting_l2": _Method(False, True, _estimator(known=False, integrate="l2"),
                                     "estimated lighting + L2 integrability (Table 1b)"),
    "estimated_lighting_l1": _Method(False, True, _estimator(known=False, integrate="l1"),
                                     "estimated lighting + L1 integrability"),
    "estimated_lighting_conv": _Method(False, True, _estimator(known=False, integrate="conv"),
                                       "estimated lighting + convex combination of leaf samples (Table 1b)"),
}


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_method(name: str, scene: Scene, *, pipeline: Optional[PipelineConfig] = None,
               classical: Optional[RefineConfig] = None, device: Any = "cpu",
               database: Optional[GeometryDatabase] = None) -> Optional[MethodResult]:
    """Run one method of :data:`METHODS` on one case.

    Args:
        name: the method.
        scene: the case; its ``lighting`` is used by the known-lighting methods.
        pipeline: :func:`sfs_torch.estimate`'s options (default: :class:`EvalConfig`'s).
        classical: the ``classical`` method's options (default: :class:`EvalConfig`'s).
        device: where the method runs.
        database: the example-geometry database of ``pipeline.database`` on ``device``, loaded
            once for many calls (``load_database(pipeline.database).to(device)``, as
            :func:`evaluate` does); ``None``: a method that uses the forest loads it
            (:func:`~sfs_torch.geometry_db.load_database`).

    Returns:
        :class:`MethodResult` (tensors on the CPU), or ``None`` when the method needs a
        known lighting and the case has none.

    Raises:
        ValueError: an unknown method.
    """
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; methods are {', '.join(METHODS)}")
    method = METHODS[name]
    if method.needs_lighting and scene.lighting is None:
        return None
    ctx = _Context(pipeline or _eval_pipeline(), classical or _classical(), torch.device(device), database)
    _synchronize(ctx.device)
    start = time.perf_counter()
    normals, lighting, excluded = method.run(ctx, scene)
    _synchronize(ctx.device)
    seconds = max(time.perf_counter() - start - excluded, 0.0)
    normals = normals.detach().float().cpu() * scene.mask
    return MethodResult(normals, None if lighting is None else lighting.detach().float().cpu(), seconds)


# ------------------------------------------------------------------------------------------
# Scores


def score(scene: Scene, result: MethodResult) -> Dict[str, Optional[float]]:
    """The score columns of one (case, method) row; ``None`` where ground truth is missing.

    ``mae_deg`` and ``median_deg`` are the median angular error over the object's pixels
    (the paper's "MAE", SPEC "Metrics"), ``mean_deg`` the mean, ``under_*`` the shares of
    pixels under 11.25, 22.5 and 30 degrees, ``nmse`` the mean ``|n_est - n_gt|^2``
    (:func:`sfs_torch.metrics.normal_metrics`); ``lmse`` compares the method's estimated
    lighting with the case's (:func:`sfs_torch.metrics.lmse`), for methods that estimate one.
    """
    row: Dict[str, Optional[float]] = {key: None for key in SCORE_COLUMNS}
    if scene.normals is not None:
        m = normal_metrics(result.normals, scene.normals.float(), scene.mask)
        row.update(mae_deg=float(m.median[0]), median_deg=float(m.median[0]), mean_deg=float(m.mean[0]),
                   under_11_25=float(m.under_11_25[0]), under_22_5=float(m.under_22_5[0]),
                   under_30=float(m.under_30[0]), nmse=float(m.nmse[0]))
    if result.lighting is not None and scene.lighting is not None:
        row["lmse"] = float(lmse(result.lighting, scene.lighting.float())[0])
    return row


@dataclass(frozen=True)
class CaseScores:
    """What :func:`score_case` made of one case.

    Attributes:
        results: method -> :class:`MethodResult`, for the methods that ran.
        rows: the case's ``cases.csv`` rows (:data:`COLUMNS`; ``None`` for an empty cell).
    """

    results: Dict[str, MethodResult]
    rows: List[Dict[str, Any]]


def score_case(scene: Scene, methods: Sequence[str], *, pipeline: Optional[PipelineConfig] = None,
               classical: Optional[RefineConfig] = None, device: Any = "cpu",
               database: Optional[GeometryDatabase] = None) -> CaseScores:
    """Run and score ``methods`` on one case (the arguments are :func:`run_method`'s). Methods
    that need a lighting the case lacks are left out.

    Raises:
        ValueError: from a method, prefixed with the case and the method.
    """
    results: Dict[str, MethodResult] = {}
    rows = []
    for method in methods:
        try:
            result = run_method(method, scene, pipeline=pipeline, classical=classical, device=device,
                                database=database)
        except ValueError as err:
            raise ValueError(f"case {scene.name!r}, method {method}: {err}") from None
        if result is None:
            continue
        results[method] = result
        rows.append({"case": scene.name, "method": method, "shape": scene.shape, "lighting": scene.lighting_name,
                     "pixels": int(scene.mask.sum()), "focal": scene.focal, **score(scene, result),
                     "time_s": result.seconds})
    return CaseScores(results, rows)


def _number(value: str) -> Optional[float]:
    return float(value) if value not in ("", None) else None


def _median(values: List[float]) -> Optional[float]:
    return statistics.median(values) if values else None


def _mean(values: List[float]) -> Optional[float]:
    return statistics.fmean(values) if values else None


def summarise(rows: Iterable[Mapping[str, Any]], methods: Sequence[str]) -> Dict[str, Dict[str, Any]]:
    """Per method, over its rows (as read from ``cases.csv``: strings, empty for missing):

    - ``cases``: rows; ``scored``: rows with ground-truth normals; ``lighting_scored``: rows with an lMSE;
    - ``median_deg``: the median over cases of the per-case median angular error (the headline);
    - ``mean_median_deg``: the mean over cases of the per-case median;
    - ``mean_deg``, ``under_11_25``, ``under_22_5``, ``under_30``, ``nmse``, ``lmse``: means over cases;
    - ``time_s``: mean seconds per case; ``total_time_s``: their sum.

    A method without rows (e.g. ``known_lighting`` on cases without lighting) gets ``cases: 0``
    and ``None`` scores.
    """
    by_method: Dict[str, List[Mapping[str, Any]]] = {m: [] for m in methods}
    for row in rows:
        if row["method"] in by_method:
            by_method[row["method"]].append(row)
    summary = {}
    for method, mine in by_method.items():
        col = {key: [v for v in (_number(r[key]) for r in mine) if v is not None] for key in (*SCORE_COLUMNS, "time_s")}
        summary[method] = {
            "cases": len(mine),
            "scored": len(col["median_deg"]),
            "lighting_scored": len(col["lmse"]),
            "median_deg": _median(col["median_deg"]),
            "mean_median_deg": _mean(col["median_deg"]),
            "mean_deg": _mean(col["mean_deg"]),
            "under_11_25": _mean(col["under_11_25"]),
            "under_22_5": _mean(col["under_22_5"]),
            "under_30": _mean(col["under_30"]),
            "nmse": _mean(col["nmse"]),
            "lmse": _mean(col["lmse"]),
            "time_s": _mean(col["time_s"]),
            "total_time_s": sum(col["time_s"]) if col["time_s"] else None,
        }
    return summary


def _fmt(value: Optional[float], spec: str) -> str:
    return "" if value is None else format(value, spec)


def report_markdown(summary: Mapping[str, Mapping[str, Any]], *, command: str, dataset: str, cases: int,
                    figures: Optional[str] = None) -> str:
    """The Markdown report: the command, then one table row per method of :func:`summarise`."""
    lines = [
        "# sfs-torch-eval report", "",
        "```", command, "```", "",
        f"Dataset `{dataset}`: {cases} cases. Per method, over the cases it ran on: the median over cases of the "
        "per-case median angular error (the paper's MAE), the means over cases of the mean angular error, of the "
        "share of pixels under 22.5 deg, of nMSE and (for methods that estimate the lighting) of lMSE, and the mean "
        "time per case. Empty: no case had the ground truth it needs.", "",
        "| method | cases | median error (deg) | mean error (deg) | < 22.5 deg | nMSE | lMSE | time per case (s) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for method, s in summary.items():
        lines.append(
            f"| {method} | {s['cases']} | {_fmt(s['median_deg'], '.2f')} | {_fmt(s['mean_deg'], '.2f')} | "
            f"{_fmt(s['under_22_5'], '.3f')} | {_fmt(s['nmse'], '.4f')} | {_fmt(s['lmse'], '.5f')} | "
            f"{_fmt(s['time_s'], '.2f')} |"
        )
    lines += ["", "Methods:", ""]
    lines += [f"- `{method}`: {METHODS[method].description}" for method in summary if method in METHODS]
    lines += ["", "Per-case rows: `cases.csv`; numbers: `summary.json`."]
    if figures:
        lines.append(f"Error maps per case (input, then each method's angular error, its median below): `{figures}/`.")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------
# Datasets


@dataclass(frozen=True)
class Cases:
    """A dataset's cases, as :func:`load_cases` gives them.

    Attributes:
        scenes: the :class:`~sfs_torch.datasets.Scene` objects (an iterator where the loader is lazy).
        total: how many there are, ``None`` when unknown before iterating (DiLiGenT).
    """

    scenes: Iterable[Scene]
    total: Optional[int]


def _check_int(value: Any, name: str, low: int, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if not is_integer(value, low):
        raise ValueError(f"{name} must be an integer >= {low}{' or null' if allow_none else ''}, got {value!r}")


def _synthetic_cases(ds: DictConfig, pipeline: PipelineConfig) -> Cases:
    from .datasets import SCENE_SIDES, scene_lightings, scene_shapes, synthetic_scenes

    if ds.side not in SCENE_SIDES:
        raise ValueError(f"dataset.side must be one of {', '.join(SCENE_SIDES)}, got {ds.side!r}")
    if ds.degradation not in DEGRADATIONS:
        raise ValueError(f"dataset.degradation must be one of {', '.join(DEGRADATIONS)}, got {ds.degradation!r}")
    _check_int(ds.resolution, "dataset.resolution", 8)
    if ds.side == "spare" and ds.shapes is None:
        raise ValueError("dataset.shapes must be a number of shapes on the spare side (null takes a whole side "
                         "of the evaluation split; the spare pool has no fixed size)")
    _check_int(ds.shapes, "dataset.shapes", 0, allow_none=True)
    _check_int(ds.lights_per_shape, "dataset.lights_per_shape", 1, allow_none=True)
    _check_int(ds.lights, "dataset.lights", 1)
    if ds.side == "test" and ds.lights > len(EVALUATION_LIGHTINGS):
        raise ValueError(f"dataset.lights must be at most {len(EVALUATION_LIGHTINGS)} on the test side "
                         f"(the R&H probes), got {ds.lights}")
    if ds.focal is not None and not is_number(ds.focal, 0, strict=True):
        raise ValueError(f"dataset.focal must be a positive focal length in pixels or null, got {ds.focal!r}")
    if ds.root is not None:
        log.warning("dataset=synthetic renders its scenes: dataset.root=%s is ignored", ds.root)
    try:
        shapes = scene_shapes(ds.shapes, ds.side, pipeline.database, sphere=ds.sphere)
    except ValueError as error:
        raise ValueError(f"dataset.shapes: {error}") from None
    lights = scene_lightings(ds.lights, ds.side)
    per_shape = len(lights) if ds.lights_per_shape is None else ds.lights_per_shape
    focal = None if ds.focal is None else float(ds.focal)
    scenes = synthetic_scenes(shapes, lights, resolution=ds.resolution, focal=focal,
                              formation=DEGRADATIONS[ds.degradation], lights_per_shape=ds.lights_per_shape,
                              seed=ds.seed)
    return Cases(scenes, len(shapes) * per_shape)


def _root(ds: DictConfig) -> Path:
    if ds.root in (None, ""):
        raise ValueError(f"dataset={ds.name} needs dataset.root=<folder>")
    root = Path(str(ds.root))
    if not root.exists():
        raise FileNotFoundError(f"dataset.root: no such folder '{root}'")
    if not root.is_dir():
        raise ValueError(f"dataset.root must be a folder, got the file '{root}'")
    return root


def _list_or_none(value: Any) -> Optional[list]:
    if value is None:
        return None
    return list(OmegaConf.to_container(value)) if OmegaConf.is_list(value) else value


def load_cases(dataset: DictConfig, pipeline: PipelineConfig) -> Cases:
    """The cases of a ``dataset`` config (its layout checked before any image is read where the loader allows).

    Raises:
        ValueError, FileNotFoundError: an unknown dataset, a missing root, a bad option or layout.
    """
    name = dataset.get("name")
    if name not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; datasets are {', '.join(DATASETS)}")
    if name == "synthetic":
        return _synthetic_cases(dataset, pipeline)
    from .dataset_loaders import load_diligent, load_folder, load_mit_berkeley

    root = _root(dataset)
    if name == "folder":
        scenes = load_folder(root)
        return Cases(scenes, len(scenes))
    if name == "mit_berkeley":
        scenes = load_mit_berkeley(root, objects=_list_or_none(dataset.objects))
        return Cases(scenes, len(scenes))
    scenes = load_diligent(root, objects=_list_or_none(dataset.objects), lights=_list_or_none(dataset.lights),
                           perspective=bool(dataset.perspective))
    return Cases(scenes, None)


# which dataset options choose cases (not how a case looks): a resumed run may change them
_SELECTION_KEYS = {"shapes", "lights", "sphere", "lights_per_shape", "objects"}


def _fingerprint(cfg: DictConfig) -> Dict[str, Any]:
    """What a case's scores depend on (``eval_config.json``): the dataset's case-forming options,
    the pipeline and the classical method's options."""
    dataset = OmegaConf.to_container(cfg.dataset, resolve=True)
    dataset = {k: v for k, v in dataset.items() if k not in _SELECTION_KEYS}
    if dataset.get("name") != "synthetic" and dataset.get("root") is not None:
        dataset["root"] = str(Path(dataset["root"]).resolve())
    elif dataset.get("name") == "synthetic":
        dataset.pop("root", None)
    return {"dataset": dataset,
            "pipeline": asdict(resolve_config(cfg.pipeline)),
            "classical": asdict(OmegaConf.to_object(cfg.classical)) if isinstance(cfg.classical, DictConfig)
            else asdict(cfg.classical)}


# ------------------------------------------------------------------------------------------
# Files


def _csv_text(rows: Sequence[Mapping[str, Any]], header: bool) -> str:
    buffer = _io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    if header:
        writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row.get(k)) for k in COLUMNS})
    return buffer.getvalue()


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return format(value, ".6g")
    return str(value)


def read_rows(path: Path) -> List[Dict[str, str]]:
    """The rows of a ``cases.csv`` (``[]`` when missing). A last line cut short by an
    interruption is dropped from the file.

    Raises:
        ValueError: the file's columns are not :data:`COLUMNS`.
    """
    if not path.is_file():
        return []
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        keep = data.rfind(b"\n") + 1
        log.warning("%s: dropping a last row cut short by an interruption", path)
        with open(path, "r+b") as f:
            f.truncate(keep)
        data = data[:keep]
    reader = csv.DictReader(_io.StringIO(data.decode("utf-8")))
    if reader.fieldnames is None:
        return []
    if tuple(reader.fieldnames) != COLUMNS:
        raise ValueError(f"'{path}' has the columns {', '.join(reader.fieldnames)}, not {', '.join(COLUMNS)}: "
                         "it was not written by this version; pass resume=false to start over, or another out=")
    return list(reader)


def _append_rows(path: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """Append one case's rows in one write, flushed to disk before returning."""
    header = not path.is_file() or path.stat().st_size == 0
    with open(path, "a", encoding="utf-8", newline="") as f:
        f.write(_csv_text(rows, header))
        f.flush()
        os.fsync(f.fileno())


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _slug(name: str) -> str:
    """A case name as a file name, one per name: ``shape|lighting`` -> ``shape__lighting``.

    A name the file name does not spell back (``"a b"``, ``"a+b"`` and ``"a_b"`` all become
    ``a_b``) gets ``-`` and the first 8 hex digits of its SHA-1 appended, so that no two
    cases share a figure; the suffix is the same in every run, so a resumed run finds it.
    """
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", name.replace("|", "__")).strip(".") or "case"
    if slug == name.replace("|", "__") and slug.replace("__", "|") == name:
        return slug
    return f"{slug}-{hashlib.sha1(name.encode('utf-8')).hexdigest()[:8]}"


def _figure(out: Path, scene: Scene, results: Mapping[str, MethodResult], partial: bool) -> Path:
    from .figures import error_map_figure

    folder = out / "figures"
    folder.mkdir(exist_ok=True)
    stem = _slug(scene.name) + ("." + "+".join(results) if partial else "")
    path = folder / f"{stem}.png"
    tmp = folder / f".{stem}.partial.png"
    error_map_figure(tmp, scene.image[0], scene.mask[0], {m: r.normals[0] for m, r in results.items()},
                     true_normals=None if scene.normals is None else scene.normals[0], title=scene.name)
    os.replace(tmp, path)
    return path


# ------------------------------------------------------------------------------------------
# The run


def _device(name: str) -> torch.device:
    return parse_device(name)


def _methods(value: Any) -> List[str]:
    names = OmegaConf.to_container(value) if OmegaConf.is_list(value) else value
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, (list, tuple)) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"methods must be a non-empty list of {', '.join(METHODS)}, got {value!r}")
    unknown = [n for n in names if n not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}; methods are {', '.join(METHODS)}")
    return list(dict.fromkeys(names))


def _output_folder(cfg: DictConfig) -> Path:
    return output_folder(cfg, PROGRAM)


def _command(cfg: DictConfig) -> str:
    """The command line that produced this run (this job's overrides, in a sweep)."""
    if HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
        args = [shlex.quote(a) for a in hydra_cfg.overrides.task]
        if hydra_cfg.mode == RunMode.MULTIRUN:
            return " ".join([PROGRAM, *args]) + f"  # job {hydra_cfg.job.num} of a sweep (-m)"
        return " ".join([PROGRAM, *args])
    return f"# sfs_torch.evaluate.evaluate() called from Python: dataset={cfg.dataset.name} out={cfg.out}"


@dataclass(frozen=True)
class _Plan:
    out: Path
    methods: List[str]
    pipeline: PipelineConfig
    classical: RefineConfig
    device: torch.device
    fingerprint: Dict[str, Any]


def _plan(cfg: DictConfig) -> _Plan:
    """Every check that needs no dataset: run before any work."""
    methods = _methods(cfg.methods)
    if cfg.dataset is None or cfg.dataset.get("name") not in DATASETS:
        name = None if cfg.dataset is None else cfg.dataset.get("name")
        raise ValueError(f"unknown dataset {name!r}; datasets are {', '.join(DATASETS)} (dataset=<name>)")
    if cfg.dataset.name != "synthetic":
        _root(cfg.dataset)
    _check_int(cfg.limit, "limit", 1, allow_none=True)
    device = _device(cfg.device)
    try:
        pipeline = resolve_config(cfg.pipeline)  # every option checked, before any case is read
    except ValueError as err:
        message = str(err)
        raise ValueError(message if message.startswith("config ") else f"pipeline.{message}") from None
    classical = OmegaConf.to_object(cfg.classical) if isinstance(cfg.classical, DictConfig) else cfg.classical
    check_refine_config(classical, prefix="classical.")
    return _Plan(_output_folder(cfg), methods, pipeline, classical, device, _fingerprint(cfg))


def _check_resume(out: Path, fingerprint: Dict[str, Any], resume: bool) -> List[Dict[str, str]]:
    """The rows to keep from a previous run into ``out`` (none unless ``resume``)."""
    csv_path, config_path = out / "cases.csv", out / "eval_config.json"
    if not resume:
        csv_path.unlink(missing_ok=True)
        return []
    rows = read_rows(csv_path)
    if rows and config_path.is_file():
        previous = json.loads(config_path.read_text(encoding="utf-8"))
        if previous != json.loads(json.dumps(fingerprint)):
            changed = sorted(k for k in fingerprint if previous.get(k) != json.loads(json.dumps(fingerprint[k])))
            raise ValueError(
                f"out={out} holds {len(rows)} rows scored with other {' and '.join(changed)} options "
                f"({config_path}): pass resume=false to start over, or choose another out="
            )
    return rows


def _warm_up(plan: _Plan, progress: bool) -> Optional[GeometryDatabase]:
    """One-off costs no case should pay in its ``time_s``: building or reading the
    example-geometry database, and torch's import of its compiler stack the first time an
    optimiser is made (seconds, on the first L-BFGS refinement). Returns that database on
    ``plan.device``, for every case (``None`` when no method uses the forest)."""
    database = None
    if any(METHODS[m].uses_forest for m in plan.methods):
        database = load_database(plan.pipeline.database, progress=progress).to(plan.device)
    if any(m not in ("silhouette", "flat") for m in plan.methods):
        torch.optim.LBFGS([torch.zeros(1, requires_grad=True)])
    return database


@contextmanager
def _quiet(logger_name: str, quiet: bool) -> Iterator[None]:
    """Raise a logger to WARNING for the duration (the pipeline logs every stage of every call),
    and log Python warnings."""
    logger = logging.getLogger(logger_name)
    level = logger.level
    if quiet:
        logger.setLevel(logging.WARNING)
    logging.captureWarnings(True)  # the pipeline's warnings about a case, logged (and kept clear of the bar)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        logger.setLevel(level)


def evaluate(cfg: DictConfig, *, command: Optional[str] = None) -> Dict[str, Any]:
    """Run an evaluation from a composed ``eval`` config; returns what ``summary.json`` holds.

    All options are checked (methods, dataset, root, pipeline, device, a resumed ``out``)
    before the dataset is loaded or any method runs.
    """
    plan = _plan(cfg)
    out = plan.out
    out.mkdir(parents=True, exist_ok=True)
    previous = _check_resume(out, plan.fingerprint, bool(cfg.resume))
    cases = load_cases(cfg.dataset, plan.pipeline)
    _write_atomic(out / "eval_config.json", json.dumps(plan.fingerprint, indent=2) + "\n")
    done: Set[Tuple[str, str]] = {(r["case"], r["method"]) for r in previous}
    rows: List[Dict[str, Any]] = list(previous)
    database = _warm_up(plan, progress=bool(cfg.progress))
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    total = cases.total if cfg.limit is None else min(cfg.limit, cases.total or cfg.limit)
    headline = "estimated_lighting" if "estimated_lighting" in plan.methods else plan.methods[0]
    running = [float(r["median_deg"]) for r in previous if r["method"] == headline and r["median_deg"]]
    seen: List[str] = []
    bar = tqdm(total=total, unit="case", desc=PROGRAM, disable=not cfg.progress, dynamic_ncols=True)
    with _quiet("sfs_torch.pipeline", not cfg.log_stages), logging_redirect_tqdm(), bar:
        for index, scene in enumerate(cases.scenes):
            if cfg.limit is not None and index >= cfg.limit:
                break
            seen.append(scene.name)
            todo = [m for m in plan.methods if (scene.name, m) not in done]
            scores = score_case(scene, todo, pipeline=plan.pipeline, classical=plan.classical, device=plan.device,
                                database=database)
            results, new_rows = scores.results, scores.rows
            if results and cfg.figures:
                _figure(out, scene, results, partial=len(todo) < len(plan.methods))
            if new_rows:
                _append_rows(out / "cases.csv", new_rows)
                rows += new_rows
                done.update((r["case"], r["method"]) for r in new_rows)
                running += [r["median_deg"] for r in new_rows
                            if r["method"] == headline and r["median_deg"] is not None]
            if running:
                bar.set_postfix_str(f"{headline} median {statistics.median(running):.2f} deg")
            bar.update(1)
    if not seen:
        raise ValueError("the dataset holds no case")
    names = set(seen)
    current = [{k: _cell(v) for k, v in r.items()} for r in rows if r["case"] in names]
    summary_methods = summarise(current, plan.methods)
    command = command or _command(cfg)
    result = {"command": command, "dataset": plan.fingerprint["dataset"]["name"], "cases": len(seen),
              "out": str(out), "methods": summary_methods}
    _write_atomic(out / "summary.json", json.dumps(result, indent=2) + "\n")
    _write_atomic(out / "report.md", report_markdown(summary_methods, command=command, dataset=result["dataset"],
                                                     cases=len(seen), figures="figures" if cfg.figures else None))
    for method, s in summary_methods.items():
        log.info("%-24s cases %4d  median %s deg  time %s s", method, s["cases"], _fmt(s["median_deg"], "7.2f"),
                 _fmt(s["time_s"], ".2f"))
    log.info("results written to %s", out.resolve())
    return result


# ------------------------------------------------------------------------------------------
# Command line


def _user_error(err: BaseException) -> None:
    """One line on stderr (and in the run's log file), then exit code 2."""
    message = " ".join(str(err).split())
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)
    print(f"{PROGRAM}: error: {message}", file=sys.stderr)
    sys.exit(2)


@hydra.main(version_base="1.3", config_path="pkg://sfs_torch.conf", config_name="eval")
def _main(cfg: DictConfig) -> Optional[float]:
    """Returns the headline score, the objective of a sweeper (``hydra/sweeper=optuna``,
    docs/sweeps.md): the median over cases of ``estimated_lighting``'s per-case median
    error in degrees (of the first method when ``estimated_lighting`` is not run)."""
    try:
        methods = evaluate(cfg)["methods"]
    except (ValueError, FileNotFoundError, NotADirectoryError) as err:
        _user_error(err)
    return methods["estimated_lighting" if "estimated_lighting" in methods else next(iter(methods))]["median_deg"]


def _check_arguments(args: Sequence[str]) -> None:
    """Fail with one line on a bad dataset name or an unwritable ``out``, before Hydra starts."""
    for arg in args:
        key, _, value = arg.lstrip("+~").partition("=")
        if key == "dataset" and value and not any(c in value for c in "()[]{}$"):
            for name in value.split(","):
                if name.strip() not in DATASETS:
                    print(f"{PROGRAM}: error: unknown dataset {name.strip()!r}; datasets are {', '.join(DATASETS)}",
                          file=sys.stderr)
                    sys.exit(2)
        if key == "out" and value not in ("", "null") and "," not in value:
            exit_unless_writable(Path(value), f"{PROGRAM}: error: cannot write to out={value}")
        hint = moved_option_hint(arg, prefix="pipeline.")
        if hint:
            print(f"{PROGRAM}: error: {hint}", file=sys.stderr)
            sys.exit(2)


def main() -> None:
    """The ``sfs-torch-eval`` console script."""
    _check_arguments(sys.argv[1:])
    _main()


if __name__ == "__main__":
    main()
