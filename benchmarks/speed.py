"""Whole-call speed of ``sfs_torch.estimate`` against another checkout, side by side in one run.

Both source trees score the same test-side images (generated once, by this checkout) in
their own subprocesses, alternately (this tree, the baseline, this tree, ...), so machine
load shared by both shows in both columns. Each pass times an estimated-lighting call and
a known-lighting call per image (the database is loaded before the clock starts) and
records the per-stage times the estimate reports and each call's median angular error. A
first tiny forest fit in each process, timed apart, takes the process's one-off costs
(loading the forest's compiled CPU loops) out of the calls.

    git worktree add /tmp/base 578b209          # e.g. the commit before the speed work
    python benchmarks/speed.py --baseline /tmp/base \\
        --config '{"refine": {"when": "never"}, "keep_prior": false, "training": {"noise_from_image": false}}'

``--config`` is this tree's config (a JSON dict of overrides; stages the baseline lacks can be
switched off through it, so that both run the same stages), ``--baseline-config`` the
baseline's (its own key names). The table gives, per call kind, the median seconds of each
tree, their ratio (this / baseline) and the median errors; ``--out`` gets the JSON.
``--focal 300`` times perspective calls (images rendered and estimated with that focal length).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sfs_torch import short_openmp_waits

short_openmp_waits()  # as the sfs-torch command does

ROOT = Path(__file__).resolve().parents[1]


def _worker(tree: Path, scenes_path: Path, config: dict) -> None:
    """Time both call kinds on every scene with the package of ``tree``; JSON lines on stdout."""
    sys.path.insert(0, str(tree))
    import torch

    import sfs_torch
    from sfs_torch.forest import VMFForest
    from sfs_torch.geometry_db import DatabaseConfig, load_database
    from sfs_torch.metrics import normal_metrics

    assert Path(sfs_torch.__file__).resolve().is_relative_to(tree.resolve()), sfs_torch.__file__
    load_database(DatabaseConfig(), progress=False)
    # one-off costs of a process, outside the calls' clocks: a first fit loads (or compiles) the
    # forest's compiled CPU loops, where the tree has them
    start = time.perf_counter()
    VMFForest(n_trees=1, max_depth=2, min_samples_leaf=1).fit(torch.rand(64, 3), torch.eye(3).repeat(22, 1)[:64])
    print(json.dumps({"warm_up": time.perf_counter() - start}), flush=True)
    for scene in torch.load(scenes_path):
        for kind in ("estimated", "known"):
            start = time.perf_counter()
            est = sfs_torch.estimate(scene["image"], scene["mask"], lighting=scene["lighting"] if kind == "known" else None,
                                     focal=scene["focal"], config=config, progress=False)
            seconds = time.perf_counter() - start
            error = float(normal_metrics(est.normals, scene["normals"], scene["mask"]).median[0])
            print(json.dumps({"case": scene["name"], "kind": kind, "seconds": seconds, "error": error,
                              "stages": {k: v for k, v in est.timings.items() if k != "database"}}), flush=True)


def _scenes(n_shapes: int, n_lights: int, resolution: int, focal: float | None, path: Path) -> None:
    import torch

    from sfs_torch.datasets import evaluation_lightings, scene_shapes, synthetic_scenes
    from sfs_torch.geometry_db import DatabaseConfig

    shapes = scene_shapes(n_shapes, "test", DatabaseConfig())
    scenes = [{"name": f"{s.shape}|{s.lighting_name}", "image": s.image, "mask": s.mask, "normals": s.normals,
               "lighting": s.lighting, "focal": focal}
              for s in synthetic_scenes(shapes, evaluation_lightings(n_lights), resolution=resolution, focal=focal,
                                        lights_per_shape=1)]
    torch.save(scenes, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", type=Path, required=True, help="the other checkout's root")
    parser.add_argument("--config", type=json.loads, default={}, help="this tree's overrides (JSON)")
    parser.add_argument("--baseline-config", type=json.loads, default=None, help="the baseline's (default: --config)")
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--focal", type=float, default=None, help="a perspective camera's focal length in pixels")
    parser.add_argument("--passes", type=int, default=2, help="passes of each tree, alternated")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "speed.json")
    parser.add_argument("--worker", nargs=3, metavar=("TREE", "SCENES", "CONFIG"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        tree, scenes, config = args.worker
        _worker(Path(tree), Path(scenes), json.loads(config))
        return
    if not (args.baseline / "sfs_torch" / "__init__.py").exists():
        parser.error(f"--baseline {args.baseline} holds no sfs_torch package")
    trees = {"this": (ROOT, args.config), "baseline": (args.baseline, args.baseline_config or args.config)}
    rows = []
    warm_ups = {name: [] for name in trees}
    with tempfile.TemporaryDirectory() as tmp:
        scenes = Path(tmp) / "scenes.pt"
        _scenes(args.shapes, args.lights, args.resolution, args.focal, scenes)
        for p in range(args.passes):
            for name, (tree, config) in trees.items():
                # run from the tree's own root: the editable install would otherwise be imported
                out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--baseline", str(args.baseline),
                                      "--worker", str(tree), str(scenes), json.dumps(config)],
                                     cwd=tree, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(tree)})
                if out.returncode:
                    sys.exit(f"{name} tree failed:\n{out.stderr[-3000:]}")
                for line in out.stdout.splitlines():
                    if line.startswith("{"):
                        record = json.loads(line)
                        if "warm_up" in record:
                            warm_ups[name].append(record["warm_up"])
                        else:
                            rows.append({"tree": name, "pass": p, **record})
                print(f"pass {p} {name}: done", flush=True)
    summary = {}
    print(f"\n{'call':<11}{'this s':>9}{'baseline s':>12}{'ratio':>8}{'this deg':>10}{'baseline deg':>14}")
    for kind in ("estimated", "known"):
        med = {t: statistics.median(r["seconds"] for r in rows if r["tree"] == t and r["kind"] == kind) for t in trees}
        err = {t: statistics.median(r["error"] for r in rows if r["tree"] == t and r["kind"] == kind and r["pass"] == 0)
               for t in trees}
        stages = {t: {s: statistics.median(r["stages"].get(s, 0.0) for r in rows if r["tree"] == t and r["kind"] == kind)
                      for s in sorted({s for r in rows if r["tree"] == t and r["kind"] == kind for s in r["stages"]})}
                  for t in trees}
        summary[kind] = {"seconds": med, "ratio": med["this"] / med["baseline"], "median_error_deg": err, "stages": stages}
        print(f"{kind:<11}{med['this']:9.2f}{med['baseline']:12.2f}{med['this'] / med['baseline']:8.2f}"
              f"{err['this']:10.2f}{err['baseline']:14.2f}")
    for kind in ("estimated", "known"):
        print(f"\nper stage, {kind} lighting (median s): this | baseline")
        st = summary[kind]["stages"]
        for s in sorted(set(st["this"]) | set(st["baseline"])):
            print(f"  {s:<30}{st['this'].get(s, float('nan')):8.2f} | {st['baseline'].get(s, float('nan')):8.2f}")
    print(f"\none-off per process (a first forest fit before the calls, median s): this "
          f"{statistics.median(warm_ups['this']):.2f} | baseline {statistics.median(warm_ups['baseline']):.2f}")
    load = os.getloadavg()
    summary.update({"warm_up_seconds": warm_ups, "images": args.shapes, "passes": args.passes, "resolution": args.resolution,
                    "focal": args.focal,
                    "config": args.config, "baseline": str(args.baseline), "baseline_config": trees["baseline"][1],
                    "load_average": load, "rows": rows})
    print(f"\nload average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; {len(rows)} calls")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
