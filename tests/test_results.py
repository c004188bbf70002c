"""``tools/results.py``, which regenerates docs/RESULTS.md: its ``quick`` preset end to end
(~1-2 min on 2 cores), with loose checks on its numbers, and the page builder on made-up
summaries."""
import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_tool():
    spec = importlib.util.spec_from_file_location("sfs_torch_results_tool", ROOT / "tools" / "results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


results = load_tool()


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """The quick preset, once for the module."""
    out = tmp_path_factory.mktemp("results") / "quick"
    with pytest.MonkeyPatch.context() as mp:
        # the conftest's per-test cache fixture does not reach a module fixture
        mp.setenv("SFS_TORCH_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
        page = results.main(["--preset", "quick", "--out", str(out)])
    summaries = {p.name: json.loads((out / p.name / "summary.json").read_text())
                 for p in results.PRESETS["quick"].parts}
    return {"out": out, "page": page, "text": page.read_text(encoding="utf-8"), "summaries": summaries}


def median(quick, part, method):
    return quick["summaries"][part]["methods"][method]["median_deg"]


class TestQuickPreset:
    def test_the_method_beats_the_prior_and_known_lighting_beats_estimated(self, quick):
        silhouette = median(quick, "ortho", "silhouette")
        estimated = median(quick, "ortho", "estimated_lighting")
        known = median(quick, "ortho", "known_lighting")
        assert estimated < silhouette, (estimated, silhouette)
        assert known < estimated, (known, estimated)
        assert quick["summaries"]["ortho"]["cases"] == 5
        lmse = quick["summaries"]["ortho"]["methods"]["estimated_lighting"]["lmse"]
        assert 0 < lmse < 0.01

    def test_every_part_scored_every_method(self, quick):
        for part in results.PRESETS["quick"].parts:
            methods = re.search(r"methods=\[(.*)\]", part.overrides[-1]).group(1).split(",")
            summary = quick["summaries"][part.name]
            assert list(summary["methods"]) == methods
            for method in methods:
                s = summary["methods"][method]
                assert s["cases"] == s["scored"] == summary["cases"] >= 1, (part.name, method)
                assert 0 <= s["median_deg"] < 60, (part.name, method)

    def test_page(self, quick):
        text, page = quick["text"], quick["page"]
        assert page == quick["out"] / "RESULTS.md"
        assert text.startswith("# Results: the paper's experiments, regenerated\n")
        assert f"python tools/results.py --preset quick --out {quick['out']}" in text
        for line in ("- commit `", "- machine: ", "- date: "):
            assert line in text
        assert "wall time " in text and " cores available" in text
        for heading in ("## Table 1a", "## Table 1b", "## Table 2", "## Table 3", "## Trends", "## Figures",
                        "## The runs"):
            assert heading in text
        # the paper's numbers beside ours, ours as the parts measured them
        row = next(line for line in text.splitlines() if line.startswith("| RGB + Silh + Tex |"))
        forest = quick["summaries"]["features"]["methods"]["known_lighting_forest"]["median_deg"]
        assert row.split("|")[2].strip() == f"{forest:.2f}" and "| 7.09 | 0.069 |" in row
        row = next(line for line in text.splitlines() if line.startswith("| ours ortho |"))
        assert f"{median(quick, 'ortho', 'estimated_lighting'):.2f}" in row and "| 15.6 |" in row
        # every part's command reproduces it alone
        for part in results.PRESETS["quick"].parts:
            assert f"out={quick['out'] / part.name}` |" in text
        # the trends say how many images agree
        assert re.search(r"Table 3, orthographic, synthetic: ours [\d.]+ vs prior [\d.]+ deg \(ours lower on \d of 5", text)

    def test_figures(self, quick):
        links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", quick["text"])
        assert len(links) == 1 + len(results.PRESETS["quick"].parts)
        for link in links:
            path = quick["page"].parent / link
            assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", link

    def test_no_run_rewrites_the_page_from_the_runs(self, quick, monkeypatch):
        def never(*args, **kwargs):
            raise AssertionError("--no-run ran a part")

        monkeypatch.setattr(results, "run_part", never)
        page = results.main(["--preset", "quick", "--out", str(quick["out"]), "--no-run",
                             "--page", str(quick["out"] / "again.md")])
        strip = lambda t: re.sub(r"\n- (machine|date): [^\n]*|python tools/results.py[^\n]*", "", t)  # noqa: E731
        assert strip(page.read_text(encoding="utf-8")) == strip(quick["text"])


def made_up(values):
    """Results whose every part has every method at the given per-method median."""
    summaries, rows = {}, {}
    for part in ("ortho", "features", "persp", "realistic", "realistic_persp"):
        summaries[part] = {"cases": 2, "methods": {m: {"median_deg": v, "nmse": v / 100, "lmse": 0.001, "time_s": 1.0}
                                                   for m, v in values.items()}}
        rows[part] = [{"case": f"s{k}|l", "method": m, "median_deg": str(v + k), "nmse": str(v / 100)}
                      for m, v in values.items() for k in range(2)]
    return results.Results(summaries, rows)


class TestPage:
    def page(self, values):
        res = made_up(values)
        prov = {"commit": "abc", "machine": "m", "load": "0.0", "date": "d"}
        preset = results.PRESETS["full"]
        return results.results_markdown(preset, res, command="python tools/results.py", prov=prov, wall_s=61.0,
                                        invocations=1, part_commands={p.name: "cmd" for p in preset.parts},
                                        part_wall={}, figures={})

    def test_an_order_like_the_papers(self):
        text = self.page({"silhouette": 20.0, "estimated_lighting": 15.0, "known_lighting": 3.0})
        line = next(line for line in text.splitlines() if line.startswith("- Table 3, orthographic, synthetic"))
        assert "ours 15.00 vs prior 20.00 deg (ours lower on 2 of 2 images), the paper's order" in line
        assert "wall time of the parts 1 min 01 s" in text

    def test_an_order_reversed(self):
        text = self.page({"silhouette": 10.0, "estimated_lighting": 15.0, "known_lighting": 3.0})
        line = next(line for line in text.splitlines() if line.startswith("- Table 3, orthographic, synthetic"))
        assert "(ours lower on 0 of 2 images), **the paper's order reversed**" in line

    def test_missing_methods_are_dashes(self):
        text = self.page({"silhouette": 10.0})
        assert "| RGB | – | – | 13.77 | 0.179 |" in text
        assert "- Table 1a, texton features: not measured here" in text
