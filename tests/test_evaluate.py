"""The ``sfs-torch-eval`` command (sfs_torch.evaluate): tiny pipeline, 32-40 px scenes, a few cases."""
import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from scenes import sphere

import sfs_torch.evaluate as ev
from sfs_torch import io
from sfs_torch.datasets import Scene
from sfs_torch.lighting import natural_lightings, render_sh
from sfs_torch.silhouette import coarse_normals

# the pipeline options tests/test_cli.py uses, under the eval app's `pipeline` node
TINY = [
    "pipeline.database.collection=blobby",
    "pipeline.database.n_shapes=12",
    "pipeline.database.n_views=4",
    "pipeline.database.resolution=64",
    "pipeline.database.n_eval_shapes=2",
    "pipeline.forest.n_trees=4",
    "pipeline.forest.max_depth=10",
    "progress=false",
]
# a sphere and the one test-side blob of the tiny database, under one R&H lighting
SYNTHETIC = ["dataset=synthetic", "dataset.shapes=1", "dataset.lights=1", "dataset.sphere=true",
             "dataset.resolution=40"]
CONF = Path(__file__).resolve().parents[1] / "conf"


def compose_eval(overrides):
    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="eval", overrides=list(overrides))


def run_eval(overrides):
    return ev.evaluate(compose_eval(overrides), command="sfs-torch-eval " + " ".join(overrides))


def read_csv(path):
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return reader.fieldnames, list(reader)


def run_cli(args, cwd):
    return subprocess.run([sys.executable, "-c", "from sfs_torch.evaluate import main; main()", *args],
                          cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    """All five methods on two synthetic cases, once for the module."""
    out = tmp_path_factory.mktemp("eval") / "out"
    with pytest.MonkeyPatch.context() as mp:
        # the conftest's per-test cache fixture does not reach a module fixture
        mp.setenv("SFS_TORCH_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
        summary = run_eval([*TINY, *SYNTHETIC, f"out={out}"])
    header, rows = read_csv(out / "cases.csv")
    return {"out": out, "summary": summary, "header": header,
            "rows": {(r["case"], r["method"]): r for r in rows}, "list": rows}


class TestSyntheticRun:
    CASES = ("sphere|grace_cathedral",)

    def test_one_row_per_case_and_method(self, synthetic_run):
        assert tuple(synthetic_run["header"]) == ev.COLUMNS
        rows = synthetic_run["list"]
        assert len(rows) == 2 * len(ev.BASE_METHODS)
        cases = sorted({r["case"] for r in rows})
        assert len(cases) == 2 and "sphere|grace_cathedral" in cases
        assert {(c, m) for c in cases for m in ev.BASE_METHODS} == set(synthetic_run["rows"])
        for r in rows:
            # synthetic cases have every ground truth: every normal score is filled
            for key in ("mae_deg", "median_deg", "mean_deg", "nmse", "time_s"):
                assert r[key] != "", (r["case"], r["method"], key)
            assert r["mae_deg"] == r["median_deg"]  # SPEC: MAE is the per-case median
            assert 0 <= float(r["nmse"]) <= 4 and float(r["time_s"]) >= 0
            # only the method that estimates a lighting gets an lMSE
            assert (r["lmse"] != "") == (r["method"] == "estimated_lighting")

    def test_flat_on_a_sphere_is_45_degrees(self, synthetic_run):
        # the angle theta of a sphere's normal from the view axis has sin(theta) = r / R:
        # over the disk, P(theta < t) = sin(t)^2, so the median is 45 deg, and the mean is
        # 2 * int_0^1 s asin(s) ds = pi / 4 rad = 45 deg as well
        row = synthetic_run["rows"][("sphere|grace_cathedral", "flat")]
        assert float(row["median_deg"]) == pytest.approx(45.0, abs=1.0)
        assert float(row["mean_deg"]) == pytest.approx(45.0, abs=1.0)
        # nMSE = mean of 2 - 2 cos(theta) = 2 - 2 * (2/3) for a hemisphere's normals
        assert float(row["nmse"]) == pytest.approx(2 / 3, abs=0.02)

    def test_silhouette_on_an_orthographic_sphere(self, synthetic_run):
        assert float(synthetic_run["rows"][("sphere|grace_cathedral", "silhouette")]["median_deg"]) < 2.0

    def test_known_lighting_methods_beat_the_silhouette_on_the_blob(self, synthetic_run):
        blob = next(c for c, _ in synthetic_run["rows"] if not c.startswith("sphere"))
        silhouette = float(synthetic_run["rows"][(blob, "silhouette")]["median_deg"])
        assert float(synthetic_run["rows"][(blob, "known_lighting")]["median_deg"]) < silhouette
        assert float(synthetic_run["rows"][(blob, "classical")]["median_deg"]) < silhouette

    def test_summary_and_report(self, synthetic_run):
        out, rows = synthetic_run["out"], synthetic_run["list"]
        summary = json.loads((out / "summary.json").read_text())
        assert summary == json.loads(json.dumps(synthetic_run["summary"]))
        assert summary["cases"] == 2 and list(summary["methods"]) == list(ev.BASE_METHODS)
        for method, s in summary["methods"].items():
            medians = sorted(float(r["median_deg"]) for r in rows if r["method"] == method)
            assert s["cases"] == s["scored"] == 2
            assert s["median_deg"] == pytest.approx(sum(medians) / 2, rel=1e-5)  # median of two
            times = [float(r["time_s"]) for r in rows if r["method"] == method]
            assert s["time_s"] == pytest.approx(sum(times) / 2, rel=1e-5)
        report = (out / "report.md").read_text().splitlines()
        assert report[0] == "# sfs-torch-eval report"
        assert report[3].startswith("sfs-torch-eval ") and "dataset.sphere=true" in report[3]
        flat = next(line for line in report if line.startswith("| flat |"))
        assert f"{summary['methods']['flat']['median_deg']:.2f}" in flat

    def test_a_figure_per_case(self, synthetic_run):
        figures = sorted(p.name for p in (synthetic_run["out"] / "figures").iterdir())
        assert "sphere__grace_cathedral.png" in figures and len(figures) == 2
        for name in figures:
            data = (synthetic_run["out"] / "figures" / name).read_bytes()
            assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000

    def test_a_finished_run_is_not_redone(self, synthetic_run, monkeypatch):
        def never(*args, **kwargs):
            raise AssertionError("a finished (case, method) ran again")

        monkeypatch.setattr(ev, "run_method", never)
        before = (synthetic_run["out"] / "cases.csv").read_bytes()
        summary = run_eval([*TINY, *SYNTHETIC, f"out={synthetic_run['out']}"])
        assert (synthetic_run["out"] / "cases.csv").read_bytes() == before
        assert summary["methods"] == json.loads(json.dumps(synthetic_run["summary"]["methods"]))


CHEAP = [*TINY, *SYNTHETIC, "methods=[silhouette,flat]", "figures=false"]


class TestResume:
    def test_an_interrupted_run_resumes_where_it_stopped(self, tmp_path, monkeypatch):
        out = tmp_path / "out"
        calls = []
        original = ev.run_method

        def interrupted(name, scene, **kwargs):
            if len(calls) == 3:  # the second case's second method
                raise KeyboardInterrupt
            calls.append((scene.name, name))
            return original(name, scene, **kwargs)

        monkeypatch.setattr(ev, "run_method", interrupted)
        with pytest.raises(KeyboardInterrupt):
            run_eval([*CHEAP, f"out={out}"])
        _, rows = read_csv(out / "cases.csv")
        first = calls[0][0]
        assert [(r["case"], r["method"]) for r in rows] == [(first, "silhouette"), (first, "flat")]

        calls.clear()
        counting = []

        def counted(name, scene, **kwargs):
            counting.append((scene.name, name))
            return original(name, scene, **kwargs)

        monkeypatch.setattr(ev, "run_method", counted)
        summary = run_eval([*CHEAP, f"out={out}"])
        # only the case in progress is redone
        assert len(counting) == 2 and all(case != first for case, _ in counting)
        _, rows = read_csv(out / "cases.csv")
        assert len(rows) == 4 and len({(r["case"], r["method"]) for r in rows}) == 4
        assert summary["methods"]["flat"]["cases"] == 2

        # a new method on resume runs alone, its figure named after what ran
        counting.clear()
        run_eval([*TINY, *SYNTHETIC, "methods=[silhouette,flat,classical]", f"out={out}"])
        assert sorted(m for _, m in counting) == ["classical", "classical"]
        figures = sorted(p.name for p in (out / "figures").iterdir())
        assert len(figures) == 2 and all(name.endswith(".classical.png") for name in figures)

    def test_a_row_cut_short_is_dropped(self, tmp_path):
        out = tmp_path / "out"
        run_eval([*CHEAP, "limit=1", f"out={out}"])
        path = out / "cases.csv"
        whole = path.read_bytes()
        path.write_bytes(whole + b"blob|grace,silhouette,blob,gra")  # killed mid-write
        rows = ev.read_rows(path)
        assert len(rows) == 2 and path.read_bytes() == whole

    def test_other_options_are_not_mixed_in(self, tmp_path):
        out = tmp_path / "out"
        run_eval([*CHEAP, "limit=1", f"out={out}"])
        with pytest.raises(ValueError, match="other dataset options.*resume=false"):
            run_eval([*CHEAP, "limit=1", "dataset.resolution=32", f"out={out}"])
        # more cases is not another option: the run extends
        run_eval([*CHEAP, "dataset.shapes=0", f"out={out}"])
        # resume=false starts over
        run_eval([*CHEAP, "limit=1", "dataset.resolution=32", "resume=false", f"out={out}"])
        _, rows = read_csv(out / "cases.csv")
        assert len(rows) == 2


class TestDatabase:
    def test_loaded_once_for_the_run(self, tmp_path, database_loads):
        # two cases, two forest methods each: every estimate() read and hashed the file again
        summary = run_eval([*TINY, *SYNTHETIC, "methods=[known_lighting_rgb,known_lighting_forest]", "figures=false",
                            f"out={tmp_path / 'out'}"])
        assert summary["methods"]["known_lighting_forest"]["cases"] == 2
        assert len(database_loads) == 1


class TestFolderWithoutGroundTruth:
    def test_runs_and_leaves_the_errors_empty(self, tmp_path):
        normals, mask = sphere(40, 15.0)
        sh = natural_lightings(0.7)["uffizi_gallery"]
        image = (render_sh(normals[None], sh[None])[0] * mask).clamp(0, 1)
        for case in ("lit", "plain"):
            (tmp_path / "data" / case).mkdir(parents=True)
            io.write_image(tmp_path / "data" / case / "image.png", image, bits=16)
            io.write_image(tmp_path / "data" / case / "mask.png", mask.float(), srgb=False)
        io.write_lighting(tmp_path / "data" / "lit" / "lighting.json", sh)
        out = tmp_path / "out"
        summary = run_eval([*TINY, "dataset=folder", f"dataset.root={tmp_path / 'data'}", f"out={out}"])
        _, rows = read_csv(out / "cases.csv")
        methods = {case: [r["method"] for r in rows if r["case"] == case] for case in ("lit", "plain")}
        # without a lighting, the known-lighting methods are skipped
        assert methods == {"lit": list(ev.BASE_METHODS), "plain": ["silhouette", "flat", "estimated_lighting"]}
        for r in rows:
            for key in ("mae_deg", "median_deg", "mean_deg", "under_22_5", "nmse"):
                assert r[key] == "", (r["case"], r["method"], key)
            assert r["time_s"] != ""
            # a given lighting is ground truth for the estimated one
            assert (r["lmse"] != "") == (r["case"] == "lit" and r["method"] == "estimated_lighting")
        assert summary["methods"]["flat"]["median_deg"] is None
        assert summary["methods"]["known_lighting"]["cases"] == 1
        assert summary["methods"]["estimated_lighting"]["lighting_scored"] == 1
        # without normals the figure shows each method's normal map
        assert sorted(p.name for p in (out / "figures").iterdir()) == ["lit.png", "plain.png"]


class TestFigureNames:
    def test_one_figure_per_case(self, tmp_path):
        normals, mask = sphere(32, 12.0)
        image = (render_sh(normals[None], natural_lightings(0.7)["uffizi_gallery"][None])[0] * mask).clamp(0, 1)
        cases = ("a b", "a+b", "a_b")  # one sanitised name, a_b
        for case in cases:
            (tmp_path / "data" / case).mkdir(parents=True)
            io.write_image(tmp_path / "data" / case / "image.png", image, bits=16)
            io.write_image(tmp_path / "data" / case / "mask.png", mask.float(), srgb=False)
        out = tmp_path / "out"
        run_eval([*TINY, "dataset=folder", f"dataset.root={tmp_path / 'data'}", "methods=[silhouette,flat]",
                  f"out={out}"])
        figures = sorted(p.name for p in (out / "figures").iterdir())
        assert len(figures) == 3
        assert "a_b.png" in figures  # the name that spells itself is unchanged

    @pytest.mark.parametrize("names", [("a b", "a+b", "a_b"), ("a|b", "a__b"), ("a_|b", "a|_b"), ("", "case"),
                                       (".a", "a")])
    def test_distinct_names_give_distinct_files(self, names):
        assert len({ev._slug(n) for n in names}) == len(names)

    def test_ordinary_names_unchanged(self):
        assert ev._slug("sphere|grace_cathedral") == "sphere__grace_cathedral"
        assert ev._slug("ball|001") == "ball__001" and ev._slug("lit") == "lit"


class TestMethods:
    def scene(self, focal=None):
        normals, mask = sphere(32, 12.0)
        sh = natural_lightings(0.7)["grace_cathedral"][None]
        image = (render_sh(normals[None], sh) * mask).clamp(0, 1)
        return Scene("ball|grace", "ball", "grace", image, mask[None], normals[None], sh, sh, focal)

    def test_silhouette_is_perspective_with_a_focal(self):
        scene = self.scene(focal=40.0)
        result = ev.run_method("silhouette", scene)
        assert torch.equal(result.normals, coarse_normals(scene.mask, focal=40.0))
        assert not torch.allclose(result.normals, coarse_normals(scene.mask), atol=1e-3)

    def test_known_lighting_methods_skip_a_case_without_lighting(self):
        scene = self.scene()
        bare = Scene(scene.name, scene.shape, "unknown", scene.image, scene.mask, None, None, None, None)
        assert ev.run_method("classical", bare) is None and ev.run_method("known_lighting", bare) is None
        scores = ev.score_case(bare, ["flat", "classical"])
        assert list(scores.results) == ["flat"] and len(scores.rows) == 1 and scores.rows[0]["median_deg"] is None

    @pytest.mark.parametrize("method, features, when, integrate, known", [
        ("known_lighting", (True, True, True), "always", None, True),
        ("known_lighting_forest", (True, True, True), "never", None, True),
        ("known_lighting_rgb", (True, False, False), "never", None, True),
        ("known_lighting_rgb_silh", (True, True, False), "never", None, True),
        ("known_lighting_rgb_tex", (True, False, True), "never", None, True),
        ("known_lighting_l2", (True, True, True), "never", "l2", True),
        ("known_lighting_l1", (True, True, True), "never", "l1", True),
        ("known_lighting_conv", (True, True, True), "never", "conv", True),
        ("estimated_lighting", (True, True, True), "always", None, False),
        ("estimated_lighting_conv", (True, True, True), "always", "conv", False),
    ])
    def test_what_each_estimate_method_asks_for(self, monkeypatch, method, features, when, integrate, known):
        import sfs_torch.pipeline as pipeline

        calls = []

        def fake(image, mask, **kwargs):
            calls.append(kwargs)
            return pipeline.Estimate(torch.zeros(1, 3, 32, 32) + mask, torch.ones(1, 1, 32, 32), torch.ones(1, 3, 9),
                                     None, mask, {"database": 0.0})

        monkeypatch.setattr(pipeline, "estimate", fake)
        scene = self.scene()
        result = ev.run_method(method, scene)
        cfg = calls[0]["config"]
        f = cfg.features
        assert (f.rgb, f.silhouette, f.texton) == features and cfg.refine.when == when
        assert calls[0]["integrate"] == integrate and (calls[0]["lighting"] is not None) == known
        assert (result.lighting is None) == known  # a given lighting is not scored

    def test_unknown_method(self):
        with pytest.raises(ValueError, match="unknown method 'nope'"):
            ev.run_method("nope", self.scene())

    def test_summarise(self):
        rows = [{"method": "flat", **{k: "" for k in ev.COLUMNS[2:]}, "median_deg": str(v), "time_s": "1"}
                for v in (1.0, 2.0, 10.0)]
        rows.append({"method": "flat", **{k: "" for k in ev.COLUMNS[2:]}, "time_s": "4"})  # no ground truth
        s = ev.summarise(rows, ["flat", "silhouette"])
        assert s["flat"]["cases"] == 4 and s["flat"]["scored"] == 3
        assert s["flat"]["median_deg"] == 2.0 and s["flat"]["mean_median_deg"] == pytest.approx(13 / 3)
        assert s["flat"]["time_s"] == pytest.approx(7 / 4) and s["flat"]["lmse"] is None
        assert s["silhouette"]["cases"] == 0 and s["silhouette"]["median_deg"] is None


class TestConfig:
    @pytest.mark.parametrize("option", sorted(p.stem for p in (CONF / "dataset").glob("*.yaml")))
    def test_every_dataset_composes(self, option):
        cfg = compose_eval([f"dataset={option}"])
        assert cfg.dataset.name == option
        OmegaConf.to_object(cfg)  # validates against the schema

    def test_defaults(self):
        cfg = compose_eval([])
        assert cfg.dataset.name == "synthetic" and cfg.dataset.side == "test"
        assert list(cfg.methods) == list(ev.BASE_METHODS)
        assert cfg.classical.model == "surface" and cfg.classical.normal_weight == 0
        assert not cfg.classical.optimise_lighting

    def test_bad_method_is_caught_before_any_work(self, tmp_path, monkeypatch):
        def never(*args, **kwargs):
            raise AssertionError("work started before the options were checked")

        monkeypatch.setattr(ev, "load_cases", never)
        monkeypatch.setattr(ev, "run_method", never)
        with pytest.raises(ValueError, match="unknown method 'sillhouette'"):
            run_eval([*TINY, "methods=[flat,sillhouette]", f"out={tmp_path / 'out'}"])
        with pytest.raises(FileNotFoundError, match="no such folder"):
            run_eval([*TINY, "dataset=diligent", f"dataset.root={tmp_path / 'nowhere'}", f"out={tmp_path / 'o'}"])
        assert not (tmp_path / "out").exists() and not (tmp_path / "o").exists()


class TestCommandLine:
    # one bad name caught before Hydra starts, one caught in the app
    @pytest.mark.parametrize("args, message", [
        (["dataset=mnist"], "unknown dataset 'mnist'; datasets are synthetic, folder, mit_berkeley, diligent"),
        (["dataset=folder", "dataset.root=.", "methods=[flat,nope]"], "unknown method 'nope'"),
    ])
    def test_bad_input_is_one_line_and_exit_code_2(self, tmp_path, args, message):
        result = run_cli([*args, "out=x"], tmp_path)
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], result.stderr
        assert "Traceback" not in result.stdout + result.stderr
        assert not (tmp_path / "x" / "cases.csv").exists()

    @pytest.mark.parametrize("args, error, message", [
        (["dataset=folder", "dataset.root=missing"], FileNotFoundError, "dataset.root: no such folder 'missing'"),
        (["dataset=folder"], ValueError, "dataset=folder needs dataset.root=<folder>"),
        (["dataset.side=train"], ValueError, "dataset.side must be one of test, validation, spare, got 'train'"),
        (["dataset.side=spare"], ValueError, "dataset.shapes must be a number of shapes on the spare side"),
        (["dataset.shapes=3"], ValueError, r"dataset.shapes: n must be an integer in \[0, 1\] on the test side, got 3"),
        (["dataset.degradation=blur"], ValueError, "dataset.degradation must be one of exact, "),
        (["classical.iterations=-1"], ValueError, "classical.iterations must be an integer >= 0"),
    ])
    def test_other_bad_options(self, tmp_path, monkeypatch, capsys, args, error, message):
        monkeypatch.chdir(tmp_path)
        with pytest.raises(error, match=message.replace("(", r"\(")) as caught:
            run_eval([*TINY, *args, "out=x"])
        # the command turns it into one line on stderr and exit code 2
        with pytest.raises(SystemExit) as exited:
            ev._user_error(caught.value)
        assert exited.value.code == 2
        assert capsys.readouterr().err == f"sfs-torch-eval: error: {caught.value}\n"
        assert not (tmp_path / "x" / "cases.csv").exists()

    def test_spare_side_scores_the_spare_pool_under_tuning_lightings(self, tmp_path):
        from sfs_torch.datasets import scene_shapes, validation_lightings
        from sfs_torch.geometry_db import DatabaseConfig

        run_eval([*TINY, "dataset=synthetic", "dataset.side=spare", "dataset.shapes=2", "dataset.lights=1",
                  "dataset.resolution=32", "methods=[silhouette]", "figures=false", f"out={tmp_path / 'out'}"])
        _, rows = read_csv(tmp_path / "out" / "cases.csv")
        tiny = DatabaseConfig(collection="blobby", n_shapes=12, n_views=4, resolution=64, n_eval_shapes=2)
        light = validation_lightings(1)[0][0]
        assert [row["case"] for row in rows] == [f"{shape.name}|{light}" for shape in scene_shapes(2, "spare", tiny)]

    def test_sweep_writes_a_folder_per_job(self, tmp_path):
        args = ["-m", *TINY, "dataset.shapes=0", "dataset.lights=1", "dataset.sphere=true", "dataset.resolution=32",
                "methods=[flat],[silhouette]", "figures=false", f"out={tmp_path / 'sweep'}"]
        result = run_cli(args, tmp_path)
        assert result.returncode == 0, result.stderr
        methods = []
        for job in ("0", "1"):
            _, rows = read_csv(tmp_path / "sweep" / job / "cases.csv")
            assert len(rows) == 1 and rows[0]["case"] == "sphere|grace_cathedral"
            methods.append(rows[0]["method"])
            report = (tmp_path / "sweep" / job / "report.md").read_text()
            assert f"methods=[{rows[0]['method']}]" in report and f"job {job} of a sweep" in report
        assert methods == ["flat", "silhouette"]
