"""Example shapes for the geometry database (paper Sec. 4): real meshes and procedural blobs.

Two kinds of shapes:

- Real meshes that ship inside two PyPI wheels (fetched once by :func:`fetch_sources`,
  never by installing the packages): dm-control's dog (body skin + bones, STL), its
  rodent walker skin (MuJoCo ``.skn``) and its fruit-fly body parts (MuJoCo ``.msh``),
  and pybullet's 1000 procedural ``random_urdfs`` (OBJ).
- Procedural smooth "blobby" star-shaped surfaces (:func:`blobby_mesh`), built from a
  seed with no dependency: the fallback collection and the data of the fast tests.

Every shape is identified by a name ``"<group>/<item>"`` and normalised the same way
(:func:`normalize_mesh`): centred on its minimal bounding sphere, scaled to radius 1,
faces wound consistently outwards, vertex normals smoothed except across sharp edges.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np
import trimesh
from tqdm import tqdm

from ._checks import is_number

__all__ = [
    "Shape",
    "ShapeSplit",
    "MeshSourceError",
    "SOURCES",
    "COLLECTIONS",
    "read_msh",
    "read_skn",
    "normalize_mesh",
    "blobby_mesh",
    "fetch_sources",
    "sources_present",
    "collection_names",
    "load_shape",
    "split_shapes",
    "drawable_count",
]

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class MeshSource:
    """One PyPI wheel that ships meshes; pinned so that the shapes never change."""

    package: str
    version: str
    license: str
    members: str  # regular expression over the wheel's member names
    pip_args: Sequence[str] = ()


# The wheels are read as zip archives, never installed. pybullet only ships binary wheels
# per platform; its data files are identical in all of them, so one fixed wheel is fetched
# whatever the local platform and Python are.
SOURCES: Dict[str, MeshSource] = {
    "dm_control": MeshSource(
        package="dm-control",
        version="1.0.50",
        license="Apache-2.0",
        members=(
            r"dm_control/suite/dog_assets/[^/]+\.stl"
            r"|dm_control/locomotion/walkers/assets/rodent_walker_skin\.skn"
            r"|dm_control/locomotion/walkers/assets/fruitfly_v2/thorax_body\.msh"
            r"|dm_control/locomotion/walkers/assets/build_fruitfly/assets/[^/]+\.msh"
            r"|dm_control/mjcf/test_assets/meshes/cube\.msh"
            r"|dm_control-1\.0\.50\.dist-info/(METADATA|licenses/(LICENSE|AUTHORS))"
        ),
    ),
    "pybullet": MeshSource(
        package="pybullet",
        version="3.2.7",
        license="zlib",
        members=r"pybullet_data/random_urdfs/\d+/\d+\.obj|pybullet-3\.2\.7\.dist-info/(METADATA|LICENSE\.txt|AUTHORS\.txt)",
        pip_args=(
            "--only-binary=:all:",
            "--platform=manylinux2014_x86_64",
            "--python-version=3.11",
            "--implementation=cp",
            "--abi=cp311",
        ),
    ),
}

_DOG = "dm_control/suite/dog_assets"
_FLY = "dm_control/locomotion/walkers/assets/build_fruitfly/assets"
_RODENT = "dm_control/locomotion/walkers/assets/rodent_walker_skin.skn"
_URDF = "pybullet_data/random_urdfs"
# Right-hand parts mirror left-hand ones: keeping both would put near-copies on both
# sides of the train/evaluation split. Fly meshes named by colour (eyes, bristles, wing
# membranes) are paint layers over a body part, or flat sheets, not solid shapes.
_RIGHT_SIDE = re.compile(r"(^|_)(R|right)(_|$|\.)")
_FLY_SOLID = re.compile(r"_(body|lower)$")

# name -> relative weight of each group when drawing a collection's shapes. "mammal"
# (dog body + bones + rodent) and "fly" are the organic majority; pybullet's random
# shapes (unions of convex pieces) add sharp edges and flat facets.
COLLECTIONS: Dict[str, Dict[str, float]] = {
    "default": {"mammal": 0.5, "fly": 0.25, "urdf": 0.25},
    "organic": {"mammal": 0.65, "fly": 0.35},
    "blobby": {"blobby": 1.0},
}
_N_BLOBBY = 10_000  # size of the (lazily generated) procedural catalogue


class MeshSourceError(RuntimeError):
    """The PyPI mesh sources are missing and could not be fetched."""


@dataclass(frozen=True)
class Shape:
    """A normalised example shape.

    Attributes:
        name: ``"<group>/<item>"``, e.g. ``"mammal/BONEFemoris_L"``, ``"blobby/0017"``.
        mesh: the mesh, centred on its bounding sphere of radius 1, with smooth vertex normals.
    """

    name: str
    mesh: trimesh.Trimesh


@dataclass(frozen=True)
class ShapeSplit:
    """Disjoint shape names for training and for evaluation."""

    train: List[str]
    evaluation: List[str]


# ----------------------------------------------------------------------------- readers
def _read_bytes(source: Union[PathLike, bytes]) -> bytes:
    return bytes(source) if isinstance(source, (bytes, bytearray)) else Path(source).read_bytes()


def read_msh(source: Union[PathLike, bytes]) -> trimesh.Trimesh:
    """Read a MuJoCo binary ``.msh`` mesh.

    Layout (little endian): ``int32 nvertex, nnormal, ntexcoord, nface``, then
    ``float32 vertex[3 nvertex], normal[3 nnormal], texcoord[2 ntexcoord]`` and
    ``int32 face[3 nface]``; nothing else. Normals and texture coordinates are dropped
    (they are recomputed by :func:`normalize_mesh`).

    Args:
        source: a path or the file's bytes.

    Returns:
        the raw (unprocessed, not normalised) triangle mesh.

    Raises:
        ValueError: the size does not match the header, or a face index is out of range.
    """
    data = _read_bytes(source)
    if len(data) < 16:
        raise ValueError(f".msh data must hold a 16-byte header, got {len(data)} bytes")
    nv, nn, nt, nf = (int(x) for x in np.frombuffer(data, "<i4", 4))
    if min(nv, nn, nt, nf) < 0 or nv == 0 or nf == 0:
        raise ValueError(f".msh header is invalid: nvertex={nv} nnormal={nn} ntexcoord={nt} nface={nf}")
    expected = 16 + 4 * (3 * nv + 3 * nn + 2 * nt + 3 * nf)
    if len(data) != expected:
        raise ValueError(f".msh size {len(data)} bytes does not match its header (expected {expected})")
    vertices = np.frombuffer(data, "<f4", 3 * nv, 16).reshape(nv, 3)
    faces = np.frombuffer(data, "<i4", 3 * nf, 16 + 4 * (3 * nv + 3 * nn + 2 * nt)).reshape(nf, 3)
    return _raw_mesh(vertices, faces, ".msh")


def read_skn(source: Union[PathLike, bytes]) -> trimesh.Trimesh:
    """Read the mesh of a MuJoCo binary ``.skn`` skin (its bind pose).

    Layout (little endian): ``int32 nvertex, ntexcoord, nface, nbone``, then
    ``float32 vertex[3 nvertex], texcoord[2 ntexcoord]``, ``int32 face[3 nface]``, then
    per bone ``char name[40], float32 bindpos[3], bindquat[4], int32 vertcount,
    int32 vertid[vertcount], float32 vertweight[vertcount]``. The bones are parsed only
    to check that the file is complete.

    Raises:
        ValueError: truncated or oversized data, or a face index out of range.
    """
    data = _read_bytes(source)
    if len(data) < 16:
        raise ValueError(f".skn data must hold a 16-byte header, got {len(data)} bytes")
    nv, nt, nf, nb = (int(x) for x in np.frombuffer(data, "<i4", 4))
    if min(nv, nt, nf, nb) < 0 or nv == 0 or nf == 0:
        raise ValueError(f".skn header is invalid: nvertex={nv} ntexcoord={nt} nface={nf} nbone={nb}")
    offset = 16 + 4 * (3 * nv + 2 * nt + 3 * nf)
    for bone in range(nb):
        if offset + 72 > len(data):
            raise ValueError(f".skn data is truncated in bone {bone} of {nb}")
        count = int(np.frombuffer(data, "<i4", 1, offset + 68)[0])
        if count < 0:
            raise ValueError(f".skn bone {bone} has a negative vertex count {count}")
        offset += 72 + 8 * count
    if offset != len(data):
        raise ValueError(f".skn size {len(data)} bytes does not match its header and bones (expected {offset})")
    vertices = np.frombuffer(data, "<f4", 3 * nv, 16).reshape(nv, 3)
    faces = np.frombuffer(data, "<i4", 3 * nf, 16 + 4 * (3 * nv + 2 * nt)).reshape(nf, 3)
    return _raw_mesh(vertices, faces, ".skn")


def _raw_mesh(vertices: np.ndarray, faces: np.ndarray, kind: str) -> trimesh.Trimesh:
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{kind} face indices must lie in [0, {len(vertices)}), got [{faces.min()}, {faces.max()}]")
    return trimesh.Trimesh(vertices.astype(np.float64), faces.astype(np.int64), process=False)


# ----------------------------------------------------------------------------- meshes
def normalize_mesh(mesh: trimesh.Trimesh, *, sharp_angle: float = 30.0) -> trimesh.Trimesh:
    """Clean a mesh and normalise it to the unit bounding sphere.

    Merges duplicate vertices (MuJoCo and STL meshes are often triangle soups), drops
    degenerate and duplicate faces, winds every body's faces consistently outwards
    (fixing inverted or mixed normals), centres the minimal bounding sphere at the
    origin and scales it to radius 1. Vertex normals are area-weighted averages of the
    face normals, except that vertices are split along edges sharper than
    ``sharp_angle`` degrees, so that faceted shapes keep flat facets.

    Args:
        mesh: any triangle mesh.
        sharp_angle: dihedral angle in degrees above which an edge stays sharp.

    Returns:
        a new mesh; ``mesh.vertex_normals`` are the shading normals.
    """
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces")
    clean = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), process=True)
    clean.update_faces(clean.nondegenerate_faces(height=1e-12))
    clean.update_faces(clean.unique_faces())
    clean.remove_unreferenced_vertices()
    if len(clean.faces) == 0:
        raise ValueError("mesh has only degenerate faces")
    trimesh.repair.fix_normals(clean, multibody=True)
    hull = clean.convex_hull.vertices if len(clean.vertices) > 4 else clean.vertices
    centre = _bounding_sphere_centre(np.asarray(hull))
    clean.apply_translation(-centre)
    clean.apply_scale(1.0 / float(np.linalg.norm(clean.vertices, axis=1).max()))
    shaded = trimesh.graph.smooth_shade(clean, angle=np.radians(sharp_angle), facet_minarea=None)
    shaded.vertex_normals  # noqa: B018 -- computed now so that later copies share them
    return shaded


def _bounding_sphere_centre(points: np.ndarray, iterations: int = 300) -> np.ndarray:
    """Centre of the minimal enclosing sphere, to within ~1/iterations of its radius.

    Badoiu-Clarkson: step towards the farthest point by 1/(k+1). trimesh's exact
    ``minimum_nsphere`` is quadratic in the hull size (seconds for a fine blob).
    """
    centre = points.mean(0)
    for k in range(iterations):
        far = points[np.argmax(((points - centre) ** 2).sum(1))]
        centre = centre + (far - centre) / (k + 2)
    return centre


def blobby_mesh(seed: int, *, subdivisions: int = 4, n_bumps: int = 8) -> trimesh.Trimesh:
    """A smooth random star-shaped surface ``r(d) = exp(sum_k a_k g_k(d))`` (normalised).

    Each ``g_k(d) = exp((d . c_k - 1) / w_k^2)`` is a Gaussian bump on the unit sphere
    around a random direction ``c_k``, of width ``w_k`` in [0.45, 1] radians and
    amplitude ``a_k`` in [-0.45, 0.7]; the exponential keeps ``r > 0``, so the surface is
    star-shaped and has no self-intersection. A random anisotropic scaling (axes in
    [0.6, 1]) adds elongated shapes. Everything comes from ``seed`` alone.

    Args:
        seed: integer seed.
        subdivisions: icosphere subdivisions (4 -> 2562 vertices, 5 -> 10242).
        n_bumps: number of bumps.

    Returns:
        the normalised mesh (see :func:`normalize_mesh`).
    """
    rng = np.random.default_rng(np.random.SeedSequence([0x5F5, int(seed)]))
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    dirs = np.asarray(sphere.vertices)
    centres = rng.normal(size=(n_bumps, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    widths = rng.uniform(0.45, 1.0, n_bumps)
    amps = rng.uniform(-0.45, 0.7, n_bumps)
    log_r = (amps * np.exp((dirs @ centres.T - 1.0) / widths**2)).sum(1)
    axes = rng.uniform(0.6, 1.0, 3)
    vertices = dirs * np.exp(log_r)[:, None] * axes
    return normalize_mesh(trimesh.Trimesh(vertices, sphere.faces, process=False), sharp_angle=180.0)


# ----------------------------------------------------------------------------- sources
def _source_dir(root: Path, key: str) -> Path:
    src = SOURCES[key]
    return root / f"{src.package}-{src.version}"


def sources_present(root: PathLike) -> bool:
    """Whether :func:`fetch_sources` completed under ``root``."""
    return all((_source_dir(Path(root), key) / "COMPLETE.json").is_file() for key in SOURCES)


def fetch_sources(root: PathLike, *, progress: bool = True) -> Path:
    """Download the pinned wheels (``pip download --no-deps``) and extract their meshes.

    Nothing is installed: each wheel is opened as a zip archive and only the mesh files
    and the licence metadata are written under ``root/<package>-<version>/``, followed by
    a ``COMPLETE.json`` marker with the wheel's SHA-256. The wheels (56 MB and 103 MB)
    are downloaded into a temporary directory and deleted afterwards.

    Raises:
        MeshSourceError: pip is missing or the download fails (e.g. no network); the
            message says how to use the procedural collection instead.
    """
    root = Path(root)
    for key, src in SOURCES.items():
        target = _source_dir(root, key)
        if (target / "COMPLETE.json").is_file():
            continue
        with tempfile.TemporaryDirectory(prefix="sfs-torch-wheel-") as tmp:
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check",
                   *src.pip_args, "-d", tmp, f"{src.package}=={src.version}"]
            log.info("fetching %s==%s (%s) with pip", src.package, src.version, src.license)
            try:
                done = subprocess.run(cmd, capture_output=True, text=True, check=False)
            except OSError as err:
                done = None
                reason = str(err)
            wheels = sorted(Path(tmp).glob("*.whl"))
            if done is None or done.returncode != 0 or not wheels:
                reason = reason if done is None else (done.stderr.strip().splitlines() or ["no wheel"])[-1]
                raise MeshSourceError(
                    f"could not download the example meshes ({src.package}=={src.version} from PyPI: {reason}). "
                    "Connect to the network and run `sfs-torch-data`, or use the procedural shapes, which need "
                    "no download: set `database.collection=blobby` (Python: DatabaseConfig(collection='blobby'))."
                )
            _extract(wheels[0], target, re.compile(src.members), progress=progress)
    return root


def _extract(wheel: Path, target: Path, members: "re.Pattern[str]", *, progress: bool) -> None:
    digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
    target.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(wheel) as archive:
        names = [n for n in archive.namelist() if members.fullmatch(n)]
        for name in tqdm(names, desc=f"extract {wheel.name.split('-')[0]}", disable=not progress, leave=False):
            out = target / name
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(archive.read(name))
    (target / "COMPLETE.json").write_text(json.dumps({"wheel": wheel.name, "sha256": digest, "files": len(names)}))


# ----------------------------------------------------------------------------- catalogue
def _group_names(group: str, root: Optional[Path]) -> List[str]:
    if group == "blobby":
        return [f"blobby/{i:04d}" for i in range(_N_BLOBBY)]
    if root is None or not sources_present(root):
        raise MeshSourceError(f"the mesh sources for group {group!r} are not present under {root}")
    dm = _source_dir(root, "dm_control")
    if group == "mammal":
        dog = sorted(p.stem for p in (dm / _DOG).glob("*.stl") if not _RIGHT_SIDE.search(p.stem))
        return [f"mammal/{n}" for n in dog] + ["mammal/rodent"]
    if group == "fly":
        parts = sorted(p.stem for p in (dm / _FLY).glob("*.msh"))
        return [f"fly/{n}" for n in parts if _FLY_SOLID.search(n) and not _RIGHT_SIDE.search(n)]
    if group == "urdf":
        pb = _source_dir(root, "pybullet")
        return sorted(f"urdf/{p.stem}" for p in (pb / _URDF).glob("*/*.obj"))
    raise ValueError(f"unknown shape group {group!r}")


def collection_names(collection: str, root: Optional[PathLike] = None) -> Dict[str, List[str]]:
    """All shape names of a collection, per group.

    Args:
        collection: a key of :data:`COLLECTIONS` (``"default"``, ``"organic"``, ``"blobby"``).
        root: the directory given to :func:`fetch_sources` (unused for ``"blobby"``).

    Raises:
        ValueError: unknown collection.
        MeshSourceError: the collection needs meshes that are not under ``root``.
    """
    if collection not in COLLECTIONS:
        raise ValueError(f"collection must be one of {sorted(COLLECTIONS)}, got {collection!r}")
    root = None if root is None else Path(root)
    return {group: _group_names(group, root) for group in COLLECTIONS[collection]}


def load_shape(name: str, root: Optional[PathLike] = None) -> Shape:
    """Load and normalise one shape by name (see :func:`collection_names`)."""
    group, _, item = name.partition("/")
    if group == "blobby":
        if not (item.isascii() and item.isdigit()):
            raise ValueError(f"unknown shape name {name!r}: a blobby shape is 'blobby/<seed>', the seed a "
                             f"non-negative integer")
        return Shape(name, blobby_mesh(int(item)))
    if root is None:
        raise MeshSourceError(f"shape {name!r} needs the mesh sources: pass their root directory")
    root = Path(root)
    dm = _source_dir(root, "dm_control")
    if group == "mammal" and item == "rodent":
        raw = read_skn(dm / _RODENT)
    elif group == "mammal":
        raw = trimesh.load(dm / _DOG / f"{item}.stl", force="mesh", process=False)
    elif group == "fly":
        raw = read_msh(dm / _FLY / f"{item}.msh")
    elif group == "urdf":
        raw = trimesh.load(_source_dir(root, "pybullet") / _URDF / item / f"{item}.obj", force="mesh", process=False)
    else:
        raise ValueError(f"unknown shape name {name!r}")
    return Shape(name, normalize_mesh(raw))


def drawable_count(groups: Dict[str, List[str]], weights: Dict[str, float]) -> int:
    """How many shapes :func:`split_shapes` can draw from ``groups``: those of positive weight."""
    return sum(len(names) for group, names in groups.items() if weights[group] > 0)


def split_shapes(groups: Dict[str, List[str]], weights: Dict[str, float], n_train: int, n_eval: int,
                 seed: int) -> ShapeSplit:
    """Draw disjoint training and evaluation shapes, whole shapes only.

    Each group's names are shuffled by ``seed``; the evaluation shapes are drawn first
    (so they do not depend on ``n_train``), then the training shapes from the rest.
    Both sets follow the group ``weights`` (largest remainder; a group that runs out
    passes its share on to the others). A group of weight 0 gives no shapes.

    Raises:
        ValueError: a group has no weight, a weight is negative or not finite, all are 0,
            or fewer shapes of positive weight are available than ``n_train + n_eval``.
    """
    missing = sorted(set(groups) - set(weights))
    if missing:
        raise ValueError(f"weights must give every group a weight, missing {missing}")
    bad = {g: w for g, w in weights.items() if not is_number(w, 0.0)}
    if bad:
        raise ValueError(f"weights must be finite numbers >= 0, got {bad}")
    if not any(weights[g] > 0 for g in groups):
        raise ValueError(f"weights must be positive for some group, got {weights}")
    total = drawable_count(groups, weights)
    if n_train < 1 or n_eval < 0 or n_train + n_eval > total:
        raise ValueError(f"n_shapes + n_eval_shapes must be in [1, {total}], got {n_train} + {n_eval}")
    rng = np.random.default_rng(np.random.SeedSequence([0x5917, int(seed)]))
    queues = {g: [names[i] for i in rng.permutation(len(names))] for g, names in sorted(groups.items())}
    evaluation = _draw(queues, weights, n_eval)
    train = _draw(queues, weights, n_train)
    return ShapeSplit(train=train, evaluation=evaluation)


def _draw(queues: Dict[str, List[str]], weights: Dict[str, float], n: int) -> List[str]:
    counts = {g: 0 for g in queues}
    remaining = n
    while remaining > 0:
        # Zero-weight groups stay out: with them alone open, the shares would be 0/0
        open_groups = [g for g in queues if weights[g] > 0 and len(queues[g]) > counts[g]]
        w = np.array([weights[g] for g in open_groups], np.float64)
        share = remaining * w / w.sum()
        take = np.floor(share).astype(int)
        for k in np.argsort(-(share - take), kind="stable")[: remaining - int(take.sum())]:
            take[k] += 1
        for g, t in zip(open_groups, take):
            t = min(int(t), len(queues[g]) - counts[g])
            counts[g] += t
            remaining -= t
    drawn = []
    for g in queues:
        drawn += queues[g][: counts[g]]
        del queues[g][: counts[g]]
    return drawn
