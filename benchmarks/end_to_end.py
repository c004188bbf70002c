"""End-to-end accuracy and speed of sfs_torch.estimate on held-out shapes.

The scenes are ``sfs_torch.datasets``' test side: shapes from the evaluation side of the
database's shape split (never trained on) that no option was tuned on, each rendered
from a random view under R&H's natural light probes with noise sigma 0.001 (the paper's
setting). For each image it reports the median angular error
of: the silhouette-only coarse normal (Eq. 10), the full method in unknown lighting,
and the full method with the true lighting given, each without and with the
photometric refinement (:mod:`sfs_torch.refine`, applied to the same forest output, so
the two columns differ by that stage alone); plus the lighting lMSE before and after
the refinement and the per-stage time of one call of each kind (database cached).

    python benchmarks/end_to_end.py            # 10 shapes (all of the test side) x 3 lightings, 256 px
    python benchmarks/end_to_end.py --shapes 6 --lights 5   # 6 shapes x 5 lightings
    python benchmarks/end_to_end.py --quick    # 3 shapes x 2 lightings, 128 px
    python benchmarks/end_to_end.py --focal 300 --out benchmarks/results/end_to_end_persp.json
    python benchmarks/end_to_end.py --integrate  # also Table 1b: the integrability variants

With ``--integrate`` the unknown-lighting normals are also refined by L2 and L1
integrability (``integrate_normals`` with the forest's kappa as weights, the pipeline's
own call and defaults) and by the convex combination (a further ``estimate`` call with
``integrate="conv"``, which needs the forest's leaves).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

import sfs_torch  # noqa: E402
from sfs_torch.datasets import evaluation_lightings, scene_shapes, synthetic_scenes  # noqa: E402
from sfs_torch.geometry_db import DatabaseConfig, load_database  # noqa: E402
from sfs_torch.integrability import integrate_normals  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.refine import RefineConfig, refine_shape_and_lighting  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import write_results  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--shapes", type=int, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--collection", default="default")
    parser.add_argument("--focal", type=float, default=None, help="perspective camera (pixels); default orthographic")
    parser.add_argument("--integrate", action="store_true", help="also score L2, L1 and convex integrability refinement")
    parser.add_argument("--lights", type=int, default=None, help="how many R&H lightings (3 by default, at most 7)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "end_to_end.json")
    args = parser.parse_args()
    n_shapes = args.shapes or (3 if args.quick else 10)
    resolution = args.resolution or (128 if args.quick else 256)
    n_lights = args.lights or (2 if args.quick else 3)
    lights = evaluation_lightings(n_lights)
    # the forest alone; the refinement is applied below to the same output
    config = {"database": {"collection": args.collection}, "training": {"cache_forests": "never"},
              "refine": {"when": "never"}}
    load_database(DatabaseConfig(collection=args.collection))
    rows = []
    shapes = scene_shapes(n_shapes, "test", DatabaseConfig(collection=args.collection))
    for scene in synthetic_scenes(shapes, lights, resolution=resolution, focal=args.focal):
        image, mask, normals, sh, name = scene.image, scene.mask, scene.normals, scene.lighting, scene.lighting_name
        start = time.perf_counter()
        est = sfs_torch.estimate(image, mask, focal=args.focal, config=config, progress=False)
        seconds = time.perf_counter() - start
        start = time.perf_counter()
        known = sfs_torch.estimate(image, mask, focal=args.focal, lighting=sh, config=config, progress=False)
        known_seconds = time.perf_counter() - start

        def refined(e, optimise_lighting):
            begin = time.perf_counter()
            out = refine_shape_and_lighting(image, mask, e.normals, e.lighting, confidence=e.confidence,
                                            focal=args.focal, config=RefineConfig(optimise_lighting=optimise_lighting))
            return out, time.perf_counter() - begin

        est_ref, est_ref_seconds = refined(est, True)
        known_ref, known_ref_seconds = refined(known, False)

        def error(n):
            return float(normal_metrics(n, normals, mask).median[0])

        rows.append({
            "shape": scene.shape, "lighting": name, "pixels": int(mask.sum()),
            "silhouette_only": error(coarse_normals(mask, focal=args.focal)),
            "unknown_light": error(est.normals), "unknown_light_refined": error(est_ref.normals),
            "known_light": error(known.normals), "known_light_refined": error(known_ref.normals),
            "lmse": float(lmse(est.lighting, sh)[0]), "lmse_refined": float(lmse(est_ref.lighting, sh)[0]),
            "seconds": seconds, "seconds_refined": seconds + est_ref_seconds,
            "known_seconds": known_seconds, "known_seconds_refined": known_seconds + known_ref_seconds,
            "stages": {**{k: v for k, v in est.timings.items() if k != "database"},
                       "photometric refinement": est_ref_seconds},
        })
        if args.focal is not None:
            # Table 3: the same perspective image estimated as if it were orthographic
            ortho = sfs_torch.estimate(image, mask, config=config, progress=False)
            rows[-1]["unknown_light_as_orthographic"] = float(normal_metrics(ortho.normals, normals, mask).median[0])
        if args.integrate:
            for method in ("l2", "l1"):
                surface = integrate_normals(est.normals, mask, method=method, weights=est.confidence, focal=args.focal)
                rows[-1][f"unknown_light_{method}"] = float(normal_metrics(surface.normals, normals, mask).median[0])
            conv = sfs_torch.estimate(image, mask, focal=args.focal, integrate="conv", config=config, progress=False)
            rows[-1]["unknown_light_conv"] = float(normal_metrics(conv.normals, normals, mask).median[0])
        r = rows[-1]
        print(f"{r['shape']:<34} {name:<16} {r['silhouette_only']:6.1f} {r['unknown_light']:6.1f} "
              f"{r['unknown_light_refined']:6.1f} {r['known_light']:6.1f} {r['known_light_refined']:6.1f} "
              f"{r['lmse']:8.5f} {r['lmse_refined']:8.5f} {seconds:6.2f}s", flush=True)

    def med(key):
        return statistics.median(r[key] for r in rows)

    stages = {k: statistics.median(r["stages"].get(k, 0.0) for r in rows) for k in rows[0]["stages"]}
    summary = {
        "images": len(rows), "resolution": resolution, "collection": args.collection, "focal": args.focal,
        "lightings": [name for name, _ in lights],
        "median_of_medians_deg": {key: med(key) for key in (
            "silhouette_only", "unknown_light", "unknown_light_refined", "known_light", "known_light_refined")},
        "median_lmse": med("lmse"), "median_lmse_refined": med("lmse_refined"),
        "median_seconds_per_call": {key: med(key) for key in (
            "seconds", "seconds_refined", "known_seconds", "known_seconds_refined")},
        "median_stage_seconds": stages,
        "threads": torch.get_num_threads(),
    }
    optional = ["unknown_light_as_orthographic", "unknown_light_l2", "unknown_light_l1", "unknown_light_conv"]
    for key in optional:
        if key in rows[0]:
            summary["median_of_medians_deg"][key] = med(key)
    print()
    print(f"{'method':<36}{'median angular error (deg)':>28}")
    for key, label in [("silhouette_only", "silhouette only (Eq. 10)"), ("unknown_light", "full method, unknown lighting"),
                       ("unknown_light_refined", "  + photometric refinement"),
                       ("known_light", "full method, known lighting"),
                       ("known_light_refined", "  + photometric refinement"),
                       ("unknown_light_as_orthographic", "unknown lighting, camera ignored"),
                       ("unknown_light_l2", "unknown lighting + L2 integrability"),
                       ("unknown_light_l1", "unknown lighting + L1 integrability"),
                       ("unknown_light_conv", "unknown lighting + convex combination")]:
        if key not in summary["median_of_medians_deg"]:
            continue
        print(f"{label:<36}{summary['median_of_medians_deg'][key]:>28.2f}")
    print(f"{'lighting lMSE (median)':<36}{summary['median_lmse']:>28.5f}")
    print(f"{'  + photometric refinement':<36}{summary['median_lmse_refined']:>28.5f}")
    for key, label in [("seconds", "s per call, unknown lighting"), ("seconds_refined", "  + photometric refinement"),
                       ("known_seconds", "s per call, known lighting"), ("known_seconds_refined", "  + photometric refinement")]:
        print(f"{label:<36}{summary['median_seconds_per_call'][key]:>28.2f}")
    for k, v in stages.items():
        print(f"  {k:<34}{v:>28.3f}")
    write_results(args, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
