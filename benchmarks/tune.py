"""Pipeline options side by side on the TUNING side: validation shapes, Poly Haven lightings.

Each variant is a set of pipeline config overrides (JSON); every variant scores the same
images (``sfs_torch.datasets``' validation side, never the shapes or R&H lightings the
benchmarks report on) with the lighting estimated, or given with ``--known``.

    python benchmarks/tune.py --variants '{}' '{"training": {"brightness_jitter": 0.1}}'
    python benchmarks/tune.py --degradation all --shapes 4 --lights 3 --variants '{}' ...
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sfs_torch  # noqa: E402
from sfs_torch.datasets import DEGRADATIONS, scene_shapes, synthetic_scenes, validation_lightings  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--focal", type=float, default=None)
    parser.add_argument("--degradation", default="exact", choices=list(DEGRADATIONS))
    parser.add_argument("--no-sphere", action="store_true", help="leave out the sphere")
    parser.add_argument("--known", action="store_true", help="give the true lighting instead of estimating it")
    parser.add_argument("--variants", nargs="*", default=["{}"], help="pipeline config overrides, one JSON object each")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "tune.json")
    args = parser.parse_args()
    variants = [json.loads(v) for v in args.variants]
    shapes = scene_shapes(args.shapes, "validation", sphere=not args.no_sphere)
    rows = []
    for scene in synthetic_scenes(shapes, validation_lightings(args.lights), resolution=args.resolution,
                                  focal=args.focal, formation=DEGRADATIONS[args.degradation]):
        row = {"case": scene.name}
        for i, overrides in enumerate(variants):
            config = {**overrides, "training": {"cache_forests": "never", **overrides.get("training", {})}}
            start = time.perf_counter()
            est = sfs_torch.estimate(scene.image, scene.mask, focal=args.focal, config=config, progress=False,
                                     lighting=scene.lighting if args.known else None)
            row[f"seconds_{i}"] = time.perf_counter() - start
            row[f"error_{i}"] = float(normal_metrics(est.normals, scene.normals, scene.mask).median[0])
            row[f"lmse_{i}"] = float(lmse(est.lighting, scene.lighting)[0])
        rows.append(row)
        print(f"{scene.name:<48}" + "".join(f"{row[f'error_{i}']:7.2f}" for i in range(len(variants))), flush=True)
    print(f"\n{len(rows)} images, {args.degradation}, {'known' if args.known else 'estimated'} lighting")
    print(f"{'variant':<8}{'median':>8}{'mean':>8}{'lMSE':>9}{'s/call':>8}  overrides")
    summary = []
    for i, overrides in enumerate(variants):
        errors = [r[f"error_{i}"] for r in rows]
        summary.append({"overrides": overrides, "median": statistics.median(errors), "mean": statistics.mean(errors),
                        "lmse": statistics.median(r[f"lmse_{i}"] for r in rows),
                        "seconds": statistics.median(r[f"seconds_{i}"] for r in rows)})
        s = summary[-1]
        print(f"{i:<8}{s['median']:>8.2f}{s['mean']:>8.2f}{s['lmse']:>9.5f}{s['seconds']:>8.1f}  {json.dumps(overrides)}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                    "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
