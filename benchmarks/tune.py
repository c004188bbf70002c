"""Pipeline options side by side: on the TUNING side by default (validation shapes, Poly Haven lightings).

Each variant is a set of pipeline config overrides (JSON); every variant scores the same
images (``sfs_torch.datasets``' validation side, never the shapes or R&H lightings the
benchmarks report on) with the lighting estimated, or given with ``--known`` (for one
variant: ``"lighting": "known"`` among its overrides).
``--side spare`` scores a larger tuning pool instead: the next shapes the database split
would draw for training (``scene_shapes(n, "spare")``: 10 mammal bones, 5 fly parts and 5
urdf objects in its first 20), under the same Poly Haven lightings; neither the forests'
database nor the learnt relief prior has seen them (the screens made on them are in
docs/pipeline.md). ``--side test`` scores the test side instead (held-out shapes, R&H lightings): for
reporting an ablation of choices already made, never for making one. Each variant after
the first is compared with the first on the same images: the change of the median and of
the mean error with their 90 % paired-bootstrap intervals (``_results.paired_bootstrap``;
a few tenths of a degree are within them on 20-30 images), and the images better / worse
by more than 1 deg. Each variant's median over the silhouette prior's also gets the
interval it spans when the shapes are drawn again, each with all its images
(``_results.ratio_over_shapes``): on the test side's six shapes it is wide
(docs/pipeline.md, "How much a figure moves with the machine and the shapes"). A table of
each shape's median over its images, the prior's and each variant's, follows
(``_results.median_per_shape``; in the JSON too).

    python benchmarks/tune.py --variants '{}' '{"training": {"brightness_jitter": 0.1}}'
    python benchmarks/tune.py --degradation all --shapes 4 --lights 3 --variants '{}' ...
    python benchmarks/tune.py --first-shape 7 --shapes 3 --lights 8 --variants '{}' ...   # validation shapes 8-10
    python benchmarks/tune.py --side test --shapes 5 --lights 3 --variants '{"refine_rounds": 0}' '{}'
    python benchmarks/tune.py --side test --shapes 6 --lights 5 --no-sphere --ablation

The shapes are spread over the split (``sfs_torch.datasets.scene_shapes``), so ``--shapes 4``
is not the first four of ``--shapes 7``: to share one run between two processes, split its
lightings (``--first-light``), not its shapes.

``--ablation`` runs :data:`ABLATION`: the paper's method, then each addition on top of
the one before, then the learnt relief prior without the relief scale before it (which it
made redundant), the default (that, and a converging refinement after it), and the
default with the true lighting given.
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
from sfs_torch.datasets import (  # noqa: E402
    DEGRADATIONS,
    SCENE_SIDES,
    scene_shapes,
    synthetic_scenes,
)
from sfs_torch.metrics import lmse, normal_metrics  # noqa: E402
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import (  # noqa: E402
    median_per_shape,
    paired_bootstrap,
    ratio_over_shapes,
    side_lightings,
    write_results,
)

# (label, overrides): each row adds to the one above it up to the learnt relief prior; then the default
# (that prior without the relief scale) and the default given the true lighting
ABLATION = [
    ("the paper's method", {"refine_rounds": 0, "keep_prior": False, "valid_refit": False,
                            "training": {"brightness_jitter": 0.0, "colour_jitter": 0.0, "noise_from_image": False},
                            "refine": {"when": "never"}}),
    ("+ constrained refit round, jitter", {"keep_prior": False, "training": {"noise_from_image": False},
                                           "refine": {"when": "never"}}),
    ("+ prior check, image-noise matching", {"refine": {"when": "never"}}),
    ("+ joint refinement of surface and lighting", {"refine": {"lighting_weight": 0.0}, "final_round": False,
                                                    "relief_prior_passes": 0}),
    ("+ natural-lighting prior", {"final_round": False, "relief_prior_passes": 0}),
    ("+ final unjittered round", {"relief_prior_passes": 0}),
    ("+ fixed relief scale", {"relief_scale": 1.1, "relief_prior_passes": 0, "relief_refinements": 0}),
    ("+ relief scale growing with the slope", {"relief_scale": 1.22, "relief_slope_power": 0.5,
                                               "relief_prior_passes": 0, "relief_refinements": 0}),
    ("+ learnt relief prior", {"relief_scale": 1.22, "relief_slope_power": 0.5, "relief_refinements": 0}),
    ("the learnt relief prior alone, no relief scale", {"relief_refinements": 0}),
    ("+ a converging refinement after it (the default)", {}),
    ("the default, true lighting given", {"lighting": "known"}),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=SCENE_SIDES, default="validation",
                        help="validation: tune on it; spare: tune on a larger pool (shapes neither trained on nor "
                             "held out); test: report an ablation on it")
    parser.add_argument("--shapes", type=int, default=3)
    parser.add_argument("--first-shape", type=int, default=0,
                        help="leave out the first this many of the --first-shape + --shapes shapes (the sphere stays; "
                             "a selection of that size, not a prefix of a larger one)")
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--first-light", type=int, default=0,
                        help="skip this many lightings first (the same lightings --lights would give after them)")
    parser.add_argument("--light-seed", type=int, default=0,
                        help="tuning sides: the seed of the lightings' random orientations")
    parser.add_argument("--exposure", type=float, default=None,
                        help="tuning sides: scale each lighting so that a lit sphere's 95th percentile is this "
                             "(validation_lightings' own is 0.9; the R&H probes sit at 0.10-0.35)")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--focal", type=float, default=None)
    parser.add_argument("--degradation", default="exact", choices=list(DEGRADATIONS))
    parser.add_argument("--no-sphere", action="store_true", help="leave out the sphere")
    parser.add_argument("--known", action="store_true", help="give the true lighting instead of estimating it")
    parser.add_argument("--variants", nargs="*", default=["{}"], help="pipeline config overrides, one JSON object each")
    parser.add_argument("--ablation", action="store_true", help="run ABLATION instead of --variants")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "tune.json")
    args = parser.parse_args()
    variants = [overrides for _, overrides in ABLATION] if args.ablation else [json.loads(v) for v in args.variants]
    labels = [label for label, _ in ABLATION] if args.ablation else [json.dumps(v) for v in variants]
    if args.first_shape < 0:
        parser.error(f"--first-shape must be >= 0, got {args.first_shape}")
    lightings = side_lightings(parser, args)
    try:
        shapes = scene_shapes(args.first_shape + args.shapes, args.side, sphere=not args.no_sphere)
    except ValueError as error:
        parser.error(f"--first-shape + --shapes: {error}")
    sphere = shapes[: len(shapes) - args.first_shape - args.shapes]  # the sphere comes first, when asked for
    shapes = sphere + shapes[len(sphere) + args.first_shape :]
    rows = []
    for scene in synthetic_scenes(shapes, lightings, resolution=args.resolution,
                                  focal=args.focal, formation=DEGRADATIONS[args.degradation]):
        coarse = coarse_normals(scene.mask, focal=args.focal)
        row = {"case": scene.name, "silhouette": float(normal_metrics(coarse, scene.normals, scene.mask).median[0])}
        for i, overrides in enumerate(variants):
            known = args.known or overrides.get("lighting") == "known"
            config = {k: v for k, v in overrides.items() if k != "lighting"}
            config["training"] = {"cache_forests": "never", **overrides.get("training", {})}
            start = time.perf_counter()
            est = sfs_torch.estimate(scene.image, scene.mask, focal=args.focal, config=config, progress=False,
                                     lighting=scene.lighting if known else None)
            row[f"seconds_{i}"] = time.perf_counter() - start
            row[f"error_{i}"] = float(normal_metrics(est.normals, scene.normals, scene.mask).median[0])
            row[f"lmse_{i}"] = float(lmse(est.lighting, scene.lighting)[0])
        rows.append(row)
        print(f"{scene.name:<48}" + "".join(f"{row[f'error_{i}']:7.2f}" for i in range(len(variants))), flush=True)
    print(f"\n{len(rows)} images ({args.side} side), {args.degradation}, "
          f"{'known' if args.known else 'estimated'} lighting")
    print(f"{'variant':<8}{'median':>8}{'mean':>8}{'lMSE':>9}{'worse':>7}{'s/call':>8}  overrides")
    prior = [r["silhouette"] for r in rows]
    silhouette = statistics.median(prior)
    print(f"{'prior':<8}{silhouette:>8.2f}{statistics.mean(prior):>8.2f}{'':>24}  the silhouette prior (Eq. 10)")
    summary = []
    # a scene's name is "shape|lighting"
    shape_of_row = [r["case"].split("|")[0] for r in rows]
    n_shapes = len(set(shape_of_row))
    for i, overrides in enumerate(variants):
        errors = [r[f"error_{i}"] for r in rows]
        summary.append({"overrides": overrides, "median": statistics.median(errors), "mean": statistics.mean(errors),
                        "ratio_to_prior": statistics.median(errors) / silhouette,
                        "ratio_interval_over_shapes": ratio_over_shapes(errors, prior, shape_of_row),
                        "median_per_shape": median_per_shape(errors, shape_of_row),
                        "lmse": statistics.median(r[f"lmse_{i}"] for r in rows),
                        "worse_than_prior": sum(r[f"error_{i}"] > r["silhouette"] for r in rows),
                        "seconds": statistics.median(r[f"seconds_{i}"] for r in rows)})
        s = summary[-1]
        print(f"{i:<8}{s['median']:>8.2f}{s['mean']:>8.2f}{s['lmse']:>9.5f}{s['worse_than_prior']:>7d}"
              f"{s['seconds']:>8.1f}  {labels[i]}")
    print("median, mean: of the per-image median angular errors (deg); lMSE: median; "
          "worse: images on which the variant's error exceeds the silhouette prior's")
    for i, s in enumerate(summary):
        low, high = s["ratio_interval_over_shapes"]
        print(f"{i} median over the prior's: {s['ratio_to_prior']:.2f}x (90 % over the {n_shapes} shapes "
              f"drawn again with their images: {low:.2f}x .. {high:.2f}x)")
    prior_per_shape = median_per_shape(prior, shape_of_row)
    if n_shapes > 1:
        print(f"\n{'shape':<40}{'prior':>8}" + "".join(f"{i:>8}" for i in range(len(variants)))
              + "  (median over each shape's images)")
        for shape, value in prior_per_shape.items():
            print(f"{shape:<40}{value:>8.2f}"
                  + "".join(f"{entry['median_per_shape'][shape]:>8.2f}" for entry in summary))
    first = [r["error_0"] for r in rows]
    for i in range(1, len(variants)):
        errors = [r[f"error_{i}"] for r in rows]
        change = paired_bootstrap(first, errors)
        change["better"] = sum(e < f - 1 for f, e in zip(first, errors))
        change["worse"] = sum(e > f + 1 for f, e in zip(first, errors))
        summary[i]["against_variant_0"] = change
        (low, high), (mean_low, mean_high) = change["median_interval"], change["mean_interval"]
        print(f"{i} against 0: median {change['median']:+.2f} (90 % paired bootstrap {low:+.2f} .. {high:+.2f}), "
              f"mean {change['mean']:+.2f} ({mean_low:+.2f} .. {mean_high:+.2f}); "
              f"better / worse by > 1 deg: {change['better']} / {change['worse']}")
    write_results(args, silhouette=silhouette, prior_per_shape=prior_per_shape, summary=summary, rows=rows)


if __name__ == "__main__":
    main()
