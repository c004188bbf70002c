"""The photometric refinement on the TUNING side: validation shapes, Poly Haven lightings.

The refinement's options (``sfs_torch.refine.RefineConfig``) were chosen on these images
only: ``sfs_torch.datasets``' validation side (the odd-indexed evaluation shapes of the
database split; the benchmarks report on the even-indexed ones) under the eight CC0 Poly
Haven environments of ``sfs_torch.natural_lighting`` seen by randomly oriented cameras
(never R&H's probes), 256 px like the benchmark, noise 0.001; each shape gets its own
lightings. For each image: the forest in unknown and in known lighting, and
the refinement of each (``when=always`` / ``when=known``) for every variant of the
options given (the forests are shared by the variants).

    python benchmarks/refine_tuning.py                          # 4 shapes x 2 lightings, defaults
    python benchmarks/refine_tuning.py --variants '{}' '{"normal_weight": 0.2}'
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sfs_torch  # noqa: E402
from sfs_torch.datasets import scene_shapes, synthetic_scenes, validation_lightings  # noqa: E402
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.refine import RefineConfig, refine_shape_and_lighting  # noqa: E402

from _results import write_results  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=4)
    parser.add_argument("--lights-per-shape", type=int, default=2)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--variants", nargs="*", default=["{}"], help="RefineConfig overrides, one JSON object each")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "refine_tuning.json")
    args = parser.parse_args()
    variants = [json.loads(v) for v in args.variants]
    config = {"training": {"cache_forests": "never"}, "refine": {"when": "never"}}
    shapes = scene_shapes(args.shapes, "validation")
    lights = validation_lightings(args.shapes * args.lights_per_shape)
    rows = []
    for scene in synthetic_scenes(shapes, lights, resolution=args.resolution, lights_per_shape=args.lights_per_shape):
        image, mask, normals, sh, name = scene.image, scene.mask, scene.normals, scene.lighting, scene.lighting_name
        est = sfs_torch.estimate(image, mask, config=config, progress=False)
        known = sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)

        def error(n):
            return float(normal_metrics(n, normals, mask).median[0])

        row = {"shape": scene.shape, "lighting": name, "unknown": error(est.normals), "known": error(known.normals),
               "lmse": float(lmse(est.lighting, sh)[0])}
        for i, options in enumerate(variants):
            est_ref = refine_shape_and_lighting(image, mask, est.normals, est.lighting, confidence=est.confidence,
                                                config=RefineConfig(**options))
            known_ref = refine_shape_and_lighting(image, mask, known.normals, sh, confidence=known.confidence,
                                                  config=RefineConfig(**{**options, "optimise_lighting": False}))
            row.update({f"unknown_refined_{i}": error(est_ref.normals), f"known_refined_{i}": error(known_ref.normals),
                        f"lmse_refined_{i}": float(lmse(est_ref.lighting, sh)[0])})
        rows.append(row)
        print(" ".join(f"{v:.4f}" if isinstance(v, float) else f"{v:<28}" for v in rows[-1].values()), flush=True)
    keys = [k for k in rows[0] if k not in ("shape", "lighting")]
    summary = {key: statistics.median(r[key] for r in rows) for key in keys}
    print(f"\nmedian over {len(rows)} images; variants: {dict(enumerate(variants))}")
    for key, value in summary.items():
        print(f"  {key:<18}{value:10.4f}")
    write_results(args, variants=variants, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
