"""What realistic image formation costs: each degradation alone and all combined.

Scenes from ``sfs_torch.datasets`` (test-side shapes, never trained on, plus a sphere;
R&H lightings, on which nothing was tuned), formed by each entry of
``sfs_torch.datasets.DEGRADATIONS``. Every degradation scores the same views. For each
image: the silhouette prior (Eq. 10), the default call with the lighting estimated, and
with the "known" lighting (the SH fit of the image over the true normals, as real
datasets define it); the estimate's lMSE against that lighting.

    python benchmarks/realistic.py                                 # 3 shapes + sphere x 3 lightings
    python benchmarks/realistic.py --degradations exact all --shapes 2
    python benchmarks/realistic.py --side validation --config '{"reflectance_map": {...}}'   # tuning

``--side validation`` swaps in the validation shapes and Poly Haven lightings (tune there).
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
from sfs_torch.datasets import DEGRADATIONS, SCENE_SIDES, scene_lightings, scene_shapes, synthetic_scenes  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import write_results  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--focal", type=float, default=None)
    parser.add_argument("--side", choices=SCENE_SIDES, default="test")
    parser.add_argument("--degradations", nargs="*", default=list(DEGRADATIONS), choices=list(DEGRADATIONS))
    parser.add_argument("--config", default="{}", help="pipeline config overrides (JSON), applied to both calls")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "realistic.json")
    args = parser.parse_args()
    config = {"training": {"cache_forests": "never"}, **json.loads(args.config)}
    shapes = scene_shapes(args.shapes, args.side, sphere=True)
    lights = scene_lightings(args.lights, args.side)
    rows = []
    for degradation in args.degradations:
        for scene in synthetic_scenes(shapes, lights, resolution=args.resolution, focal=args.focal,
                                      formation=DEGRADATIONS[degradation]):
            start = time.perf_counter()
            est = sfs_torch.estimate(scene.image, scene.mask, focal=args.focal, config=config, progress=False)
            seconds = time.perf_counter() - start
            known = sfs_torch.estimate(scene.image, scene.mask, focal=args.focal, lighting=scene.lighting,
                                       config=config, progress=False)

            def error(n):
                return float(normal_metrics(n, scene.normals, scene.mask).median[0])

            rows.append({"degradation": degradation, "shape": scene.shape, "lighting": scene.lighting_name,
                         "silhouette": error(coarse_normals(scene.mask, focal=args.focal)),
                         "estimated": error(est.normals), "known": error(known.normals),
                         "lmse": float(lmse(est.lighting, scene.lighting)[0]), "seconds": seconds})
            r = rows[-1]
            print(f"{degradation:<9} {scene.name:<46} {r['silhouette']:6.1f} {r['estimated']:6.1f} {r['known']:6.1f} "
                  f"{r['lmse']:8.5f} {seconds:5.1f}s", flush=True)

    summary = {}
    for degradation in args.degradations:
        mine = [r for r in rows if r["degradation"] == degradation]
        spheres = [r for r in mine if r["shape"] == "sphere"]
        summary[degradation] = {
            "images": len(mine),
            **{key: statistics.median(r[key] for r in mine) for key in ("silhouette", "estimated", "known", "lmse")},
            "sphere_estimated_minus_silhouette": max(r["estimated"] - r["silhouette"] for r in spheres),
        }
    print(f"\n{'degradation':<12}{'images':>7}{'silhouette':>11}{'estimated':>10}{'known':>8}"
          f"{'est/silh':>9}{'est/known':>10}{'lMSE':>9}{'sphere est-silh (worst)':>24}")
    for degradation, s in summary.items():
        print(f"{degradation:<12}{s['images']:>7}{s['silhouette']:>11.2f}{s['estimated']:>10.2f}{s['known']:>8.2f}"
              f"{s['estimated'] / s['silhouette']:>9.2f}{s['estimated'] / s['known']:>10.2f}{s['lmse']:>9.5f}"
              f"{s['sphere_estimated_minus_silhouette']:>24.2f}")
    print()
    write_results(args, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
