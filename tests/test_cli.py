import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from scenes import sphere

from sfs_torch import io
from sfs_torch.lighting import natural_lightings, render_sh

TINY = [
    "database=blobby",
    "database.n_shapes=12",
    "database.n_views=4",
    "database.resolution=64",
    "database.n_eval_shapes=2",
    "forest.n_trees=4",
    "forest.max_depth=10",
]
SPEC_FILES = ["normals.npy", "normals.png", "lighting.json", "reflectance_map.png", "confidence.png"]


def run_cli(args, cwd):
    return subprocess.run(
        [sys.executable, "-c", "from sfs_torch.cli import main; main()", *args],
        cwd=cwd, capture_output=True, text=True, timeout=600,
    )


def write_sphere(tmp_path, size=48, radius=18.0):
    normals, mask = sphere(size, radius)
    image = (render_sh(normals[None], natural_lightings(0.7)["uffizi_gallery"][None])[0] * mask).clamp(0, 1)
    io.write_image(tmp_path / "obj.png", image, bits=16)
    io.write_image(tmp_path / "obj_mask.png", mask.float(), srgb=False)
    return mask


class TestCLI:
    def test_demo_writes_everything(self, tmp_path):
        result = run_cli([*TINY, "demo.shape=0", "demo.resolution=48", f"out={tmp_path / 'demo'}"], tmp_path)
        assert result.returncode == 0, result.stderr
        out = tmp_path / "demo"
        for name in SPEC_FILES + ["summary.png", "metrics.json"]:
            assert (out / name).is_file(), name
        numbers = json.loads((out / "metrics.json").read_text())
        # the full method must beat the silhouette-only coarse normal on the demo shape
        assert numbers["median error (deg)"] < numbers["silhouette-only median (deg)"]
        normals = np.load(out / "normals.npy")
        assert normals.shape == (48, 48, 3) and normals.dtype == np.float32

    def test_user_files_with_integration(self, tmp_path):
        mask = write_sphere(tmp_path)
        out = tmp_path / "result"
        result = run_cli([*TINY, "image=obj.png", "mask=obj_mask.png", f"out={out}", "integrate=l2"], tmp_path)
        assert result.returncode == 0, result.stderr
        for name in SPEC_FILES + ["depth.npy", "mesh.ply", "novel_view.png", "summary.png"]:
            assert (out / name).is_file(), name
        normals = np.load(out / "normals.npy")
        assert np.all(normals[~mask[0].numpy()] == 0)
        assert np.allclose(np.linalg.norm(normals[mask[0].numpy()], axis=-1), 1, atol=1e-5)
        sh = io.read_lighting(out / "lighting.json")
        assert sh.shape == (3, 9)

    def test_known_lighting(self, tmp_path):
        write_sphere(tmp_path)
        sh = natural_lightings(0.7)["uffizi_gallery"]
        io.write_lighting(tmp_path / "light.json", sh)
        # no out=: a dated folder under outputs/
        result = run_cli([*TINY, "image=obj.png", "mask=obj_mask.png", "lighting=light.json"], tmp_path)
        assert result.returncode == 0, result.stderr
        written = list((tmp_path / "outputs").glob("*/*/lighting.json"))
        assert len(written) == 1
        assert torch.allclose(io.read_lighting(written[0]), sh)

    def test_multirun_sweep(self, tmp_path):
        write_sphere(tmp_path)
        result = run_cli(["-m", *TINY, "image=obj.png", "mask=obj_mask.png", "features=rgb,all"], tmp_path)
        assert result.returncode == 0, result.stderr
        jobs = sorted((tmp_path / "multirun").glob("*/*/[0-9]"))
        assert len(jobs) == 2
        for job in jobs:
            assert (job / "normals.npy").is_file()

    def test_bad_input_is_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, "image=missing.png", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "missing.png" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr

    def test_unwritable_out_is_one_clear_line(self, tmp_path):
        (tmp_path / "a_file").write_text("not a folder")
        result = run_cli([*TINY, f"out={tmp_path / 'a_file' / 'sub'}"], tmp_path)
        assert result.returncode == 2
        assert "cannot write to out=" in result.stderr
        assert "Traceback" not in result.stderr

    def test_bad_device_is_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, "device=foo", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "device must be 'cpu', 'cuda' or 'cuda:N', got 'foo'" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr

    @pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
    def test_cuda_without_cuda_says_how_to_fall_back(self, tmp_path):
        result = run_cli([*TINY, "device=cuda", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "sees no CUDA device here; run with device=cpu" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr

    def test_rerun_removes_the_previous_runs_extras(self, tmp_path):
        write_sphere(tmp_path)
        out = tmp_path / "result"
        first = run_cli([*TINY, "image=obj.png", "mask=obj_mask.png", f"out={out}", "integrate=l2"], tmp_path)
        assert first.returncode == 0, first.stderr
        assert (out / "depth.npy").is_file()
        again = run_cli([*TINY, "image=obj.png", "mask=obj_mask.png", f"out={out}"], tmp_path)
        assert again.returncode == 0, again.stderr
        for name in ("depth.npy", "mesh.ply", "novel_view.png"):
            assert not (out / name).exists(), name
        assert (out / "normals.npy").is_file()
        assert not list(out.glob(".sfs-torch-partial-*"))


class TestAtomicOutputs:
    def test_a_crash_while_writing_leaves_the_previous_outputs_whole(self, tmp_path, monkeypatch):
        from hydra import compose, initialize_config_module

        import sfs_torch.cli as cli

        write_sphere(tmp_path)
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path / "cache"))
        out = tmp_path / "result"
        overrides = [*TINY, f"image={tmp_path / 'obj.png'}", f"mask={tmp_path / 'obj_mask.png'}", f"out={out}"]
        with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
            cli.run(compose(config_name="config", overrides=overrides))
            before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

            def crash(*args, **kwargs):
                raise RuntimeError("killed while writing the summary")

            # a crash after the first files of the second run were written
            monkeypatch.setattr(cli, "summary_figure", crash)
            with pytest.raises(RuntimeError, match="killed"):
                cli.run(compose(config_name="config", overrides=[*overrides, "integrate=l2"]))
        after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
        assert after == before  # nothing of the failed run under a final name, nothing lost
        assert not any(p.is_dir() and p.name.startswith(".sfs-torch-partial-") for p in out.iterdir())
        decoded = io.read_normals_npy(out / "normals.npy")
        assert decoded.shape == (3, 48, 48)
