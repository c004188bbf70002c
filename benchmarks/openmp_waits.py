"""Whole-call time of ``sfs_torch.estimate`` under OpenMP wait settings, idle and under load.

Each setting runs in its own subprocess (the setting must be in the environment before
torch starts), alternately (setting 1, setting 2, ..., then again), on the same test-side
images; a first call per process is not timed. ``--load K`` keeps K busy-looping
processes running meanwhile, as other jobs on a shared machine would.

    python benchmarks/openmp_waits.py --load 0
    python benchmarks/openmp_waits.py --load 2

A setting is ``NAME=VALUE`` (``OMP_WAIT_POLICY=PASSIVE``, ``GOMP_SPINCOUNT=3000``) or
``unset`` (libgomp's default). The table gives, per setting, the median seconds of a
call, of the photometric refinement plus the final round, and of forest training.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from sfs_torch._openmp import SPIN_COUNT, WAIT_VARIABLES

from _results import write_results

# the passive policy alone, the package's spin count (what its commands set), libgomp's default
SETTINGS = ["OMP_WAIT_POLICY=PASSIVE", f"GOMP_SPINCOUNT={SPIN_COUNT}", "unset"]


def _worker(shapes: int) -> None:
    """Time one estimated-lighting call per test-side image; one JSON line each on stdout."""
    import sfs_torch
    from sfs_torch.datasets import evaluation_lightings, scene_shapes, synthetic_scenes

    scenes = list(synthetic_scenes(scene_shapes(shapes, "test", sphere=False), evaluation_lightings(1), resolution=256))
    config = {"training": {"cache_forests": "never"}}
    sfs_torch.estimate(scenes[0].image, scenes[0].mask, config=config, progress=False)
    for scene in scenes:
        start = time.perf_counter()
        est = sfs_torch.estimate(scene.image, scene.mask, config=config, progress=False)
        seconds = time.perf_counter() - start
        refine = est.timings.get("photometric refinement", 0.0) + est.timings.get("final round", 0.0)
        print(json.dumps({"case": scene.name, "seconds": seconds, "refinement": refine,
                          "forest": est.timings.get("train forest", 0.0)}), flush=True)


def _environment(setting: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in WAIT_VARIABLES}
    if setting != "unset":
        name, value = setting.split("=", 1)
        env[name] = value
    return env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--settings", nargs="+", default=SETTINGS)
    parser.add_argument("--load", type=int, default=0, help="busy-looping processes running meanwhile")
    parser.add_argument("--shapes", type=int, default=2, help="test-side images, one R&H probe")
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "openmp_waits.json")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        _worker(args.shapes)
        return
    for setting in args.settings:
        if setting != "unset" and setting.split("=", 1)[0] not in WAIT_VARIABLES:
            parser.error(f"a setting is one of {WAIT_VARIABLES} as NAME=VALUE, or 'unset'; got {setting!r}")
    if args.load < 0 or args.shapes < 1 or args.passes < 1:
        parser.error("--load must be >= 0, --shapes and --passes >= 1")
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    rows = []
    try:
        for p in range(args.passes):
            for setting in args.settings:
                done = subprocess.run([sys.executable, __file__, "--worker", "--shapes", str(args.shapes)],
                                      env=_environment(setting), capture_output=True, text=True, check=True)
                for line in done.stdout.splitlines():
                    rows.append({"setting": setting, "pass": p, **json.loads(line)})
                print(f"pass {p} {setting}: done", flush=True)
    finally:
        for process in busy:
            process.kill()
    print(f"\n{args.shapes} test-side images x {args.passes} passes, load {args.load} busy processes; median s")
    print(f"{'setting':<26} {'call':>7} {'refinement':>11} {'forest':>7}")
    summary = {}
    for setting in args.settings:
        mine = [r for r in rows if r["setting"] == setting]
        summary[setting] = {k: statistics.median(r[k] for r in mine) for k in ("seconds", "refinement", "forest")}
        s = summary[setting]
        print(f"{setting:<26} {s['seconds']:7.2f} {s['refinement']:11.2f} {s['forest']:7.2f}")
    write_results(args, summary=summary, rows=rows, load_average=list(os.getloadavg()))


if __name__ == "__main__":
    main()
