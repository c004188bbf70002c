"""End-to-end accuracy and speed of sfs_torch.estimate on held-out shapes.

Every shape comes from the EVALUATION side of the database's shape split (never
trained on), rendered from a random view under R&H's natural light probes with noise
sigma 0.001 (the paper's setting). For each image it reports the median angular error
of: the silhouette-only coarse normal (Eq. 10), the full method in unknown lighting,
and the full method with the true lighting given; plus the lighting lMSE and the
per-stage time of one unknown-lighting call (database already cached).

    python benchmarks/end_to_end.py            # 10 shapes x 3 lightings, 256 px
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
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

import sfs_torch  # noqa: E402
from sfs_torch.geometry_db import DatabaseConfig, evaluation_shapes, load_database  # noqa: E402
from sfs_torch.integrability import integrate_normals  # noqa: E402
from sfs_torch.lighting import natural_lightings, render_sh  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.rendering import random_view_rotations, render_normals  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--shapes", type=int, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--collection", default="default")
    parser.add_argument("--focal", type=float, default=None, help="perspective camera (pixels); default orthographic")
    parser.add_argument("--integrate", action="store_true", help="also score L2, L1 and convex integrability refinement")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "end_to_end.json")
    args = parser.parse_args()
    n_shapes = args.shapes or (3 if args.quick else 10)
    resolution = args.resolution or (128 if args.quick else 256)
    light_names = ["grace_cathedral", "campus_sunset"] if args.quick else ["grace_cathedral", "campus_sunset", "uffizi_gallery"]
    config = {"database": {"collection": args.collection}, "training": {"cache_forests": False}}
    db_cfg = DatabaseConfig(collection=args.collection)
    load_database(db_cfg)
    shapes = evaluation_shapes(db_cfg)
    # spread the picks over the evaluation split's groups
    step = max(1, len(shapes) // n_shapes)
    shapes = shapes[::step][:n_shapes]
    lights = natural_lightings(0.8)
    generator = torch.Generator().manual_seed(0)
    rows = []
    for shape in shapes:
        view = render_normals(shape.mesh, random_view_rotations(1, generator)[0], resolution, focal=args.focal)
        normals, mask = view.normals[None], view.mask[None]
        for name in light_names:
            sh = lights[name][None]
            image = ((render_sh(normals, sh) + 0.001 * torch.randn(normals.shape, generator=generator)).clamp(0, 1)) * mask
            start = time.perf_counter()
            est = sfs_torch.estimate(image, mask, focal=args.focal, config=config, progress=False)
            seconds = time.perf_counter() - start
            known = sfs_torch.estimate(image, mask, focal=args.focal, lighting=sh, config=config, progress=False)
            rows.append({
                "shape": shape.name, "lighting": name, "pixels": int(mask.sum()),
                "silhouette_only": float(normal_metrics(coarse_normals(mask, focal=args.focal), normals, mask).median[0]),
                "unknown_light": float(normal_metrics(est.normals, normals, mask).median[0]),
                "known_light": float(normal_metrics(known.normals, normals, mask).median[0]),
                "lmse": float(lmse(est.lighting, sh)[0]),
                "seconds": seconds,
                "stages": {k: v for k, v in est.timings.items() if k != "database"},
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
                  f"{r['known_light']:6.1f} {r['lmse']:8.5f} {seconds:6.2f}s", flush=True)

    def med(key):
        return statistics.median(r[key] for r in rows)

    stages = {k: statistics.median(r["stages"].get(k, 0.0) for r in rows) for k in rows[0]["stages"]}
    summary = {
        "images": len(rows), "resolution": resolution, "collection": args.collection, "focal": args.focal,
        "median_of_medians_deg": {"silhouette_only": med("silhouette_only"), "unknown_light": med("unknown_light"),
                                  "known_light": med("known_light")},
        "median_lmse": med("lmse"), "median_seconds_per_call": med("seconds"), "median_stage_seconds": stages,
        "threads": torch.get_num_threads(),
    }
    optional = ["unknown_light_as_orthographic", "unknown_light_l2", "unknown_light_l1", "unknown_light_conv"]
    for key in optional:
        if key in rows[0]:
            summary["median_of_medians_deg"][key] = med(key)
    print()
    print(f"{'method':<36}{'median angular error (deg)':>28}")
    for key, label in [("silhouette_only", "silhouette only (Eq. 10)"), ("unknown_light", "full method, unknown lighting"),
                       ("known_light", "full method, known lighting"),
                       ("unknown_light_as_orthographic", "unknown lighting, camera ignored"),
                       ("unknown_light_l2", "unknown lighting + L2 integrability"),
                       ("unknown_light_l1", "unknown lighting + L1 integrability"),
                       ("unknown_light_conv", "unknown lighting + convex combination")]:
        if key not in summary["median_of_medians_deg"]:
            continue
        print(f"{label:<36}{summary['median_of_medians_deg'][key]:>28.2f}")
    print(f"{'lighting lMSE (median)':<36}{summary['median_lmse']:>28.5f}")
    print(f"{'seconds per call (median)':<36}{summary['median_seconds_per_call']:>28.2f}")
    for k, v in stages.items():
        print(f"  {k:<34}{v:>28.3f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=2))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
