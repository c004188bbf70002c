"""The ``sfs-torch`` command (a Hydra app).

``sfs-torch`` alone runs the built-in demo end to end: an evaluation shape (never
used for training) rendered under a natural lighting, estimated in unknown
illumination, with outputs and a summary figure. ``sfs-torch image=... mask=...``
runs on the user's files. Overrides are Hydra's ``key=value``.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

# Idle OpenMP threads spin by default; on a small shared CPU that made the forest's many
# short parallel loops 20-50x slower (docs/forest.md). The command owns its process, so it
# chooses a passive policy (unless the user chose one) before torch starts its threads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.core.config_store import ConfigStore  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from . import io  # noqa: E402
from .figures import confidence_display_max, summary_figure  # noqa: E402
from .geometry_db import evaluation_shapes  # noqa: E402
from .integrability import depth_to_mesh  # noqa: E402
from .lighting import natural_lightings, render_sh, render_sphere  # noqa: E402
from .metrics import lmse, normal_metrics  # noqa: E402
from .novel_view import render_novel_view  # noqa: E402
from .pipeline import Estimate, PipelineConfig, estimate  # noqa: E402
from .rendering import random_view_rotations, render_normals  # noqa: E402
from .silhouette import coarse_normals  # noqa: E402

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
    device: str = "cpu"
    # mesh files written when there is a depth map: any of io.MESH_FORMATS ("ply", "obj",
    # "glb"); [] for none. Typed Any so that a bad value reaches _mesh_formats' one-line error.
    mesh_formats: Any = field(default_factory=lambda: ["ply"])
    demo: DemoConfig = field(default_factory=DemoConfig)


ConfigStore.instance().store(name="sfs_torch_schema", node=AppConfig)
# hydra.run.dir is `out` when given, else a dated folder (oc.select keeps a null value).
OmegaConf.register_new_resolver("sfs_torch_or", lambda value, default: default if value is None else value, replace=True)


def _pipeline_config(cfg: DictConfig) -> DictConfig:
    keep = set(PipelineConfig.__dataclass_fields__)
    return OmegaConf.create({k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k in keep})


def _demo_inputs(cfg: DictConfig, device: torch.device) -> Dict[str, Any]:
    """Render the demo scene: an evaluation shape under a natural lighting."""
    shapes = evaluation_shapes(OmegaConf.to_object(cfg.database))
    if not 0 <= cfg.demo.shape < len(shapes):
        raise ValueError(f"demo.shape must be in [0, {len(shapes) - 1}], got {cfg.demo.shape}")
    lights = natural_lightings(cfg.demo.albedo)
    if cfg.demo.lighting not in lights:
        raise ValueError(f"demo.lighting must be one of {sorted(lights)}, got {cfg.demo.lighting!r}")
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


def _write_outputs(out: Path, est: Estimate, camera: DictConfig, mesh_formats: Tuple[str, ...]) -> None:
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
        io.write_image(out / "novel_view.png", render_novel_view(mesh, est.lighting.cpu()))


def _depth_description(decode: Dict[str, float], camera: DictConfig) -> Dict[str, Any]:
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
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {name!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device={name} but torch {torch.__version__} sees no CUDA device here; run with device=cpu, or "
            "install a CUDA build of torch (README)"
        )
    return device


def _output_folder(cfg: DictConfig) -> Path:
    """``out``; in a sweep (``-m``) or without ``out``, the job's Hydra output folder.

    In a sweep every job gets its own subfolder (``hydra.sweep.dir/hydra.sweep.subdir``, the
    sweep folder being ``out`` when given), so that parallel jobs never write into one folder.
    """
    if HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
        if not cfg.out or hydra_cfg.mode == RunMode.MULTIRUN:
            return Path(hydra_cfg.runtime.output_dir)
    if not cfg.out:
        raise ValueError("out must be given when the config was not composed by the sfs-torch command")
    return Path(cfg.out)


def run(cfg: DictConfig) -> Dict[str, float]:
    """Run the app on a composed config; returns the key numbers (also written as JSON)."""
    device = _device(cfg.device)
    mesh_formats = _mesh_formats(cfg.mesh_formats)
    out = _output_folder(cfg)
    pipeline_cfg = _pipeline_config(cfg)
    if cfg.image is None:
        if cfg.mask is not None:
            raise ValueError("mask was given without image: pass image=PATH too (or neither for the demo)")
        demo = _demo_inputs(cfg, device)
        image, mask, known = demo["image"], demo["mask"], None
        log.info("demo: evaluation shape %r under %s", demo["name"], cfg.demo.lighting)
    else:
        loaded = io.read_image_and_mask(cfg.image, cfg.mask, srgb=cfg.image_srgb)
        image, mask = loaded.image.to(device), loaded.mask.to(device)
        known = io.read_lighting(cfg.lighting) if cfg.lighting else None
        demo = None
    est = estimate(image, mask, lighting=known, config=pipeline_cfg)
    # every file is written under a hidden staging folder first and renamed into place
    # when all are complete: a killed run leaves no half-written file under a final name
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".sfs-torch-partial-", dir=out))
    try:
        _write_outputs(staging, est, cfg.camera, mesh_formats)
        numbers = _finish(cfg, staging, est, image, mask, demo)
        _publish(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for key, value in numbers.items():
        log.info("%-32s %.4g", key, value)
    log.info("outputs written to %s", out.resolve())
    return numbers


def _finish(cfg: DictConfig, out: Path, est: Estimate, image, mask, demo) -> Dict[str, float]:
    """Write the key numbers (``metrics.json``) and the summary figure; return the numbers."""
    numbers: Dict[str, float] = {}
    for stage, seconds in est.timings.items():
        numbers[f"time {stage} (s)"] = seconds
    title = f"sfs-torch: {cfg.image or 'demo ' + demo['name']}"
    if demo is not None:
        metrics = normal_metrics(est.normals[None].cpu(), demo["normals"][None], mask[None].cpu())
        baseline = normal_metrics(coarse_normals(mask[None].cpu()), demo["normals"][None], mask[None].cpu())
        numbers = {
            "median error (deg)": float(metrics.median[0]),
            "mean error (deg)": float(metrics.mean[0]),
            "< 22.5 deg": float(metrics.under_22_5[0]),
            "silhouette-only median (deg)": float(baseline.median[0]),
            "lighting lMSE": float(lmse(est.lighting[None].cpu(), demo["lighting"][None])[0]),
            **numbers,
        }
    summary_numbers = {k: v for k, v in numbers.items() if not k.startswith("time ")}
    summary_numbers["time per call (s)"] = sum(t for stage, t in est.timings.items() if stage != "database")
    summary_figure(
        out / "summary.png", image.cpu(), mask.cpu(), est.normals.cpu(), est.lighting.cpu(),
        true_normals=None if demo is None else demo["normals"], true_lighting=None if demo is None else demo["lighting"],
        confidence=est.confidence.cpu(), depth=None if est.depth is None else est.depth.cpu(),
        numbers=summary_numbers, title=title,
    )
    (out / "metrics.json").write_text(json.dumps(numbers, indent=2))
    return numbers


@hydra.main(version_base="1.3", config_path="pkg://sfs_torch.conf", config_name="config")
def _main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except (ValueError, FileNotFoundError) as err:
        # A user error gets one clear line, not a stack trace.
        log.error("%s", err)
        sys.exit(2)


def _check_out_argument(args: list) -> None:
    """Fail with one line when ``out=`` cannot be written, before Hydra sets up its log file there."""
    for arg in args:
        if not arg.startswith("out=") or arg[4:] in ("", "null"):
            continue
        path = Path(arg[4:])
        try:
            path.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=path):
                pass
        except OSError as err:
            print(f"sfs-torch: cannot write to out={path}: {err.strerror or err}", file=sys.stderr)
            sys.exit(2)


def main() -> None:
    _check_out_argument(sys.argv[1:])
    _main()
