"""Regenerate ``docs/RESULTS.md``: the paper's experiments (Richter & Roth 2015, Tables 1-3)
run by ``sfs-torch-eval`` on the test side, next to the paper's numbers.

    python tools/results.py                                  # the full run: ~8 min on 2 CPU cores
    python tools/results.py --preset quick --out /tmp/quick  # ~1 min: what tests/test_results.py runs

Each *part* is one ``sfs-torch-eval`` run into ``<out>/<part>`` (``out`` defaults to
``outputs/results/<preset>``); its command is printed into the page, so any table can be
rerun on its own. The page is assembled from the parts' ``summary.json`` and ``cases.csv``,
with one error-map figure per part and an overview chart (``<page folder>/results/``).
Everything runs on the test side (the test-side shapes of the evaluation split, under the
Ramamoorthi-Hanrahan probes): nothing is chosen on it.

``--resume`` continues an interrupted run (``sfs-torch-eval resume=true``: finished
(case, method) rows are kept), and the page then reports the wall time summed over the
invocations. Further arguments are ``sfs-torch-eval`` overrides added to every part, e.g.
``device=cuda`` (they are part of the recorded commands). The options are described in
``docs/evaluation.md`` ("The paper's tables").
"""
from __future__ import annotations

import argparse
import csv
import datetime as _dt
import json
import logging
import os
import platform
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from sfs_torch import short_openmp_waits

short_openmp_waits()  # as sfs-torch-eval does

ROOT = Path(__file__).resolve().parents[1]
log = logging.getLogger("sfs_torch.results")


# ------------------------------------------------------------------------------------------
# Presets: each part is one sfs-torch-eval run


@dataclass(frozen=True)
class Part:
    """One ``sfs-torch-eval`` run: ``name`` is its folder under ``out``."""

    name: str
    title: str
    overrides: Tuple[str, ...]
    headline: str  # the method whose median case is shown in the part's figure


@dataclass(frozen=True)
class Preset:
    name: str
    common: Tuple[str, ...]  # overrides of every part
    parts: Tuple[Part, ...]
    focal: float  # of the perspective parts, pixels
    resolution: int
    description: str


TABLE_1A = ("known_lighting_rgb", "known_lighting_rgb_silh", "known_lighting_rgb_tex", "known_lighting_forest")
TABLE_1B = ("known_lighting_l2", "known_lighting_l1", "known_lighting_conv")


def _methods(*names: str) -> str:
    return f"methods=[{','.join(names)}]"


def _parts(focal: float, *, fewer: Tuple[str, ...] = ()) -> Tuple[Part, ...]:
    """The five runs. Every part scores the same shapes under the same lightings from the same
    views (the first of ``ortho``'s images where ``fewer`` takes fewer shapes): only the camera
    and the image formation differ, so a case ``shape|lighting`` is comparable across parts."""
    persp = f"dataset.focal={focal:g}"
    return (
        Part("ortho", "orthographic, exact image formation (the paper's synthetic setting)",
             (_methods("silhouette", "estimated_lighting", "known_lighting"),), "estimated_lighting"),
        Part("features", "orthographic, exact: the forest alone in known lighting, by features and integrability",
             (*fewer, _methods(*TABLE_1A, *TABLE_1B)), "known_lighting_forest"),
        Part("persp", f"perspective (f = {focal:g} px), exact",
             (*fewer, persp, _methods("silhouette", "estimated_lighting", "known_lighting_forest", "known_lighting_l2")),
             "estimated_lighting"),
        Part("realistic", "orthographic, realistic image formation (shadows, specular, exposure, sensor, 8-bit)",
             (*fewer, "dataset.degradation=all", _methods("silhouette", "estimated_lighting", "known_lighting")),
             "estimated_lighting"),
        Part("realistic_persp", f"perspective (f = {focal:g} px), realistic image formation",
             (*fewer, persp, "dataset.degradation=all", _methods("silhouette", "estimated_lighting")),
             "estimated_lighting"),
    )


PRESETS: Dict[str, Preset] = {
    # The default database's 10 test-side shapes, each under its own R&H probe (shape k under
    # probe k mod 7), 256 px as the README's benchmark: 10 images in every part. ~8 min on 2
    # cores (150 estimate calls, each training a forest; `features`' 70 about 40% of it).
    "full": Preset(
        "full",
        ("dataset=synthetic", "dataset.side=test", "dataset.lights=7", "dataset.lights_per_shape=1"),
        _parts(300.0),
        300.0, 256,
        "the default database's 10 test-side shapes, each under one R&H probe, 256x256 images",
    ),
    # CI-sized (tests/test_results.py, ~1-2 min on 2 cores): procedural blobby shapes (no
    # download), a small database and forest, 128 px; 5 orthographic images, 1 in the others.
    "quick": Preset(
        "quick",
        ("dataset=synthetic", "dataset.side=test", "dataset.lights=5", "dataset.lights_per_shape=1",
         "dataset.resolution=128", "pipeline.database.collection=blobby", "pipeline.database.n_shapes=40",
         "pipeline.database.n_views=8", "pipeline.database.resolution=128", "pipeline.database.n_eval_shapes=10",
         "pipeline.forest.n_trees=4", "pipeline.forest.max_depth=12"),
        _parts(150.0, fewer=("dataset.shapes=1",)),
        150.0, 128,
        "a small blobby database and forest, 128x128 images: a check that the command works, not results",
    ),
}


# ------------------------------------------------------------------------------------------
# The paper's numbers (paper/richter_roth_2015.txt; SPEC "Figures from the paper")

PAPER_1A = {  # Table 1a: MIT objects, natural illuminations, sigma 0.001, known lighting: MAE (deg), nMSE
    "known_lighting_rgb": ("RGB", 13.77, 0.179),
    "known_lighting_rgb_silh": ("RGB + Silh", 10.90, 0.130),
    "known_lighting_rgb_tex": ("RGB + Tex", 7.92, 0.097),
    "known_lighting_forest": ("RGB + Silh + Tex", 7.09, 0.069),
}
PAPER_1B = (  # Table 1b: (label, part, method, MAE, nMSE, run time s)
    ("no integrability", "features", "known_lighting_forest", 7.09, 0.069, 89.0),
    ("L2, orthographic", "features", "known_lighting_l2", 7.33, 0.057, 98.5),
    ("L2, orthographic, conv.", "features", "known_lighting_conv", 6.46, 0.056, 1172.8),
    ("L1, orthographic", "features", "known_lighting_l1", 7.34, 0.058, 98.0),
    ("L2, perspective", "persp", "known_lighting_l2", 7.42, 0.059, 97.2),
)
# Table 3 (MAE deg, lMSE) for synthetic / real illumination
PAPER_3 = {
    ("silhouette", "ortho"): ((25.4, None), (25.4, None)),
    ("silhouette", "persp"): ((25.0, None), (25.0, None)),
    ("estimated_lighting", "ortho"): ((15.6, 0.0013), (23.8, 0.0021)),
    ("estimated_lighting", "persp"): ((14.0, 0.0010), (23.1, 0.0018)),
}


# ------------------------------------------------------------------------------------------
# Running


def _compose(overrides: Sequence[str]):
    from hydra import compose, initialize_config_module

    import sfs_torch.evaluate  # noqa: F401  (registers the eval schema)

    with initialize_config_module(config_module="sfs_torch.conf", version_base="1.3"):
        return compose(config_name="eval", overrides=list(overrides))


def part_overrides(preset: Preset, part: Part, extra: Sequence[str], out: Path) -> List[str]:
    """The ``sfs-torch-eval`` overrides of one part (without the tool's progress/resume flags)."""
    return [*preset.common, *part.overrides, *extra, f"out={out / part.name}"]


def _display_path(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def run_part(preset: Preset, part: Part, extra: Sequence[str], out: Path, *, resume: bool,
             progress: bool) -> Dict[str, Any]:
    """Run one part with :func:`sfs_torch.evaluate.evaluate`; returns its summary."""
    from sfs_torch.evaluate import evaluate

    overrides = part_overrides(preset, part, extra, out)
    shown = [*overrides[:-1], f"out={_display_path(out / part.name)}"]
    cfg = _compose([*overrides, f"resume={str(resume).lower()}", f"progress={str(progress).lower()}"])
    return evaluate(cfg, command="sfs-torch-eval " + " ".join(shlex.quote(a) for a in shown))


def read_cases(path: Path) -> List[Dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


# ------------------------------------------------------------------------------------------
# Provenance


def _git(*args: str) -> Optional[str]:
    try:
        result = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip() if result.returncode == 0 else None


def provenance() -> Dict[str, str]:
    """Commit, machine and date of this run (read-only git queries)."""
    import torch

    commit = _git("rev-parse", "--short=10", "HEAD") or "unknown (not a git checkout)"
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    if dirty:
        commit += " with uncommitted changes"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    return {
        "commit": commit,
        "machine": f"{cpu}, {cores} cores available, {torch.get_num_threads()} torch threads, "
                   f"{platform.system()} {platform.release()}, Python {platform.python_version()}, torch {torch.__version__}",
        "load": load,
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


# ------------------------------------------------------------------------------------------
# The page


def _f(value: Optional[float], spec: str = ".2f") -> str:
    return "–" if value is None else format(value, spec)


def _images(count: int) -> str:
    return f"{count} image{'' if count == 1 else 's'}"


Key = Tuple[str, str]  # (part, method)


class Results:
    """The parts' summaries and rows, looked up by (part, method)."""

    def __init__(self, summaries: Mapping[str, Mapping[str, Any]], rows: Mapping[str, List[Dict[str, str]]]):
        self.summaries = summaries
        self.rows = rows

    def get(self, part: str, method: str, key: str = "median_deg") -> Optional[float]:
        s = self.summaries.get(part, {}).get("methods", {}).get(method)
        return None if s is None else s.get(key)

    def cases(self, part: str) -> int:
        return int(self.summaries.get(part, {}).get("cases", 0))

    def per_case(self, part: str, method: str, key: str = "median_deg") -> Dict[str, float]:
        return {r["case"]: float(r[key]) for r in self.rows.get(part, [])
                if r["method"] == method and r[key] not in ("", None)}

    def wins(self, a: Key, b: Key, key: str = "median_deg") -> Tuple[int, int]:
        """On how many of the images both have (the same ``shape|lighting``, also across
        parts) ``a`` has the lower error than ``b``, and how many there are."""
        x, y = self.per_case(*a, key), self.per_case(*b, key)
        common = sorted(set(x) & set(y))
        return sum(x[c] < y[c] for c in common), len(common)

    def paired_difference(self, a: Key, b: Key, key: str = "median_deg") -> Optional[float]:
        """The median over the images both have of ``a``'s error minus ``b``'s."""
        x, y = self.per_case(*a, key), self.per_case(*b, key)
        common = sorted(set(x) & set(y))
        return statistics.median(x[c] - y[c] for c in common) if common else None


def _compare(res: Results, what: str, a: Key, b: Key, paper: Tuple[float, float], names: Tuple[str, str],
             note: str = "", key: str = "median_deg") -> str:
    """One line: is ``a``'s error (MAE, or ``key``) below ``b``'s here, and in the paper?"""
    ours_a, ours_b = res.get(*a, key), res.get(*b, key)
    pa, pb = paper
    first, second = names
    unit, spec, label = (" deg", ".2f", "") if key == "median_deg" else ("", ".3f", f"{key.replace('nmse', 'nMSE')} ")
    paper_says = f"{label}{first} {pa:{spec}} vs {second} {pb:{spec}}{unit}"
    if ours_a is None or ours_b is None:
        return f"- {what}: not measured here (paper: {paper_says})."
    wins, total = res.wins(a, b, key)
    same = (ours_a < ours_b) == (pa < pb)
    verdict = "the paper's order" if same else "**the paper's order reversed**"
    line = (f"- {what}: {label}{first} {ours_a:{spec}} vs {second} {ours_b:{spec}}{unit} ({first} lower on {wins} "
            f"of {total} images), {verdict} (paper: {paper_says}).")
    paired = res.paired_difference(a, b, key)
    if paired is not None and paired != 0 and (paired < 0) != (ours_a < ours_b):
        line += (f" Image by image the order is the other way ({first} minus {second}: median {paired:+{spec}}"
                 f"{unit}), so the medians' order is not a robust finding on these images.")
    return line + (f" {note}" if note else "")


def results_markdown(preset: Preset, res: Results, *, command: str, prov: Mapping[str, str], wall_s: float,
                     invocations: int, part_commands: Mapping[str, str], part_wall: Mapping[str, float],
                     figures: Mapping[str, str]) -> str:
    """The Markdown page from the parts' results."""
    g = res.get
    n = {p.name: res.cases(p.name) for p in preset.parts}
    minutes, seconds = divmod(int(round(wall_s)), 60)
    wall = f"{minutes} min {seconds:02d} s" + (f", summed over up to {invocations} invocations per part "
                                              "(`--resume`)" if invocations > 1 else "")
    lines = [
        "# Results: the paper's experiments, regenerated",
        "",
        "This page is written by one command (`tools/results.py`; edit that, not this page):",
        "",
        "```",
        command,
        "```",
        "",
        f"- preset `{preset.name}`: {preset.description};",
        f"- commit `{prov['commit']}`;",
        f"- machine: {prov['machine']}; load average {prov['load']} (1, 5, 15 min) as the run ended (other "
        "work may have shared the cores: it lengthens the times and changes no score);",
        f"- date: {prov['date']}, as the run ended; wall time of the parts {wall}.",
        "",
        "All images are of the **test side**: shapes of the evaluation split that are never trained on and "
        "never tuned on, under Ramamoorthi-Hanrahan's light probes ([Evaluation scenes](datasets.md)); no "
        "option was chosen on them. Every part renders the same shapes under the same lightings from the same "
        "views, so an image `shape|lighting` differs between parts only by the camera and the image "
        "formation. **MAE** is, as in the paper, an image's median angular error; the tables give the median "
        "of it over the images (the paper does not say how it aggregates images). nMSE and lMSE are means over "
        "the images ([Conventions](conventions.md)). The paper's numbers are on its data (MIT intrinsic "
        "objects rendered under natural illuminations, and photographs for its real columns) and its hardware: "
        "the trends compare, the digits do not. The commands of the parts are at the end.",
        "",
        "## Table 1a: features (known lighting, the forest alone)",
        "",
        f"Part `features`, {_images(n['features'])} (the first of part `ortho`'s): the regression forest without "
        "photometric refinement or integrability, trained for the image's true lighting, by feature set.",
        "",
        "| features | MAE (deg) | nMSE | paper MAE | paper nMSE |",
        "|---|---:|---:|---:|---:|",
    ]
    for method, (label, mae, nmse) in PAPER_1A.items():
        lines.append(f"| {label} | {_f(g('features', method))} | {_f(g('features', method, 'nmse'), '.3f')} | "
                     f"{mae:.2f} | {nmse:.3f} |")
    lines += [
        "",
        "## Table 1b: integrability (known lighting, the forest alone)",
        "",
        f"The images of Table 1a, except the perspective row: part `persp`'s {_images(n['persp'])}, rendered with "
        f"f = {preset.focal:g} px, on which the forest alone scores {_f(g('persp', 'known_lighting_forest'))} deg "
        f"(nMSE {_f(g('persp', 'known_lighting_forest', 'nmse'), '.3f')}). Time per image includes the forest's "
        "training, as the paper's run time does.",
        "",
        "| method | MAE (deg) | nMSE | time per image (s) | paper MAE | paper nMSE | paper run time (s) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, part, method, mae, nmse, secs in PAPER_1B:
        lines.append(f"| {label} | {_f(g(part, method))} | {_f(g(part, method, 'nmse'), '.3f')} | "
                     f"{_f(g(part, method, 'time_s'), '.1f')} | {mae:.2f} | {nmse:.3f} | {secs:.1f} |")
    lines += [
        "",
        "## Table 2: known against estimated lighting",
        "",
        "`known_lighting` is our default with a known lighting: the forest, then photometric refinement (an "
        "addition to the paper; the forest alone is Table 1a's last row). `estimated_lighting` is the whole "
        "method in unknown lighting, whose lighting our default then refines jointly with an integrable surface "
        "(also an addition); lMSE scores that lighting. The paper's synthetic row is its Table 2a (Barron "
        "& Malik's re-rendered MIT images, nMSE only), its real row Table 2b's natural-illumination columns "
        "(photographs). Our realistic images add cast shadows, a specular lobe, exposure and white-balance "
        "errors, shot noise and 8-bit sRGB files to the same scenes ([Evaluation scenes](datasets.md)): a "
        "stand-in for photographs, not photographs.",
        "",
        "| images | MAE known (deg) | MAE estimated (deg) | nMSE known | nMSE estimated | lMSE | paper MAE known "
        "| paper MAE estimated | paper nMSE known | paper nMSE estimated | paper lMSE |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for part, label, paper in (("ortho", "synthetic", "– | – | 0.034 | 0.196 | 0.013"),
                               ("realistic", "realistic", "20.51 | 23.07 | – | – | 0.002")):
        lines.append(
            f"| {label} (part `{part}`, {_images(n[part])}) | {_f(g(part, 'known_lighting'))} | "
            f"{_f(g(part, 'estimated_lighting'))} | {_f(g(part, 'known_lighting', 'nmse'), '.3f')} | "
            f"{_f(g(part, 'estimated_lighting', 'nmse'), '.3f')} | {_f(g(part, 'estimated_lighting', 'lmse'), '.5f')} "
            f"| {paper} |")
    lines += [
        "",
        "## Table 3: the silhouette prior against the method, orthographic against perspective",
        "",
        f"Unknown lighting. Baseline: Eq. 10's coarse normals from the mask alone (`silhouette`). Perspective "
        f"rows: images rendered with f = {preset.focal:g} px, the focal length given to both methods. Synthetic: "
        "exact image formation; realistic: as in Table 2 (the paper: photographs). Images: "
        + ", ".join(f"`{p}` {n[p]}" for p in ("ortho", "persp", "realistic", "realistic_persp")) + ".",
        "",
        "| method | synthetic MAE (deg) | synthetic lMSE | realistic MAE (deg) | realistic lMSE | paper synthetic "
        "MAE | paper synthetic lMSE | paper real MAE | paper real lMSE |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    columns = {"ortho": ("ortho", "realistic"), "persp": ("persp", "realistic_persp")}
    for method, label in (("silhouette", "baseline"), ("estimated_lighting", "ours")):
        for camera, (synthetic, realistic) in columns.items():
            (ps, psl), (pr, prl) = PAPER_3[(method, camera)]
            lines.append(
                f"| {label} {camera} | {_f(g(synthetic, method))} | {_f(g(synthetic, method, 'lmse'), '.5f')} | "
                f"{_f(g(realistic, method))} | {_f(g(realistic, method, 'lmse'), '.5f')} | {ps:.1f} | "
                f"{_f(psl, '.4f')} | {pr:.1f} | {_f(prl, '.4f')} |")
    lines += ["", "## Trends: ours against the paper's", "",
              "Each line compares two rows above, here and in the paper, with the number of images on which the "
              "first is the better (images are matched by `shape|lighting`, also across parts). Where the order "
              "differs from the paper's, the measurements that bear on it follow.", ""]
    lines += _trends(res, preset)
    if figures:
        lines += ["", "## Figures", "", "Our MAE next to the paper's, for the rows of Tables 1a, 1b and 3:", "",
                  f"![ours against the paper]({figures['overview']})", ""]
        for p in preset.parts:
            if p.name in figures:
                lines += [f"Part `{p.name}` ({p.title}): the image with the median `{p.headline}` error, and each "
                          "method's angular error (0-45 deg):", "", f"![{p.name}]({figures[p.name]})", ""]
    lines += ["", "## The runs", "",
              "Each part is one `sfs-torch-eval` run ([Evaluating](evaluation.md)): rerun one to check its table. "
              "Its folder holds `cases.csv` (a row per image and method), `summary.json`, `report.md` and every "
              "image's error maps.", "",
              "| part | images | wall time (s) | command |", "|---|---:|---:|---|"]
    for p in preset.parts:
        lines.append(f"| `{p.name}` | {n[p.name]} | {_f(part_wall.get(p.name), '.0f')} | `{part_commands[p.name]}` |")
    return "\n".join(lines) + "\n"


def _trends(res: Results, preset: Preset) -> List[str]:
    g = res.get
    f = "features"
    out = [
        _compare(res, "Table 1a, silhouette features", (f, "known_lighting_rgb_silh"), (f, "known_lighting_rgb"),
                 (10.90, 13.77), ("RGB + Silh", "RGB")),
        _compare(res, "Table 1a, texton features", (f, "known_lighting_rgb_tex"), (f, "known_lighting_rgb"),
                 (7.92, 13.77), ("RGB + Tex", "RGB")),
        _compare(res, "Table 1a, all features against textons alone", (f, "known_lighting_forest"),
                 (f, "known_lighting_rgb_tex"), (7.09, 7.92), ("all", "RGB + Tex")),
    ]
    ours_all, ours_rgb = g(f, "known_lighting_forest"), g(f, "known_lighting_rgb")
    if ours_all and ours_rgb:
        out.append(f"- Table 1a, level: RGB alone / all features = {ours_rgb / ours_all:.2f} here (paper: 13.77 / "
                   "7.09 = 1.94). Our exact test images are shaded by the same 9-term SH model, with the same noise "
                   "(sigma 0.001), as the forest's training patches: with the lighting known, only the shapes "
                   "differ from the training data. That may be why every known-lighting error here is far below "
                   "the paper's; what the paper's test renderings shared with its training data we cannot check.")
    def nmse_note(a: Key, b: Key, paper: Tuple[float, float]) -> str:
        x, y = g(*a, "nmse"), g(*b, "nmse")
        if x is None or y is None:
            return ""
        return f"In nMSE: {x:.3f} vs {y:.3f} (paper: {paper[0]:.3f} vs {paper[1]:.3f})."

    for method, label, paper, paper_nmse in (("known_lighting_l2", "L2", 7.33, 0.057),
                                             ("known_lighting_l1", "L1", 7.34, 0.058),
                                             ("known_lighting_conv", "convex combination", 6.46, 0.056)):
        a, b = (f, method), (f, "known_lighting_forest")
        out.append(_compare(res, f"Table 1b, {label} integrability", a, b, (paper, 7.09), (label, "none"),
                            nmse_note(a, b, (paper_nmse, 0.069))))
    a, b = (f, "known_lighting_conv"), (f, "known_lighting_l2")
    out.append(_compare(res, "Table 1b, convex combination against L2", a, b, (6.46, 7.33), ("conv", "L2"),
                        nmse_note(a, b, (0.056, 0.057))))
    a, b = ("persp", "known_lighting_l2"), ("persp", "known_lighting_forest")
    out.append(_compare(res, "Table 1b, L2 under perspective (part `persp`)", a, b, (7.42, 7.09), ("L2", "none"),
                        nmse_note(a, b, (0.059, 0.069))))
    t_none, t_conv = g(f, "known_lighting_forest", "time_s"), g(f, "known_lighting_conv", "time_s")
    if t_none and t_conv:
        out.append(f"- Table 1b, run time: the convex combination takes {t_conv / t_none:.2f}x the forest alone's "
                   "time here (paper: 1172.8 / 89.0 = 13.2x); our solver (`integrate_convex`: projected-gradient steps "
                   "on per-pixel convex weights of a few leaf samples, each a warm-started L2 solve) is not the "
                   "paper's.")
    out.append(_compare(res, "Table 2, synthetic", ("ortho", "known_lighting"), ("ortho", "estimated_lighting"),
                        (0.034, 0.196), ("known", "estimated"), key="nmse"))
    out.append(_compare(res, "Table 2, synthetic, MAE", ("ortho", "known_lighting"), ("ortho", "estimated_lighting"),
                        (7.09, 15.6), ("known", "estimated"),
                        "(The paper's pair: Table 1a's known-lighting 7.09 and Table 3's 15.6, on other images.)"))
    known_exact, known_real = g("ortho", "known_lighting"), g("realistic", "known_lighting")
    note = ""
    if known_exact is not None and known_real is not None:
        note = (f"The realistic formation raises the known-lighting error from {known_exact:.2f} to "
                f"{known_real:.2f} deg.")
    out.append(_compare(res, "Table 2, realistic", ("realistic", "known_lighting"),
                        ("realistic", "estimated_lighting"), (20.51, 23.07), ("known", "estimated"), note))
    for camera, synthetic, realistic in (("orthographic", "ortho", "realistic"), ("perspective", "persp", "realistic_persp")):
        key = "ortho" if synthetic == "ortho" else "persp"
        for part, column, index in ((synthetic, "synthetic", 0), (realistic, "realistic", 1)):
            out.append(_compare(res, f"Table 3, {camera}, {column}", (part, "estimated_lighting"),
                                (part, "silhouette"), (PAPER_3[("estimated_lighting", key)][index][0],
                                                       PAPER_3[("silhouette", key)][index][0]),
                                ("ours", "prior")))
    for column, ortho, persp, index in (("synthetic", "ortho", "persp", 0), ("realistic", "realistic", "realistic_persp", 1)):
        prior_o, prior_p = g(ortho, "silhouette"), g(persp, "silhouette")
        ours_o, ours_p = g(ortho, "estimated_lighting"), g(persp, "estimated_lighting")
        note = ""
        if None not in (prior_o, prior_p, ours_o, ours_p):
            note = (f"The perspective images are other images of the same scenes: on them the prior goes from "
                    f"{prior_o:.2f} to {prior_p:.2f} deg, and the method's margin over the prior from "
                    f"{prior_o - ours_o:+.2f} to {prior_p - ours_p:+.2f} deg (paper: {25.4 - PAPER_3[('estimated_lighting', 'ortho')][index][0]:+.1f} "
                    f"to {25.0 - PAPER_3[('estimated_lighting', 'persp')][index][0]:+.1f}).")
        out.append(_compare(res, f"Table 3, {column}, perspective against orthographic", (persp, "estimated_lighting"),
                            (ortho, "estimated_lighting"), (PAPER_3[("estimated_lighting", "persp")][index][0],
                                                            PAPER_3[("estimated_lighting", "ortho")][index][0]),
                            ("perspective", "orthographic"), note))
    out.append(_compare(res, "Table 3, synthetic against realistic (orthographic)", ("ortho", "estimated_lighting"),
                        ("realistic", "estimated_lighting"), (15.6, 23.8), ("synthetic", "realistic")))
    sil = g("ortho", "silhouette")
    if sil is not None:
        out.append(f"- Level: the silhouette prior scores {sil:.2f} deg on our orthographic test images (paper: "
                   "25.4 on its objects). The prior's error depends on the shapes only, so the method's margin over "
                   "it, not its absolute error, is what compares with the paper.")
    return out


# ------------------------------------------------------------------------------------------
# Figures


def _representative(rows: List[Dict[str, str]], method: str) -> Optional[str]:
    """The case whose ``method`` median error is the median over the part's cases."""
    scored = sorted((float(r["median_deg"]), r["case"]) for r in rows if r["method"] == method and r["median_deg"])
    if not scored:
        return None
    return scored[(len(scored) - 1) // 2][1]


def copy_figures(preset: Preset, res: Results, out: Path, figures_dir: Path, page: Path) -> Dict[str, str]:
    """One error-map figure per part and the overview chart into ``figures_dir``; returns
    part -> link relative to the page."""
    from sfs_torch.evaluate import _slug

    figures_dir.mkdir(parents=True, exist_ok=True)
    links = {}
    for part in preset.parts:
        case = _representative(res.rows.get(part.name, []), part.headline)
        if case is None:
            continue
        folder = out / part.name / "figures"
        source = folder / f"{_slug(case)}.png"
        if not source.is_file():  # a resumed run that added methods writes <case>.<methods>.png
            candidates = sorted(folder.glob(f"{_slug(case)}.*.png"))
            if not candidates:
                continue
            source = candidates[-1]
        target = figures_dir / f"{part.name}.png"
        shutil.copyfile(source, target)
        links[part.name] = os.path.relpath(target, page.parent)
    target = figures_dir / "overview.png"
    overview_figure(res, target)
    links["overview"] = os.path.relpath(target, page.parent)
    return links


def overview_figure(res: Results, path: Path) -> None:
    """Grouped bars: our MAE next to the paper's, for Tables 1a, 1b and 3."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [
        ("Table 1a: features (known lighting)",
         [(label, res.get("features", m), paper) for m, (label, paper, _) in PAPER_1A.items()]),
        ("Table 1b: integrability (known lighting)",
         [(label.replace(", orthographic", "").replace("no integrability", "none"), res.get(part, m), paper)
          for label, part, m, paper, _, _ in PAPER_1B]),
        ("Table 3: unknown lighting",
         [(f"{'prior' if m == 'silhouette' else 'ours'} {cam}, {col}", res.get(part, m), PAPER_3[(m, cam)][i][0])
          for col, i, parts in (("synthetic", 0, {"ortho": "ortho", "persp": "persp"}),
                                ("realistic", 1, {"ortho": "realistic", "persp": "realistic_persp"}))
          for m in ("silhouette", "estimated_lighting") for cam, part in parts.items()]),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained",
                             gridspec_kw={"width_ratios": [4, 5, 8]})
    for ax, (title, bars) in zip(axes, groups):
        x = range(len(bars))
        ours = [float("nan") if b[1] is None else b[1] for b in bars]
        ax.bar([i - 0.2 for i in x], ours, 0.4, label="ours", color="#3b6ea8")
        ax.bar([i + 0.2 for i in x], [b[2] for b in bars], 0.4, label="paper", color="#c8c8c8")
        ax.set_xticks(list(x), [b[0] for b in bars], fontsize=8, rotation=30, ha="right", rotation_mode="anchor")
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("MAE (deg)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------------------
# The command


def _wall_file(out: Path) -> Path:
    return out / "wall.json"


def _read_wall(out: Path) -> Dict[str, Dict[str, float]]:
    """Per part: the wall seconds of its runs into ``out`` and how many there were; and the
    provenance of the last invocation that ran a part."""
    path = _wall_file(out)
    data = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    wall = {"seconds": dict(data.get("seconds", {})), "invocations": dict(data.get("invocations", {}))}
    if "provenance" in data:
        wall["provenance"] = dict(data["provenance"])
    return wall


def _write_wall(out: Path, data: Mapping[str, Any]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    _wall_file(out).write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def _terminate(signum, frame):  # a killed run (SIGTERM, e.g. a timeout) still records its wall time
    raise SystemExit(128 + signum)


def main(argv: Optional[Sequence[str]] = None) -> Path:
    """Run every part of a preset and write the page; returns the page's path."""
    parser = argparse.ArgumentParser(prog="python tools/results.py", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="full")
    parser.add_argument("--out", type=Path, help="folder of the parts' runs (default outputs/results/<preset>)")
    parser.add_argument("--page", type=Path,
                        help="the Markdown page (default docs/RESULTS.md for full, <out>/RESULTS.md otherwise); "
                             "its figures go to <page folder>/results/")
    parser.add_argument("--resume", action="store_true", help="keep the rows of an interrupted run into --out")
    parser.add_argument("--parts", help="comma-separated parts to run (default all); the page needs all of them")
    parser.add_argument("--no-run", action="store_true", help="run nothing: write the page from the runs in --out")
    parser.add_argument("overrides", nargs="*", help="sfs-torch-eval overrides added to every part")
    args = parser.parse_args(argv)
    preset = PRESETS[args.preset]
    out = args.out or Path("outputs") / "results" / preset.name
    page = args.page or (ROOT / "docs" / "RESULTS.md" if preset.name == "full" else out / "RESULTS.md")
    wanted = [p.name for p in preset.parts] if not args.parts else args.parts.split(",")
    if args.no_run:
        wanted = []
    unknown = [p for p in wanted if p not in {q.name for q in preset.parts}]
    if unknown:
        parser.error(f"unknown part {unknown[0]!r}; parts are {', '.join(p.name for p in preset.parts)}")
    for override in args.overrides:
        if override.split("=", 1)[0].lstrip("+~") in ("out", "resume", "progress"):
            parser.error(f"{override}: set by the tool (use --out, --resume)")

    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    # the command that regenerates the page: --resume, --parts and --no-run only split the work
    canonical = [*(["--preset", preset.name] if preset.name != "full" else []),
                 *(["--out", str(args.out)] if args.out else []), *(["--page", str(args.page)] if args.page else []),
                 *args.overrides]
    command = " ".join(["python tools/results.py", *(shlex.quote(a) for a in canonical)])
    progress = sys.stderr.isatty()
    wall = _read_wall(out)
    handler = signal.signal(signal.SIGTERM, _terminate)
    try:
        for part in preset.parts:
            if part.name not in wanted:
                continue
            log.info("part %s: %s", part.name, part.title)
            part_start = time.perf_counter()
            try:
                run_part(preset, part, args.overrides, out, resume=args.resume, progress=progress)
            finally:
                # a resumed part adds its time to the earlier runs'; a fresh one starts over
                elapsed = time.perf_counter() - part_start
                keep = args.resume and part.name in wall["seconds"]
                wall["seconds"][part.name] = (wall["seconds"][part.name] if keep else 0.0) + elapsed
                wall["invocations"][part.name] = (wall["invocations"][part.name] if keep else 0) + 1
                _write_wall(out, wall)
    finally:
        signal.signal(signal.SIGTERM, handler)
    # the commit, machine and date of the runs: of this invocation when it ran a part, else
    # (--no-run) of the last one that did
    prov = provenance() if wanted or "provenance" not in wall else wall["provenance"]
    wall["provenance"] = prov
    _write_wall(out, wall)
    missing = [p.name for p in preset.parts if not (out / p.name / "summary.json").is_file()]
    if missing:
        log.info("parts %s not run yet: the page is not written (run without --parts, or with --resume)",
                 ", ".join(missing))
        return page
    summaries = {p.name: json.loads((out / p.name / "summary.json").read_text(encoding="utf-8")) for p in preset.parts}
    rows = {p.name: read_cases(out / p.name / "cases.csv") for p in preset.parts}
    res = Results(summaries, rows)
    commands = {p.name: "sfs-torch-eval " + " ".join(shlex.quote(a) for a in [
        *part_overrides(preset, p, args.overrides, out)[:-1], f"out={_display_path(out / p.name)}"]) for p in preset.parts}
    page.parent.mkdir(parents=True, exist_ok=True)
    figures = copy_figures(preset, res, out, page.parent / "results", page)
    total = sum(wall["seconds"].get(p.name, 0.0) for p in preset.parts)
    text = results_markdown(preset, res, command=command, prov=prov, wall_s=total,
                            invocations=max(int(wall["invocations"].get(p.name, 1)) for p in preset.parts),
                            part_commands=commands, part_wall=wall["seconds"], figures=figures)
    page.write_text(text, encoding="utf-8")
    log.info("wrote %s (the parts' wall time: %.0f s)", page, total)
    return page


if __name__ == "__main__":
    main()
