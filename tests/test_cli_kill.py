"""``sfs-torch`` killed (SIGKILL) at any moment leaves no partial file under a final name.

One full run is timed first; the command is then started again and killed at several
fractions of that duration, and at moments inside its writing phase (found by the hidden
staging folder appearing). After every kill each file in the output folder is decoded;
only the hidden ``.sfs-torch-partial-*`` folders may hold incomplete files.
"""
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from omegaconf import OmegaConf

from sfs_torch import io

from test_cli import write_sphere

# smaller than test_cli.TINY: the database is built in a few seconds; accuracy is not the point
ARGS = [
    "database=blobby",
    "database.n_shapes=4",
    "database.n_views=2",
    "database.resolution=64",
    "database.n_eval_shapes=1",
    "forest.n_trees=4",
    "forest.max_depth=10",
    "image=obj.png",
    "mask=obj_mask.png",
    "integrate=l2",  # every optional output too: depth, meshes, novel view
    "mesh_formats=[ply,obj,glb]",
]
STAGING = ".sfs-torch-partial-*"
PNG_END = b"IEND\xaeB`\x82"


def start(cwd: Path, out: Path) -> subprocess.Popen:
    with open(cwd / "cli-output.txt", "ab") as log:  # the child keeps its own copy of the handle
        return subprocess.Popen([sys.executable, "-c", "from sfs_torch.cli import main; main()", *ARGS, f"out={out}"],
                                cwd=cwd, stdout=log, stderr=subprocess.STDOUT)


def staging_folders(out: Path) -> set:
    return set(out.glob(STAGING)) if out.is_dir() else set()


def decode_outputs(out: Path, mask: np.ndarray) -> list:
    """Decode every file under ``out`` except the hidden staging folders; return their names.

    Fails on a file that does not decode completely, or one the test does not know.
    """
    decoded = []
    for path in sorted(p for p in out.rglob("*") if p.is_file()):
        relative = path.relative_to(out)
        if relative.parts[0].startswith(".sfs-torch-partial-"):
            continue  # the only place where incomplete files may be
        name = relative.as_posix()
        if path.suffix == ".png":
            assert path.read_bytes().endswith(PNG_END), f"{name}: truncated PNG"
            if name == "normals.png":
                values = io.read_normals_png(path)
            elif name == "depth.png":
                decode = json.loads((out / "depth.json").read_text()) if (out / "depth.json").exists() else None
                values = io.read_depth_png(path, **({k: decode[k] for k in ("scale", "offset")} if decode else
                                                    {"scale": 1.0, "offset": 0.0})).depth
            else:
                values = io.read_image(path, srgb=False)
            assert bool(torch.isfinite(values).all()), name
        elif name == "normals.npy":
            normals = io.read_normals_npy(path)
            assert normals.shape == (3, *mask.shape), name
            assert np.allclose(np.linalg.norm(normals.numpy()[:, mask], axis=0), 1, atol=1e-5), name
        elif path.suffix == ".npy":
            assert np.load(path, allow_pickle=False).shape == mask.shape, name
        elif name == "lighting.json":
            assert io.read_lighting(path).shape == (3, 9)
        elif path.suffix == ".json":
            assert isinstance(json.loads(path.read_text()), dict), name
        elif path.suffix in (".ply", ".obj", ".glb"):
            loaded = trimesh.load(path, process=False, maintain_order=True)
            mesh = next(iter(loaded.geometry.values())) if isinstance(loaded, trimesh.Scene) else loaded
            assert len(mesh.vertices) == int(mask.sum()) and len(mesh.faces) > 0, name
        elif path.suffix == ".yaml":  # Hydra's record of the run, written before it starts
            OmegaConf.load(path)
        elif path.suffix == ".log":  # Hydra's log: appended line by line, any prefix is whole text
            path.read_text(encoding="utf-8")
        else:
            pytest.fail(f"an output this test cannot decode: {name}")
        decoded.append(name)
    return decoded


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_sigkill_at_any_moment_leaves_only_whole_files(tmp_path):
    from hydra import compose, initialize_config_module

    import sfs_torch.cli as cli

    mask = write_sphere(tmp_path)[0].numpy()
    out = tmp_path / "result"
    # a first run in this process builds the database, so that the timed runs only start up,
    # estimate and write
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        overrides = [a.replace("=obj", f"={tmp_path}/obj") for a in ARGS]
        cli.run(compose(config_name="config", overrides=[*overrides, f"out={tmp_path / 'warm'}"]))

    # the timed run: its duration, and its writing phase (while the staging folder exists)
    began, proc, writing, written = time.perf_counter(), start(tmp_path, out), None, None
    while proc.poll() is None:
        if writing is None and staging_folders(out):
            writing = time.perf_counter()
        elif writing is not None and written is None and not staging_folders(out):
            written = time.perf_counter()
        time.sleep(0.002)
    duration = time.perf_counter() - began
    assert proc.returncode == 0, (tmp_path / "cli-output.txt").read_text()[-2000:]
    assert writing is not None and written is not None, "the staging folder was never seen"
    write_time = written - writing
    complete = decode_outputs(out, mask)

    killed_while_writing, report = 0, []
    moments = [("fraction", f) for f in (0.25, 0.5, 0.75, 0.95)] + [("writing", f) for f in (0.1, 0.5)]
    for kind, fraction in moments:
        before = staging_folders(out)
        began, proc = time.perf_counter(), start(tmp_path, out)
        while proc.poll() is None:
            now = time.perf_counter()
            if kind == "fraction" and now - began >= fraction * duration:
                break
            if kind == "writing" and staging_folders(out) - before:
                time.sleep(fraction * write_time)
                break
            time.sleep(0.002)
        alive = proc.poll() is None
        proc.kill()
        proc.wait()
        left = staging_folders(out) - before
        killed_while_writing += bool(left)
        report.append(f"{kind} {fraction}: killed at {time.perf_counter() - began:.2f} s"
                      + (" while writing" if left else "" if alive else " (had finished)"))
        # every file under a final name decodes whole: the previous run's, or this run's
        assert set(decode_outputs(out, mask)) == set(complete), (kind, fraction)

    # a kill did interrupt the writing (it left its staging folder): the check above saw that case
    assert killed_while_writing >= 1, "no kill fell in the writing phase"
    # a later run publishes over what the killed ones left behind
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        cli.run(compose(config_name="config", overrides=[*overrides, f"out={out}"]))
    assert set(decode_outputs(out, mask)) == set(complete)
    print(f"run {duration:.1f} s, writing {write_time:.2f} s;", "; ".join(report))
