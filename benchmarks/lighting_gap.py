"""How close an estimated lighting must come to the true one: the forest along the way between them.

For each image the default call (lighting estimated) gives a final lighting ``L_est``.
Forests are then trained without jitter, as for a given lighting (the forest alone:
``refine.when=never``, ``keep_prior=false``), for lightings on the straight way to the
true lighting ``L_true``:

    L(alpha) = (1 - alpha) L_est + alpha L_true

(both shade the visible hemisphere non-negatively, so every ``L(alpha)`` does too).
For each ``alpha`` the table gives the normals' median angular error and two scores that
need no ground truth: the integrability residual (median angle between the forest's
normals and the normals of their kappa-weighted L2-integrated surface) and the
photometric residual (:func:`sfs_torch.refine.photometric_residual`). It measures what a
better lighting estimate would buy, and whether those scores could tell a better
lighting from a worse one.

    python benchmarks/lighting_gap.py --side test --shapes 6 --lights 5
    python benchmarks/lighting_gap.py --shapes 7 --lights 3 --alphas 0 0.5 1
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sfs_torch  # noqa: E402
from sfs_torch.datasets import (  # noqa: E402
    SCENE_SIDES,
    scene_lightings,
    scene_shapes,
    synthetic_scenes,
)
from sfs_torch.geometry_db import load_database  # noqa: E402
from sfs_torch.integrability import integrate_normals  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.pipeline import resolve_config  # noqa: E402
from sfs_torch.refine import photometric_residual  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import write_results  # noqa: E402

FOREST_ALONE = {"keep_prior": False, "refine": {"when": "never"}, "training": {"cache_forests": "never"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=SCENE_SIDES, default="validation")
    parser.add_argument("--shapes", type=int, default=7)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.0, 0.25, 0.5, 0.75, 0.9, 1.0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "lighting_gap.json")
    args = parser.parse_args()
    if not all(0 <= a <= 1 for a in args.alphas):
        parser.error(f"--alphas must lie in [0, 1] (between the estimate and the truth), got {args.alphas}")
    shapes = scene_shapes(args.shapes, args.side)
    lightings = scene_lightings(args.lights, args.side)
    database = load_database(resolve_config({}).database, progress=False)
    rows = []
    for scene in synthetic_scenes(shapes, lightings, resolution=args.resolution):
        start = time.perf_counter()
        mask = scene.mask

        def error(normals):
            return float(normal_metrics(normals, scene.normals, mask).median[0])

        default = sfs_torch.estimate(scene.image, mask, config={"training": {"cache_forests": "never"}},
                                     progress=False, database=database)
        row = {"case": scene.name, "prior": error(coarse_normals(mask)), "default": error(default.normals),
               "default_lmse": float(lmse(default.lighting, scene.lighting)[0]), "alphas": []}
        for alpha in args.alphas:
            lighting = (1 - alpha) * default.lighting + alpha * scene.lighting
            est = sfs_torch.estimate(scene.image, mask, lighting=lighting, config=FOREST_ALONE, progress=False,
                                     database=database)
            surface = integrate_normals(est.normals, mask, weights=est.confidence)
            row["alphas"].append({
                "alpha": alpha, "error": error(est.normals), "lmse": float(lmse(lighting, scene.lighting)[0]),
                "integrability": float(normal_metrics(est.normals, surface.normals, mask).median[0]),
                "photometric": float(photometric_residual(est.normals, lighting, scene.image, mask)[0]),
            })
        rows.append(row)
        print(f"{scene.name:<44} prior {row['prior']:6.2f} default {row['default']:6.2f} | "
              + " ".join(f"{a['alpha']:g}: {a['error']:5.2f}" for a in row["alphas"])
              + f"  ({time.perf_counter() - start:.0f} s)", flush=True)

    summary = []
    for i, alpha in enumerate(args.alphas):
        cells = [r["alphas"][i] for r in rows]
        summary.append({
            "alpha": alpha, "median": statistics.median(c["error"] for c in cells),
            "mean": statistics.mean(c["error"] for c in cells), "lmse": statistics.median(c["lmse"] for c in cells),
            "integrability": statistics.median(c["integrability"] for c in cells),
            "photometric": statistics.median(c["photometric"] for c in cells),
        })
    last = len(args.alphas) - 1
    lowest = {key: sum(r["alphas"][last][key] <= min(a[key] for a in r["alphas"]) for r in rows)
              for key in ("integrability", "photometric")}
    print(f"\n{len(rows)} images ({args.side} side); the forest alone, without jitter, for L(alpha)")
    print(f"{'lighting':<24}{'median':>8}{'mean':>8}{'lMSE':>10}{'integ.':>8}{'photo. %':>10}")
    print(f"{'silhouette prior':<24}{statistics.median(r['prior'] for r in rows):>8.2f}"
          f"{statistics.mean(r['prior'] for r in rows):>8.2f}")
    print(f"{'default call':<24}{statistics.median(r['default'] for r in rows):>8.2f}"
          f"{statistics.mean(r['default'] for r in rows):>8.2f}{statistics.median(r['default_lmse'] for r in rows):>10.5f}")
    for s in summary:
        print(f"{'alpha = %g' % s['alpha']:<24}{s['median']:>8.2f}{s['mean']:>8.2f}{s['lmse']:>10.5f}"
              f"{s['integrability']:>8.2f}{100 * s['photometric']:>10.3f}")
    print(f"alpha = {args.alphas[last]:g} scores lowest of all alphas: integrability on {lowest['integrability']}, "
          f"photometric on {lowest['photometric']} of {len(rows)} images")
    write_results(args, summary=summary, lowest_at_last_alpha=lowest, rows=rows)


if __name__ == "__main__":
    main()
