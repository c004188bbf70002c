import json
import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh
from omegaconf import OmegaConf
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


def test_time_per_call_is_the_call_not_the_sum_of_nested_stages(tmp_path):
    from sfs_torch.cli import _finish
    from sfs_torch.pipeline import Estimate

    normals, mask = sphere(32, 12.0)
    image = render_sh(normals[None], natural_lightings(0.7)["uffizi_gallery"][None])[0] * mask
    est = Estimate(normals=normals, confidence=mask.float(), lighting=natural_lightings(0.7)["uffizi_gallery"],
                   depth=None, mask=mask,
                   timings={"database": 4.0, "lighting": 0.5, "final round": 2.0, "train forest": 1.5})
    numbers = _finish(tmp_path, est, 6.75, image, mask, "t", None, None)
    assert numbers["time per call (s)"] == 2.75  # the call's 6.75 s less the database's one-off 4 s
    assert numbers["time train forest (s)"] == 1.5 and (tmp_path / "summary.png").is_file()


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
        assert numbers["time final round (s)"] <= numbers["time per call (s)"]
        normals = np.load(out / "normals.npy")
        assert normals.shape == (48, 48, 3) and normals.dtype == np.float32

    def test_user_files_with_integration(self, tmp_path):
        mask = write_sphere(tmp_path)
        out = tmp_path / "result"
        args = [*TINY, "image=obj.png", "mask=obj_mask.png", f"out={out}", "integrate=l2", "mesh_formats=[ply,obj,glb]"]
        result = run_cli(args, tmp_path)
        assert result.returncode == 0, result.stderr
        for name in SPEC_FILES + ["depth.npy", "depth.png", "depth.json", "novel_view.png", "summary.png"]:
            assert (out / name).is_file(), name
        normals = np.load(out / "normals.npy")
        m = mask[0].numpy()
        assert np.all(normals[~m] == 0)
        assert np.allclose(np.linalg.norm(normals[m], axis=-1), 1, atol=1e-5)
        sh = io.read_lighting(out / "lighting.json")
        assert sh.shape == (3, 9)
        # depth.png + depth.json decode to depth.npy within half a quantisation step
        depth = np.load(out / "depth.npy")
        decode = json.loads((out / "depth.json").read_text())
        assert decode["file"] == "depth.png" and decode["focal"] is None
        back = io.read_depth_png(out / "depth.png", scale=decode["scale"], offset=decode["offset"])
        assert np.array_equal(back.mask[0].numpy(), m)
        assert np.abs(back.depth[0].numpy() - depth)[m].max() <= decode["scale"] / 2 + 1e-5
        assert (decode["depth_min"], decode["depth_max"]) == pytest.approx((depth[m].min(), depth[m].max()))
        # every mesh: one vertex per mask pixel (row-major) carrying the estimated normal there
        for kind in ("ply", "obj", "glb"):
            loaded = trimesh.load(out / f"mesh.{kind}", process=False, maintain_order=True)
            mesh = next(iter(loaded.geometry.values())) if isinstance(loaded, trimesh.Scene) else loaded
            assert len(mesh.vertices) == m.sum(), kind
            np.testing.assert_allclose(mesh.vertices[:, 2], depth[m], atol=1e-4, err_msg=kind)
            np.testing.assert_allclose(mesh.vertex_normals, normals[m], atol=1e-6, err_msg=kind)

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

    def test_joblib_sweep_writes_a_folder_per_job(self, tmp_path):
        pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="pip install -e '.[sweep]'")
        write_sphere(tmp_path)
        sweep = tmp_path / "sweep"
        args = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", *TINY, "image=obj.png", "mask=obj_mask.png",
                # the forest's normals, not the silhouette prior a sphere keeps, so the seeds show
                "forest.seed=0,1", "keep_prior=false", f"out={sweep}"]
        result = run_cli(args, tmp_path)
        assert result.returncode == 0, result.stderr
        assert "Joblib.Parallel(n_jobs=2" in result.stdout + result.stderr  # the joblib launcher ran the jobs
        jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
        assert [job.name for job in jobs] == ["0", "1"]
        seeds = []
        for job in jobs:
            assert (job / "normals.npy").is_file() and (job / "lighting.json").is_file()
            assert not (sweep / "normals.npy").exists()
            resolved = OmegaConf.load(job / ".hydra" / "config.yaml")
            assert resolved.image == "obj.png" and resolved.forest.n_trees == 4
            seeds.append(resolved.forest.seed)
            assert f"forest.seed={resolved.forest.seed}" in OmegaConf.load(job / ".hydra" / "overrides.yaml")
        assert sorted(seeds) == [0, 1]
        # the same image with another forest: the normals differ
        assert not np.array_equal(np.load(jobs[0] / "normals.npy"), np.load(jobs[1] / "normals.npy"))

    def test_bad_mesh_format_is_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, "mesh_formats=[ply,stl]", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "mesh_formats may hold ply, obj, glb" in result.stderr + result.stdout
        assert "got 'stl'" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr
        assert not (tmp_path / "x" / "normals.npy").exists()

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
        args = [*TINY, "image=obj.png", "mask=obj_mask.png", f"out={out}"]
        first = run_cli([*args, "integrate=l2", "mesh_formats=[ply,obj,glb]"], tmp_path)
        assert first.returncode == 0, first.stderr
        extras = ("depth.npy", "depth.png", "depth.json", "mesh.ply", "mesh.obj", "mesh.glb", "novel_view.png")
        for name in extras:
            assert (out / name).is_file(), name
        again = run_cli([*args, "refine=known"], tmp_path)  # no integration, no refined surface: no depth
        assert again.returncode == 0, again.stderr
        for name in extras:
            assert not (out / name).exists(), name
        assert (out / "normals.npy").is_file()
        assert not list(out.glob(".sfs-torch-partial-*"))


class TestConfigCheckedAtEntry:
    """A bad pipeline option fails in one line naming its key, before the demo scene, the input
    files, the renderer or any item of a batch is touched (the database above all)."""

    CASES = [
        (["refine_rounds=-1"], "refine_rounds must be an integer >= 0, got -1"),
        (["normal_rotation=pxl"], "normal_rotation must be one of ('centroid', 'pixel'), got 'pxl'"),
        (["integrate.method=l3"], "integrate.method must be one of ('none', 'l2', 'l1', 'conv')"),
        (["integrate.max_iter=0"], "integrate.max_iter must be an integer >= 1, got 0"),  # also with none
        (["forest.n_trees=0"], "forest.n_trees must be an int >= 1, got 0"),
        (["silhouette.depth_layer_ratio=0.5"], "silhouette.depth_layer_ratio must be > 1"),
    ]

    @pytest.fixture()
    def no_work(self, monkeypatch):
        import sfs_torch.cli as cli
        import sfs_torch.pipeline as pipeline

        def never(*args, **kwargs):
            raise AssertionError("work started before the config was checked")

        for module, name in ((cli, "_demo_inputs"), (cli, "evaluation_shapes"), (cli, "estimate"), (cli, "_read_item"),
                             (cli, "gl_context"), (cli.io, "read_image_and_mask"), (pipeline, "load_database")):
            monkeypatch.setattr(module, name, never)
        return cli

    @pytest.mark.parametrize("mode", ["demo", "image", "batch"])
    @pytest.mark.parametrize("overrides, message", CASES, ids=[c[0][0] for c in CASES])
    def test_run_and_batch(self, tmp_path, no_work, mode, overrides, message):
        photos = tmp_path / "photos"
        (photos / "item").mkdir(parents=True)
        extra = {"demo": [], "image": ["image=obj.png", "integrate=l2"], "batch": [f"input_dir={photos}"]}[mode]
        cfg = compose_batch([*extra, *overrides, f"out={tmp_path / 'r'}"])
        with pytest.raises(ValueError) as info:
            (no_work.run_batch if mode == "batch" else no_work.run)(cfg)
        assert message in str(info.value)
        assert not (tmp_path / "r").exists()

    @pytest.mark.parametrize("override, message", [
        ("demo.albedo=-1", "demo.albedo must be a number > 0, got -1"),  # a black image, fitted silently before
        ("demo.albedo=0", "demo.albedo must be a number > 0, got 0"),
        ("demo.noise_sigma=-0.1", "demo.noise_sigma must be a number >= 0, got -0.1"),
        ("demo.resolution=4", "demo.resolution must be an integer >= 8, got 4"),
        ("demo.shape=-1", "demo.shape must be an integer >= 0, got -1"),
        ("demo.lighting=sun", "demo.lighting must be one of ['campus_sunset', "),
    ])
    def test_demo_options_before_the_meshes(self, tmp_path, no_work, override, message):
        cfg = compose_batch([override, f"out={tmp_path / 'r'}"])
        with pytest.raises(ValueError) as info:
            no_work.run(cfg)
        assert message in str(info.value)
        assert not (tmp_path / "r").exists()

    def test_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, "normal_rotation=pxl", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "normal_rotation must be one of ('centroid', 'pixel'), got 'pxl'" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr

    @pytest.mark.parametrize("old, hint", [
        ("reflectance_map.refine_rounds=0", "reflectance_map.refine_rounds is now refine_rounds"),
        ("integrate.method=null", "integrate.method=None is now integrate.method='none' (integrate=none)"),
    ])
    def test_a_moved_key_says_where_it_went(self, tmp_path, old, hint):
        result = run_cli([*TINY, old, "out=x"], tmp_path)
        assert result.returncode == 2
        assert hint in result.stderr
        assert "Traceback" not in result.stderr and not (tmp_path / "x").exists()


class TestMeshFormats:
    @pytest.mark.parametrize(
        "value, expected",
        [(["ply"], ("ply",)), (["glb", "PLY", "glb"], ("glb", "ply")), ([], ()), ("obj", ("obj",))],
    )
    def test_valid(self, value, expected):
        from sfs_torch.cli import _mesh_formats

        assert _mesh_formats(OmegaConf.create({"v": value}).v) == expected

    @pytest.mark.parametrize("value", [["stl"], None, 3, [1], "ply,obj"])
    def test_invalid(self, value):
        from sfs_torch.cli import _mesh_formats

        with pytest.raises(ValueError, match="mesh_formats"):
            _mesh_formats(OmegaConf.create({"v": value}).v)

    def test_checked_before_any_work(self, tmp_path, monkeypatch):
        from hydra import compose, initialize_config_module

        import sfs_torch.cli as cli

        def never(*args, **kwargs):
            raise AssertionError("work started before mesh_formats was checked")

        monkeypatch.setattr(cli, "_demo_inputs", never)
        monkeypatch.setattr(cli, "estimate", never)
        with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
            cfg = compose(config_name="config", overrides=[*TINY, "mesh_formats=[obj,gltf]", f"out={tmp_path / 'r'}"])
        with pytest.raises(ValueError, match="mesh_formats may hold ply, obj, glb .*got 'gltf'"):
            cli.run(cfg)
        assert not (tmp_path / "r").exists()

    def test_publish_drops_the_formats_a_rerun_did_not_write(self, tmp_path):
        from sfs_torch.cli import _publish

        out, staging = tmp_path / "out", tmp_path / "out" / ".sfs-torch-partial-x"
        staging.mkdir(parents=True)
        for name in ("mesh.ply", "mesh.obj", "depth.png", "depth.json", "normals.npy"):
            (out / name).write_text("old")
        for name in ("mesh.glb", "depth.png", "depth.json", "normals.npy"):
            (staging / name).write_text("new")
        _publish(staging, out)
        files = {p.name: p.read_text() for p in out.iterdir() if p.is_file()}
        assert files == {"mesh.glb": "new", "depth.png": "new", "depth.json": "new", "normals.npy": "new"}


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


def write_item(folder, radius=18.0, truth=False, size=48):
    """One batch item in the folder layout: ``image.png``, ``mask.png`` (+ ``normals.npy``)."""
    normals, mask = sphere(size, radius)
    image = (render_sh(normals[None], natural_lightings(0.7)["uffizi_gallery"][None])[0] * mask).clamp(0, 1)
    io.write_image(folder / "image.png", image, bits=16)
    io.write_image(folder / "mask.png", mask.float(), srgb=False)
    if truth:
        io.write_normals_npy(folder / "normals.npy", normals)
    return folder


def read_summary(out):
    import csv

    with open(out / "summary.csv", newline="") as f:
        return list(csv.DictReader(f))


def compose_batch(overrides):
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="config", overrides=[*TINY, *overrides])


class TestBatch:
    def test_runs_every_item_reports_failures_and_resumes(self, tmp_path):
        photos = tmp_path / "photos"
        write_item(photos / "a_sphere", truth=True)
        write_item(photos / "b_sphere", radius=14.0)
        broken = write_item(photos / "c_broken")
        (broken / "mask.png").write_text("not an image")
        (photos / "_notes").mkdir()  # ignored, as by load_folder
        out = tmp_path / "results"
        args = [*TINY, f"input_dir={photos}", f"out={out}"]

        first = run_cli(args, tmp_path)
        assert first.returncode == 1, first.stderr  # the batch ran to the end, one item failed
        log = first.stdout + first.stderr
        assert "Traceback" not in log
        failure_lines = [line for line in log.splitlines() if "c_broken: failed:" in line]
        assert len(failure_lines) == 1 and "mask.png" in failure_lines[0]
        assert "2 ok, 1 failed, 0 skipped" in log
        rows = read_summary(out)
        assert list(rows[0]) == ["item", "status", "seconds", "error", "median_error_deg"]
        assert [(r["item"], r["status"]) for r in rows] == [("a_sphere", "ok"), ("b_sphere", "ok"), ("c_broken", "failed")]
        assert "mask.png" in rows[2]["error"] and rows[0]["error"] == rows[1]["error"] == ""
        assert float(rows[0]["seconds"]) > 0 and float(rows[1]["seconds"]) > 0
        for item in ("a_sphere", "b_sphere"):
            for name in SPEC_FILES + ["summary.png", "metrics.json"]:
                assert (out / item / name).is_file(), (item, name)
            assert not list((out / item).glob(".sfs-torch-partial-*"))
            assert np.load(out / item / "normals.npy").shape == (48, 48, 3)
        assert not (out / "c_broken" / "normals.npy").exists() and not (out / "_notes").exists()
        # the angular error against the ground truth normals, only where there are some
        numbers = json.loads((out / "a_sphere" / "metrics.json").read_text())
        assert float(rows[0]["median_error_deg"]) == pytest.approx(numbers["median error (deg)"], abs=1e-4)
        # no worse than the silhouette prior, which a sphere may keep (keep_prior)
        assert 0 <= numbers["median error (deg)"] <= numbers["silhouette-only median (deg)"] + 1e-3
        assert rows[1]["median_error_deg"] == "" and rows[2]["median_error_deg"] == ""
        assert "median error (deg)" not in json.loads((out / "b_sphere" / "metrics.json").read_text())

        # a rerun skips the finished items (their files untouched) and retries the failed one
        stamps = {item: (out / item / "normals.npy").stat().st_mtime_ns for item in ("a_sphere", "b_sphere")}
        again = run_cli(args, tmp_path)
        assert again.returncode == 1, again.stderr
        rows = read_summary(out)
        assert [r["status"] for r in rows] == ["skipped", "skipped", "failed"]
        assert float(rows[0]["median_error_deg"]) == pytest.approx(numbers["median error (deg)"], abs=1e-4)
        assert {item: (out / item / "normals.npy").stat().st_mtime_ns for item in stamps} == stamps

        # with the broken item repaired every item is ok or skipped: exit code 0
        write_item(broken)
        fixed = run_cli(args, tmp_path)
        assert fixed.returncode == 0, fixed.stderr
        assert [r["status"] for r in read_summary(out)] == ["skipped", "skipped", "ok"]
        assert (out / "c_broken" / "normals.npy").is_file()

    def test_missing_input_dir_is_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, f"input_dir={tmp_path / 'nowhere'}", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "input_dir: no such folder" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr

    @pytest.mark.parametrize(
        "case, extra, match",
        [
            ("empty", [], "holds no item folder"),
            ("only_hidden", [], "holds no item folder"),
            ("file", [], "must be a folder of item folders"),
            ("good", ["image=obj.png"], "image= cannot be given too"),
            ("good", ["lighting=light.json"], "lighting= cannot be given too"),
            ("good", ["image_srgb=false"], "store linear images as image.npy"),
            ("out_inside", [], "is inside input_dir"),
        ],
    )
    def test_checked_before_any_work(self, tmp_path, monkeypatch, case, extra, match):
        import sfs_torch.cli as cli

        def never(*args, **kwargs):
            raise AssertionError("work started before input_dir was checked")

        monkeypatch.setattr(cli, "_read_item", never)
        monkeypatch.setattr(cli, "estimate", never)
        photos, out = tmp_path / "photos", tmp_path / "r"
        photos.mkdir()
        if case == "only_hidden":
            (photos / ".cache").mkdir()
            (photos / "_old").mkdir()
        elif case == "file":
            photos.rmdir()
            photos.write_text("a file")
        elif case in ("good", "out_inside"):
            (photos / "item").mkdir()
            if case == "out_inside":
                out = photos / "results"
        cfg = compose_batch([f"input_dir={photos}", f"out={out}", *extra])
        with pytest.raises(ValueError, match=match):
            cli.run_batch(cfg)
        assert not out.exists()

    def test_item_files_reach_the_single_image_path(self, tmp_path, monkeypatch):
        import sfs_torch.cli as cli

        photos = tmp_path / "photos"
        item = write_item(photos / "persp", truth=True)
        sh = natural_lightings(0.7)["uffizi_gallery"]
        io.write_lighting(item / "lighting.json", sh)
        (item / "camera.json").write_text(json.dumps({"focal": 300.0, "principal_point": [20.0, 25.0]}))
        write_item(photos / "plain")  # no lighting.json: estimated; no camera.json: the command's camera
        calls = {}

        def record(out, image, mask, known, pipeline_cfg, mesh_formats, title, **kwargs):
            calls[out.name] = (image, mask, known, pipeline_cfg.camera, kwargs)
            return {}

        monkeypatch.setattr(cli, "_estimate_and_publish", record)
        result = cli.run_batch(compose_batch([f"input_dir={photos}", f"out={tmp_path / 'r'}", "camera=persp"]))
        assert [(r.item, r.status) for r in result.items] == [("persp", "ok"), ("plain", "ok")]
        image, mask, known, camera, kwargs = calls["persp"]
        assert image.shape == (3, 48, 48) and mask.shape == (1, 48, 48) and mask.dtype == torch.bool
        assert torch.allclose(known, sh)
        assert camera.focal == 300.0 and list(camera.principal_point) == [20.0, 25.0]
        assert kwargs["true_normals"].shape == (3, 48, 48) and kwargs["progress"] is False
        _, _, known, camera, kwargs = calls["plain"]
        assert known is None and kwargs["true_normals"] is None
        assert camera.focal == 1000.0 and camera.principal_point is None  # camera=persp's

    def test_the_database_is_loaded_once_for_the_batch(self, tmp_path, database_loads):
        import sfs_torch.cli as cli

        photos = tmp_path / "photos"
        for name, radius in (("a", 12.0), ("b", 10.0), ("c", 11.0)):
            write_item(photos / name, radius=radius, size=32)
        result = cli.run_batch(compose_batch([f"input_dir={photos}", f"out={tmp_path / 'r'}", "refine_rounds=0",
                                              "refine.when=never"]))
        assert [r.status for r in result.items] == ["ok", "ok", "ok"]
        # once for the batch, not once per item (each estimate() read and hashed the file again)
        assert len(database_loads) == 1

    def test_skip_done_false_recomputes(self, tmp_path, monkeypatch):
        import sfs_torch.cli as cli

        photos, out = tmp_path / "photos", tmp_path / "r"
        write_item(photos / "a")
        # a given lighting: no refined surface, so these are all the files a default run writes
        io.write_lighting(photos / "a" / "lighting.json", natural_lightings(0.7)["uffizi_gallery"])
        (out / "a").mkdir(parents=True)
        for name in cli.REQUIRED_OUTPUTS:
            (out / "a" / name).write_text("{}")
        monkeypatch.setattr(cli, "_estimate_and_publish", lambda *args, **kwargs: {})
        skipped = cli.run_batch(compose_batch([f"input_dir={photos}", f"out={out}"]))
        assert [r.status for r in skipped.items] == ["skipped"]
        # integrate= adds files: the item is incomplete for that run
        deeper = cli.run_batch(compose_batch([f"input_dir={photos}", f"out={out}", "integrate=l2"]))
        assert [r.status for r in deeper.items] == ["ok"]
        redone = cli.run_batch(compose_batch([f"input_dir={photos}", f"out={out}", "skip_done=false"]))
        assert [r.status for r in redone.items] == ["ok"]

    def test_rerun_is_not_skipped_when_it_writes_more_files(self, tmp_path):
        """An estimated lighting's refined surface gives depth, meshes and a novel view without
        integrate=: a rerun asking for another mesh format, or an item lacking the depth files,
        is not finished."""
        import sfs_torch.cli as cli

        photos, out = tmp_path / "photos", tmp_path / "r"
        write_item(photos / "a", radius=12.0, size=32)
        fast = [f"input_dir={photos}", f"out={out}", "refine_rounds=0", "refine.iterations=5"]
        first = cli.run_batch(compose_batch(fast))
        assert [r.status for r in first.items] == ["ok"]
        assert (out / "a" / "mesh.ply").is_file() and not (out / "a" / "mesh.glb").exists()
        # the same run again finds every file it would write
        assert [r.status for r in cli.run_batch(compose_batch(fast)).items] == ["skipped"]
        again = cli.run_batch(compose_batch([*fast, "mesh_formats=[ply,glb]"]))
        assert [r.status for r in again.items] == ["ok"]
        assert (out / "a" / "mesh.glb").is_file()
        (out / "a" / "depth.npy").unlink()
        assert [r.status for r in cli.run_batch(compose_batch(fast)).items] == ["ok"]

    @pytest.mark.parametrize(
        "overrides, given, depth",
        [
            ([], False, True),  # the joint refinement's surface
            ([], True, False),  # a given lighting: the pixel model
            (["integrate=l2"], True, True),
            (["refine.when=never"], False, False),
            (["refine.when=known"], False, False),
            (["refine.when=known", "refine.model=surface"], True, True),
            (["refine.model=pixel"], False, False),
            (["refine.optimise_lighting=false"], False, False),
        ],
    )
    def test_expected_outputs_follow_the_depth_rule(self, overrides, given, depth):
        import sfs_torch.cli as cli

        pipeline_cfg = cli._pipeline_config(compose_batch(overrides))
        expected = cli._expected_outputs(pipeline_cfg, ("ply", "glb"), given)
        assert ("mesh.glb" in expected) is depth and ("depth.npy" in expected) is depth


class TestNovelViewRenderer:
    @staticmethod
    def no_context():
        from sfs_torch.preview import GLContext

        return GLContext(False, "egl", None, "no OpenGL context on egl: EGLError: no display")

    def test_bad_renderer_is_one_clear_line(self, tmp_path):
        result = run_cli([*TINY, "novel_view.renderer=vulkan", "out=x"], tmp_path)
        assert result.returncode == 2
        assert "novel_view.renderer must be one of auto, pyrender, embree, got 'vulkan'" in result.stderr + result.stdout
        assert "Traceback" not in result.stderr
        assert not (tmp_path / "x" / "normals.npy").exists()

    @pytest.mark.parametrize("batch", [False, True], ids=["single", "batch"])
    def test_pyrender_without_a_context_is_checked_before_any_work(self, tmp_path, monkeypatch, batch):
        import sfs_torch.cli as cli

        def never(*args, **kwargs):
            raise AssertionError("work started before novel_view.renderer was checked")

        monkeypatch.setattr(cli, "gl_context", self.no_context)
        monkeypatch.setattr(cli, "_demo_inputs", never)
        monkeypatch.setattr(cli, "estimate", never)
        extra = [f"input_dir={write_item(tmp_path / 'photos' / 'a').parent}"] if batch else []
        cfg = compose_batch([*extra, "integrate=l2", "novel_view.renderer=pyrender", f"out={tmp_path / 'r'}"])
        with pytest.raises(ValueError, match="novel_view.renderer=pyrender needs an offscreen OpenGL context, but no "
                                             "OpenGL context on egl: EGLError: no display; use novel_view.renderer=auto"):
            (cli.run_batch if batch else cli.run)(cfg)
        assert not (tmp_path / "r").exists()

    def test_auto_falls_back_and_says_so(self, monkeypatch, caplog):
        import logging

        import sfs_torch.cli as cli

        monkeypatch.setattr(cli, "gl_context", self.no_context)
        cfg = compose_batch(["integrate=l2", "out=x"])
        with caplog.at_level(logging.INFO, logger="sfs_torch"):
            view = cli._novel_view(cfg, cli._pipeline_config(cfg))
        assert view.choice.name == "embree" and view.choice.requested == "auto"
        assert "novel view renderer: embree: the Embree ray caster; pyrender unavailable (no OpenGL context" in caplog.text

    def test_no_context_is_made_without_a_novel_view(self, monkeypatch):
        import sfs_torch.cli as cli

        monkeypatch.setattr(cli, "gl_context", lambda: pytest.fail("no novel view is drawn: no context needed"))
        cfg = compose_batch(["novel_view.renderer=pyrender", "refine=never", "out=x"])  # no depth map at all
        assert cli._novel_view(cfg, cli._pipeline_config(cfg)).choice is None
        cfg = compose_batch(["novel_view.renderer=pyrender", "out=x"])  # a given lighting: per-pixel normals
        assert cli._novel_view(cfg, cli._pipeline_config(cfg), given=True).choice is None

    def test_the_refined_surface_is_drawn_by_the_renderer_asked_for(self):
        # an estimated lighting's refined surface is a depth map without integrate=: its
        # novel view used to ignore novel_view.renderer (always the ray caster)
        import sfs_torch.cli as cli

        cfg = compose_batch(["novel_view.renderer=embree", "out=x"])
        for given in (False, None):
            view = cli._novel_view(cfg, cli._pipeline_config(cfg), given=given)
            assert view.choice is not None and view.choice.name == "embree"

    @pytest.mark.parametrize("override, match", [
        ("novel_view.resolution=0", "novel_view.resolution must be a positive integer"),
        ("novel_view.azimuth_deg=inf", "must be finite"),
    ])
    def test_bad_viewpoint(self, override, match):
        import sfs_torch.cli as cli

        cfg = compose_batch([override, "integrate=l2", "novel_view.renderer=embree", "out=x"])
        with pytest.raises(ValueError, match=match):
            cli._novel_view(cfg, cli._pipeline_config(cfg))

    def test_the_choice_and_viewpoint_reach_the_novel_view(self, tmp_path, monkeypatch):
        from types import SimpleNamespace

        import sfs_torch.cli as cli

        calls = []

        def record(mesh, lighting, **kwargs):
            calls.append(kwargs)
            return torch.zeros(3, kwargs["resolution"], kwargs["resolution"])

        monkeypatch.setattr(cli, "render_novel_view", record)
        cfg = compose_batch(["integrate=l2", "novel_view.renderer=embree", "novel_view.azimuth_deg=-50",
                             "novel_view.resolution=40", "out=x"])
        pipeline_cfg = cli._pipeline_config(cfg)
        normals, mask = sphere(24, 9.0)
        depth = 9.0 * normals[2:]  # the sphere's height, in pixels
        est = SimpleNamespace(normals=normals, mask=mask, depth=depth, lighting=natural_lightings(0.7)["uffizi_gallery"],
                              confidence=torch.ones(1, 24, 24))
        cli._write_outputs(tmp_path, est, pipeline_cfg.camera, (), cli._novel_view(cfg, pipeline_cfg))
        assert calls == [dict(azimuth_deg=-50.0, elevation_deg=20.0, resolution=40, renderer="embree")]
        assert io.read_image(tmp_path / "novel_view.png").shape == (3, 40, 40)
