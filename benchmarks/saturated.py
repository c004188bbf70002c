"""Images with half of the object's pixels saturated: accuracy and the returned lighting's validity.

Test-side scenes (held-out shapes and a sphere under R&H probes; nothing was tuned on
them), exact image formation, then scaled until the median object pixel clips at 1 in
its brightest channel and clipped, so about half of the object's pixels read 1 in some
channel. Three variants, each on the same images: the default call, the default before
the photometric refinement (``refine=known``: with the lighting estimated it stops after
the forest), and that without the lighting refit round (``refine_rounds=0``). For each:
the median and mean over images of the per-image median angular error, and how many of
the returned lightings shade the visible hemisphere of a sphere below -1 % of their peak
(``valid_refit`` constrains the refits on 400 directions; the jointly refined lighting
is not constrained).

    python benchmarks/saturated.py                      # 7 shapes + sphere x 7 lightings, 64 px
    python benchmarks/saturated.py --shapes 2 --lights 2 --resolution 128
"""
from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

import sfs_torch  # noqa: E402
from sfs_torch.datasets import evaluation_lightings, scene_shapes, synthetic_scenes  # noqa: E402
from sfs_torch.lighting import render_sphere  # noqa: E402
from sfs_torch.metrics import normal_metrics  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import write_results  # noqa: E402

VARIANTS = {
    "default": {},
    "before refinement": {"refine": {"when": "known"}},
    "no refit round": {"refine_rounds": 0, "refine": {"when": "known"}},
}


def saturate(image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``image`` (1, 3, H, W) scaled so its median object pixel's brightest channel is 1, clipped."""
    brightest = image.amax(1)[mask[:, 0]]
    return (image / float(torch.quantile(brightest, 0.5))).clamp(0, 1) * mask


def lowest_shading(lighting: torch.Tensor) -> float:
    """The lowest value of the lighting's rendered sphere (visible hemisphere) over its peak."""
    sphere = render_sphere(lighting, 64)
    return float(sphere.min() / sphere.max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", type=int, default=7)
    parser.add_argument("--lights", type=int, default=7)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "saturated.json")
    args = parser.parse_args()
    rows = []
    for scene in synthetic_scenes(scene_shapes(args.shapes, "test", sphere=True), evaluation_lightings(args.lights),
                                  resolution=args.resolution):
        image = saturate(scene.image, scene.mask)
        row = {"case": scene.name,
               "saturated": float((image[:, :, scene.mask[0, 0]] >= 1).any(1).float().mean()),
               "silhouette": float(normal_metrics(coarse_normals(scene.mask), scene.normals, scene.mask).median[0])}
        for name, overrides in VARIANTS.items():
            config = {**overrides, "training": {"cache_forests": "never"}}
            est = sfs_torch.estimate(image, scene.mask, config=config, progress=False)
            row[name] = {"error": float(normal_metrics(est.normals, scene.normals, scene.mask).median[0]),
                         "lowest_shading": lowest_shading(est.lighting)}
        rows.append(row)
        print(f"{scene.name:<48}{row['saturated']:6.2f}" + "".join(
            f"{row[n]['error']:8.2f}{row[n]['lowest_shading']:7.3f}" for n in VARIANTS), flush=True)
    print(f"\n{len(rows)} images (test side), about half of each object's pixels saturated; "
          f"saturated fraction {min(r['saturated'] for r in rows):.2f}-{max(r['saturated'] for r in rows):.2f}")
    print(f"{'variant':<20}{'median':>8}{'mean':>8}{'invalid':>9}{'lowest':>8}")
    print(f"{'silhouette prior':<20}{statistics.median(r['silhouette'] for r in rows):>8.2f}"
          f"{statistics.mean(r['silhouette'] for r in rows):>8.2f}")
    summary = {}
    for name in VARIANTS:
        errors = [r[name]["error"] for r in rows]
        lowest = [r[name]["lowest_shading"] for r in rows]
        summary[name] = {"median": statistics.median(errors), "mean": statistics.mean(errors),
                         "invalid": sum(v < -0.01 for v in lowest), "lowest_shading": min(lowest)}
        s = summary[name]
        print(f"{name:<20}{s['median']:>8.2f}{s['mean']:>8.2f}{s['invalid']:>9d}{s['lowest_shading']:>8.3f}")
    print("invalid: lightings shading the visible hemisphere below -1 % of their peak; lowest: the lowest shading / peak")
    write_results(args, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
