"""The example-geometry database: lighting-independent training patches (paper Sec. 4, 5).

Built once per configuration and cached: ``n_shapes`` training shapes
(:mod:`sfs_torch.shapes`), each rendered (:mod:`sfs_torch.rendering`, orthographic) from
``n_views`` uniformly random viewpoints; in each view ``samples_per_view`` object pixels
are drawn uniformly, and their ``P x P`` normal patch, patch mask and the silhouette
features ``[d_rel, cos beta, sin beta]`` of the centre pixel (computed on the FULL view
mask) are kept. For every new lighting the pipeline only shades these patches.

Cache: ``cache_dir() / "geometry" / "db-<key>.safetensors"`` plus a JSON sidecar holding
the format version, the configuration, the shape names and the file's SHA-256; the key
hashes the configuration, the format version and the silhouette settings. A file that is
unreadable, fails its checksum or describes another configuration is logged and rebuilt.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple, Union

import platformdirs
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import Tensor
from tqdm import tqdm

from ._checks import is_integer, is_number
from .rendering import random_view_rotations, render_normals
from .shapes import (
    COLLECTIONS,
    SOURCES,
    Shape,
    ShapeSplit,
    collection_names,
    fetch_sources,
    load_shape,
    sources_present,
    split_shapes,
)
from .silhouette import SilhouetteConfig, silhouette_features

__all__ = [
    "DatabaseConfig",
    "GeometryDatabase",
    "build_database",
    "load_database",
    "evaluation_shapes",
    "database_split",
    "cache_dir",
    "mesh_dir",
    "main",
]

log = logging.getLogger(__name__)

# Bump whenever the content of a database built from the same config changes.
FORMAT_VERSION = 1
_FIELDS = ("normals", "masks", "silhouette", "shape_id", "view_id")


@dataclass
class DatabaseConfig:
    """What goes into the example-geometry database.

    Attributes:
        collection: ``"default"`` (the dm-control and pybullet meshes fetched from PyPI),
            ``"organic"`` (dm-control only) or ``"blobby"`` (procedural, no download).
        n_shapes: training shapes.
        n_views: random orthographic viewpoints per shape.
        resolution: rendered view size in pixels. 128 puts the object at ~115 px across,
            the size of the paper's test objects (MIT intrinsics crops at ~1/2 scale) and
            of the demos, so the 5x5 patches see a similar curvature per pixel; a
            view renders in ~10 ms.
        samples_per_view: object pixels drawn per view (all of them when fewer).
        patch_size: odd side ``P`` of the normal patches.
        n_eval_shapes: held-out shapes for demos and benchmarks; never in training.
        seed: drives the split, the viewpoints and the pixel samples.
        scale: radius of the unit bounding sphere in the view, as a fraction of half the
            resolution (the margin keeps the silhouette off the image border).
    """

    collection: str = "default"
    n_shapes: int = 100
    n_views: int = 10
    resolution: int = 128
    samples_per_view: int = 150
    patch_size: int = 5
    n_eval_shapes: int = 20
    seed: int = 0
    scale: float = 0.9


@dataclass(frozen=True)
class GeometryDatabase:
    """Lighting-independent training samples; ``N`` patches in all.

    Attributes:
        normals: :math:`(N, 3, P, P)` float32 camera-frame normal patches, 0 outside the object.
        masks: :math:`(N, 1, P, P)` bool object pixels of each patch.
        silhouette: :math:`(N, 3)` float32 ``[d_rel, cos beta, sin beta]`` of each centre pixel.
        shape_id: :math:`(N,)` int64 index into ``shape_names``.
        view_id: :math:`(N,)` int64 view index within its shape.
        shape_names: the training shapes' names.
    """

    normals: Tensor
    masks: Tensor
    silhouette: Tensor
    shape_id: Tensor
    view_id: Tensor
    shape_names: Tuple[str, ...] = field(default=())

    def to(self, device: Union[str, torch.device]) -> "GeometryDatabase":
        """The database with its tensors on ``device``; ``self`` when they are there already."""
        device = torch.device(device)
        tensors = {f.name: getattr(self, f.name) for f in fields(self) if isinstance(getattr(self, f.name), Tensor)}
        if all(t.device == device for t in tensors.values()):
            return self
        return replace(self, **{name: t.to(device) for name, t in tensors.items()})


def cache_dir() -> Path:
    """``$SFS_TORCH_CACHE`` when set, else the user cache directory of ``sfs-torch``."""
    env = os.environ.get("SFS_TORCH_CACHE")
    return Path(env) if env else Path(platformdirs.user_cache_dir("sfs-torch"))


def mesh_dir() -> Path:
    """Where :func:`sfs_torch.shapes.fetch_sources` puts the PyPI meshes."""
    return cache_dir() / "meshes"


def _check_config(cfg: DatabaseConfig) -> None:
    if cfg.collection not in COLLECTIONS:
        raise ValueError(f"collection must be one of {sorted(COLLECTIONS)}, got {cfg.collection!r}")
    for name in ("n_shapes", "n_views", "samples_per_view"):
        if not is_integer(getattr(cfg, name), 1):
            raise ValueError(f"{name} must be a positive integer, got {getattr(cfg, name)!r}")
    for name in ("n_eval_shapes", "seed"):
        if not is_integer(getattr(cfg, name), 0):
            raise ValueError(f"{name} must be a non-negative integer, got {getattr(cfg, name)!r}")
    if not (is_integer(cfg.patch_size, 1) and cfg.patch_size % 2 == 1):
        raise ValueError(f"patch_size must be a positive odd integer, got {cfg.patch_size!r}")
    if not is_integer(cfg.resolution, 8):
        raise ValueError(f"resolution must be an integer >= 8, got {cfg.resolution!r}")
    if not (is_number(cfg.scale) and 0 < cfg.scale < 1):
        raise ValueError(f"scale must be a number in (0, 1) so that the silhouette stays inside the image, "
                         f"got {cfg.scale!r}")


def _mesh_root(collection: str, progress: bool = False) -> Optional[Path]:
    """The mesh sources' directory, fetched first when the collection needs them."""
    if collection not in COLLECTIONS or collection == "blobby":
        return None
    root = mesh_dir()
    if not sources_present(root):
        log.info("example meshes missing under %s: fetching them from PyPI (one time)", root)
        fetch_sources(root, progress=progress)
    return root


def database_split(cfg: DatabaseConfig) -> ShapeSplit:
    """The training and evaluation shape names of ``cfg`` (disjoint; fetches meshes if needed)."""
    _check_config(cfg)
    groups = collection_names(cfg.collection, _mesh_root(cfg.collection))
    return split_shapes(groups, COLLECTIONS[cfg.collection], cfg.n_shapes, cfg.n_eval_shapes, cfg.seed)


def evaluation_shapes(cfg: DatabaseConfig) -> List[Shape]:
    """The held-out shapes (name + normalised trimesh) for demos and benchmarks."""
    split = database_split(cfg)
    root = _mesh_root(cfg.collection)
    return [load_shape(name, root) for name in split.evaluation]


def _sample_view_patches(
    normals: Tensor, masks: Tensor, samples: int, patch: int, generator: torch.Generator
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Draw object pixels of each view with their patches and silhouette features.

    ``(V, 3, H, W)`` normals and ``(V, 1, H, W)`` masks -> ``(n, 3, P, P)`` patches,
    ``(n, 1, P, P)`` patch masks, ``(n, 3)`` silhouette features, ``(n,)`` view index.
    """
    v, _, h, w = normals.shape
    sil = silhouette_features(masks)
    # Uniform sampling without replacement: the `samples` object pixels of highest
    # uniform random score; views with fewer object pixels keep them all.
    score = torch.rand(v, h * w, generator=generator).masked_fill(~masks.flatten(1), -1.0)
    top = score.topk(min(samples, h * w), dim=1)
    view_idx = torch.arange(v)[:, None].expand_as(top.indices)[top.values >= 0]
    pix_idx = top.indices[top.values >= 0]
    pad = patch // 2
    padded = F.pad(torch.cat([normals, masks.to(normals.dtype)], 1), (pad,) * 4)  # (V, 4, H + 2p, W + 2p)
    offsets = torch.arange(patch)
    rows = (pix_idx // w)[:, None] + offsets  # padded row of each patch row, (n, P)
    cols = (pix_idx % w)[:, None] + offsets
    cols = padded[view_idx[:, None, None], :, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)  # (n, 4, P, P)
    centre = sil.flatten(2).permute(0, 2, 1)[view_idx, pix_idx]
    return cols[:, :3].contiguous(), cols[:, 3:] > 0.5, centre.float(), view_idx


def build_database(cfg: DatabaseConfig, *, progress: bool = True) -> GeometryDatabase:
    """Render the training shapes and sample their patches (no cache; see :func:`load_database`).

    Deterministic given ``cfg`` (the seed drives split, viewpoints and samples).

    Raises:
        ValueError: an invalid configuration.
        sfs_torch.shapes.MeshSourceError: the PyPI meshes are needed but cannot be fetched.
    """
    _check_config(cfg)
    root = _mesh_root(cfg.collection, progress)
    split = database_split(cfg)
    generator = torch.Generator().manual_seed(cfg.seed)
    parts = {k: [] for k in _FIELDS}
    for shape_id, name in enumerate(tqdm(split.train, desc="geometry database", unit="shape", disable=not progress)):
        mesh = load_shape(name, root).mesh
        views = [render_normals(mesh, rot, cfg.resolution, scale=cfg.scale)
                 for rot in random_view_rotations(cfg.n_views, generator)]
        normals = torch.stack([view.normals for view in views])
        masks = torch.stack([view.mask for view in views])
        patches, patch_masks, sil, view_id = _sample_view_patches(
            normals, masks, cfg.samples_per_view, cfg.patch_size, generator
        )
        parts["normals"].append(patches)
        parts["masks"].append(patch_masks)
        parts["silhouette"].append(sil)
        parts["shape_id"].append(torch.full_like(view_id, shape_id))
        parts["view_id"].append(view_id)
    return GeometryDatabase(**{k: torch.cat(v) for k, v in parts.items()}, shape_names=tuple(split.train))


def _cache_key(cfg: DatabaseConfig) -> str:
    payload = {
        "format": FORMAT_VERSION,
        "config": asdict(cfg),
        "silhouette": asdict(SilhouetteConfig()),
        "sources": {k: f"{s.package}=={s.version}" for k, s in SOURCES.items()},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:20]


def _cache_paths(cfg: DatabaseConfig) -> Tuple[Path, Path]:
    base = cache_dir() / "geometry" / f"db-{_cache_key(cfg)}"
    return base.with_suffix(".safetensors"), base.with_suffix(".json")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def _save(db: GeometryDatabase, cfg: DatabaseConfig) -> None:
    data_path, meta_path = _cache_paths(cfg)
    data_path.parent.mkdir(parents=True, exist_ok=True)
    tmp_data, tmp_meta = (p.with_name(f"{p.name}.tmp{os.getpid()}") for p in (data_path, meta_path))
    save_file({k: getattr(db, k).contiguous() for k in _FIELDS}, str(tmp_data))
    meta = {
        "format": FORMAT_VERSION,
        "config": asdict(cfg),
        "key": _cache_key(cfg),
        "sha256": _sha256(tmp_data),
        "shape_names": list(db.shape_names),
        "n_samples": int(db.normals.shape[0]),
    }
    tmp_meta.write_text(json.dumps(meta, indent=1))
    # Data first: a crash in between leaves a checksum mismatch, never a wrong pairing.
    os.replace(tmp_data, data_path)
    os.replace(tmp_meta, meta_path)


def _load(cfg: DatabaseConfig) -> GeometryDatabase:
    """Read and verify the cached database; raise ``ValueError``/``OSError`` when unusable."""
    data_path, meta_path = _cache_paths(cfg)
    meta = json.loads(meta_path.read_text())
    if meta.get("format") != FORMAT_VERSION or meta.get("config") != asdict(cfg):
        raise ValueError(f"stale metadata (format {meta.get('format')}, config {meta.get('config')})")
    if _sha256(data_path) != meta.get("sha256"):
        raise ValueError("checksum mismatch")
    tensors = load_file(str(data_path))
    n = meta["n_samples"]
    p = cfg.patch_size
    expected = {
        "normals": ((n, 3, p, p), torch.float32), "masks": ((n, 1, p, p), torch.bool),
        "silhouette": ((n, 3), torch.float32), "shape_id": ((n,), torch.int64), "view_id": ((n,), torch.int64),
    }
    for name, (shape, dtype) in expected.items():
        t = tensors.get(name)
        if t is None or tuple(t.shape) != shape or t.dtype != dtype:
            raise ValueError(f"field {name} missing or malformed")
    return GeometryDatabase(**{k: tensors[k] for k in _FIELDS}, shape_names=tuple(meta["shape_names"]))


def load_database(cfg: DatabaseConfig, *, progress: bool = True) -> GeometryDatabase:
    """The cached database for ``cfg``, built (and cached) first when missing or unusable.

    Cache: ``cache_dir() / "geometry"``, keyed by a hash of ``cfg``, the format version
    and the silhouette settings. A corrupt (checksum), stale (other format/config) or
    unreadable file is logged as a warning and rebuilt, never used.
    """
    _check_config(cfg)
    data_path, _ = _cache_paths(cfg)
    db = _cached(cfg)
    if db is not None:
        return db
    # Concurrent first runs share one build: the first holds the lock and builds, the
    # others wait for it and then load what it wrote.
    with _build_lock(data_path.with_suffix(".lock")):
        db = _cached(cfg)
        if db is not None:
            return db
        start = time.perf_counter()
        db = build_database(cfg, progress=progress)
        _save(db, cfg)
    log.info("built the geometry database (%d samples) in %.1f s: %s", db.normals.shape[0],
             time.perf_counter() - start, data_path)
    return db


def _cached(cfg: DatabaseConfig) -> Optional[GeometryDatabase]:
    """The verified cached database, or ``None`` when missing or unusable (logged)."""
    data_path, meta_path = _cache_paths(cfg)
    if not (data_path.exists() and meta_path.exists()):
        return None
    try:
        return _load(cfg)
    except Exception as err:  # anything wrong with the file means: rebuild it
        log.warning("cached geometry database %s is unusable (%s): rebuilding it", data_path, err)
        return None


@contextmanager
def _build_lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock on ``path`` (POSIX ``flock``; elsewhere no lock)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # Windows: concurrent first runs may build twice, each safely
        yield
        return
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def main(argv: Optional[Sequence[str]] = None) -> None:
    """``sfs-torch-data``: fetch the PyPI meshes and build the default database."""
    parser = argparse.ArgumentParser(prog="sfs-torch-data", description=main.__doc__)
    defaults = DatabaseConfig()
    for f in fields(DatabaseConfig):
        parser.add_argument(f"--{f.name.replace('_', '-')}", type=type(getattr(defaults, f.name)),
                            default=getattr(defaults, f.name), help=f"(default: {getattr(defaults, f.name)})")
    parser.add_argument("--fetch-only", action="store_true", help="only download and extract the meshes")
    args = parser.parse_args(argv)
    cfg = DatabaseConfig(**{f.name: getattr(args, f.name) for f in fields(DatabaseConfig)})
    try:  # before the meshes are fetched
        _check_config(cfg)
    except ValueError as error:
        parser.error(str(error))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.collection != "blobby":
        start = time.perf_counter()
        fetch_sources(mesh_dir())
        log.info("mesh sources ready in %s (%.1f s)", mesh_dir(), time.perf_counter() - start)
    if args.fetch_only:
        return
    db = load_database(cfg, progress=True)
    log.info("geometry database: %d samples from %d shapes in %s", db.normals.shape[0], len(db.shape_names),
             _cache_paths(cfg)[0])
