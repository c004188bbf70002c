"""The lighting refit with and without the validity constraint, side by side on held-out images.

The images are those of ``benchmarks/end_to_end.py`` with the same arguments (the same
shapes, views, lightings and noise); each is estimated in unknown lighting (the forest
alone, ``refine.when=never``) with ``valid_refit`` true and false.

    python benchmarks/refit_constraint.py --shapes 6 --lights 5
    python benchmarks/refit_constraint.py --shapes 5 --lights 3 --focal 300
"""
from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sfs_torch  # noqa: E402
from sfs_torch.datasets import evaluation_lightings, scene_shapes, synthetic_scenes  # noqa: E402
from sfs_torch.metrics import normal_metrics  # noqa: E402

from _results import write_results  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=10)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--focal", type=float, default=None)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "refit_constraint.json")
    args = parser.parse_args()
    rows = []
    for scene in synthetic_scenes(scene_shapes(args.shapes, "test"), evaluation_lightings(args.lights), focal=args.focal):
        row = {"shape": scene.shape, "lighting": scene.lighting_name}
        for valid in (True, False):
            config = {"training": {"cache_forests": "never"}, "refine": {"when": "never"}, "valid_refit": valid}
            est = sfs_torch.estimate(scene.image, scene.mask, focal=args.focal, config=config, progress=False)
            error = normal_metrics(est.normals, scene.normals, scene.mask).median[0]
            row["valid" if valid else "unconstrained"] = float(error)
        rows.append(row)
        print(f"{scene.shape:<34} {scene.lighting_name:<20} {row['valid']:6.2f} {row['unconstrained']:6.2f}",
              flush=True)
    summary = {key: {"median": statistics.median(r[key] for r in rows), "mean": statistics.mean(r[key] for r in rows)}
               for key in ("valid", "unconstrained")}
    print(f"\n{'refit':<16}{'median':>10}{'mean':>10}   ({len(rows)} images, focal {args.focal})")
    for key, value in summary.items():
        print(f"{key:<16}{value['median']:>10.2f}{value['mean']:>10.2f}")
    write_results(args, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
