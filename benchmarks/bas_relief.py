"""How much of the estimated-lighting error is a bas-relief transform of the surface.

Under orthographic projection a generalised bas-relief (GBR) transform of a surface,
``z -> lam z + mu x + nu y``, with the lighting transformed alike, leaves the occluding
contour's normals as they are and changes the shading of a uniform-albedo object only
through an albedo factor (Belhumeur et al. 1999). On the normals of the default call
(lighting estimated) this script finds, per image, the transform that brings them
closest to the truth, over three families:

- **scale**: ``lam`` alone (``mu = nu = 0``), a deeper or flatter relief;
- **tilt**: ``mu, nu`` alone (``lam = 1``), a plane added to the depth;
- **both**: every ``(lam, mu, nu)`` of the grids;
- **fitted**: any ``(lam, mu, nu)``, found by ``sfs_torch.relief_prior.best_relief`` (L-BFGS
  on the mean angle to the truth) from the best of the grids.

The transformed normals are ``normalize(lam n_x - mu n_z, lam n_y - nu n_z, n_z)``
(``sfs_torch.integrability.bas_relief_normals``, as the default's ``relief_scale``). These
are oracles (they use the true normals): they say how much error a cue that picked the
transform could remove, not that any cue can. The script also scores every depth scale of
``FINE_SCALES`` applied to all images alike, with no oracle (how the default's
``relief_scale`` was chosen, on the tuning side), and every rule
``lam = c * (s / 0.8) ** p`` for ``p`` in ``SLOPE_POWERS``, ``s`` the median slope of each
image's normals (``sfs_torch.integrability.median_slope``) and ``c`` the factor with the
lowest mean error over the images (how ``relief_slope_power`` was chosen; run it on the
call without a relief scale, ``--call '{"relief_scale": 1.0, "relief_slope_power": 0,
"relief_prior_passes": 0}'``). On such a call it also scores the default's relief scale
(none since the learnt prior made the slope rule redundant; the rule when it was the
default) followed by 1, 2 or 3 passes of the learnt relief prior (``sfs_torch.relief_prior``;
how ``relief_prior_passes`` was chosen).
With ``--hypotheses`` the tilts are also
tried as hypotheses produced alike, with no ground truth: the default's normals tilted,
the lighting refitted to them (``refit_lighting``) and the joint refinement run from them
(with the tilted normals as its prior). The tilt whose refinement ends at the lowest loss
is picked, and so is the one with the lowest photometric residual. That measures whether
the refinement's own energy can tell the tilt. With ``--converging`` the hypotheses are
refined as the call refines its surface after the prior check, the height held in
``relief_refinement_unit`` image sides (``refine.height_unit``, 1 px, hardly moves an
orthographic surface). With ``--lighting-prior W ...`` every
transform of the grid gets the lighting refitted to its normals and is scored by its
photometric residual (relative to the untransformed normals') plus ``W`` times that
lighting's natural-lighting prior energy; the best-scored transform is picked, per ``W``.
That measures whether the lighting prior can tell the transform.

    python benchmarks/bas_relief.py --shapes 7 --lights 3 --exposure 0.2
    python benchmarks/bas_relief.py --shapes 7 --lights 3 --exposure 0.2 --hypotheses
    python benchmarks/bas_relief.py --shapes 7 --lights 3 --exposure 0.2 --hypotheses 0.25 --converging
    python benchmarks/bas_relief.py --side test --shapes 6 --lights 5 --degradation all
    python benchmarks/bas_relief.py --shapes 7 --lights 3 --exposure 0.2 --lighting-prior 0.1 0.3 1 3
    python benchmarks/bas_relief.py --shapes 10 --lights 8 --exposure 0.2 --light-seed 1 \
        --call '{"relief_scale": 1.0, "relief_slope_power": 0, "relief_prior_passes": 0}'
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

import sfs_torch  # noqa: E402
from sfs_torch.datasets import (  # noqa: E402
    DEGRADATIONS,
    SCENE_SIDES,
    scene_shapes,
    synthetic_scenes,
)
from sfs_torch.geometry_db import load_database  # noqa: E402
from sfs_torch.integrability import bas_relief_normals, median_slope  # noqa: E402
from sfs_torch.metrics import normal_metrics  # noqa: E402
from sfs_torch.natural_lighting import lighting_prior_energy, load_lighting_prior  # noqa: E402
from sfs_torch.pipeline import (  # noqa: E402
    RELIEF_REFERENCE_SLOPE,
    PipelineConfig,
    _converging_refine,
    _relief_factor,
    resolve_config,
)
from sfs_torch.reflectance_map import refit_lighting  # noqa: E402
from sfs_torch.refine import photometric_residual, refine_shape_and_lighting  # noqa: E402
from sfs_torch.relief_prior import (  # noqa: E402
    ReliefTransform,
    apply_relief,
    best_relief,
    load_relief_net,
    predict_relief,
)
from sfs_torch.silhouette import coarse_normals  # noqa: E402

from _results import side_lightings, write_results  # noqa: E402

SCALES = (0.6, 0.8, 1.0, 1.25, 1.6, 2.0)
# every image's error at each of these depth scales, for a scale chosen once for all images
FINE_SCALES = (0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 1.6, 1.8, 2.0)
TILTS = (-1.0, -0.6, -0.3, 0.0, 0.3, 0.6, 1.0)
# depth scale c * (s / RELIEF_REFERENCE_SLOPE) ** p per image, s its normals' median slope
SLOPE_POWERS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25)
SLOPE_FACTORS = tuple(round(0.9 + 0.02 * i, 2) for i in range(36))
# the default's relief scale (1: none), then this many passes of the learnt relief prior
DEFAULT = PipelineConfig()
RELIEF_PRIOR_PASSES = (1, 2, 3)
# which (scale, tilt_x, tilt_y) of the grid each oracle may choose
FAMILIES = {"scale": lambda t: t[1] == t[2] == 0, "tilt": lambda t: t[0] == 1, "both": lambda t: True}


def against_default(errors: list, rows: list) -> dict:
    """Median and mean of one rule's per-image ``errors``, and how many images it makes better
    / worse than the default call (``rows[i]["default"]``) by more than 1 deg."""
    return {"median": statistics.median(errors), "mean": statistics.mean(errors),
            "better": sum(e < r["default"] - 1 for e, r in zip(errors, rows)),
            "worse": sum(e > r["default"] + 1 for e, r in zip(errors, rows))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=SCENE_SIDES, default="validation",
                        help="as benchmarks/tune.py's --side")
    parser.add_argument("--shapes", type=int, default=7)
    parser.add_argument("--lights", type=int, default=3)
    parser.add_argument("--first-light", type=int, default=0)
    parser.add_argument("--light-seed", type=int, default=0,
                        help="tuning sides: as benchmarks/tune.py's --light-seed")
    parser.add_argument("--call", default="{}", help="pipeline config overrides of the call, one JSON object")
    parser.add_argument("--exposure", type=float, default=None,
                        help="tuning sides: as benchmarks/tune.py's --exposure")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--degradation", default="exact", choices=list(DEGRADATIONS))
    parser.add_argument("--hypotheses", type=float, nargs="?", const=0.5, default=None, metavar="T",
                        help="also try the tilts (mu, nu) in {-T, 0, T}^2 as refined hypotheses (default T: 0.5)")
    parser.add_argument("--converging", action="store_true",
                        help="refine the hypotheses with the height in relief_refinement_unit image sides")
    parser.add_argument("--lighting-prior", type=float, nargs="+", default=None, metavar="W",
                        help="also pick the transform by photometric residual + W x lighting prior energy, per W")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "bas_relief.json")
    args = parser.parse_args()
    if args.hypotheses is not None and not args.hypotheses > 0:
        parser.error(f"--hypotheses must be positive, got {args.hypotheses}")
    if args.converging and args.hypotheses is None:
        parser.error("--converging refines the --hypotheses: give --hypotheses too")
    if args.lighting_prior is not None and not all(w >= 0 for w in args.lighting_prior):
        parser.error(f"--lighting-prior weights must be >= 0, got {args.lighting_prior}")
    lightings = side_lightings(parser, args)
    shapes = scene_shapes(args.shapes, args.side, sphere=False)
    cfg = resolve_config({"training": {"cache_forests": "never"}, **json.loads(args.call)})
    database = load_database(cfg.database, progress=False)
    grid = list(itertools.product(SCALES, TILTS, TILTS))
    prior = load_lighting_prior() if args.lighting_prior is not None else None
    relief_net = load_relief_net()
    rows = []
    for scene in synthetic_scenes(shapes, lightings, resolution=args.resolution,
                                  formation=DEGRADATIONS[args.degradation]):
        start = time.perf_counter()
        mask, image = scene.mask, scene.image

        def error(normals):
            return float(normal_metrics(normals * mask, scene.normals, mask).median[0])

        est = sfs_torch.estimate(image, mask, config=cfg, progress=False, database=database)
        errors = {t: error(bas_relief_normals(est.normals, *t)) for t in grid}
        row = {"case": scene.name, "prior": error(coarse_normals(mask)), "default": errors[(1.0, 0.0, 0.0)],
               "by_scale": {f"{lam:g}": error(bas_relief_normals(est.normals, lam, 0.0, 0.0)) for lam in FINE_SCALES}}
        row["slope"] = float(median_slope(est.normals, mask))
        relative = row["slope"] / RELIEF_REFERENCE_SLOPE
        row["by_slope"] = {f"{p:g}": [error(bas_relief_normals(est.normals, c * relative**p)) for c in SLOPE_FACTORS]
                           for p in SLOPE_POWERS}
        ruled = bas_relief_normals(est.normals, _relief_factor(est.normals[0], mask[0], DEFAULT)) * mask
        row["rule"] = error(ruled)
        for passes in RELIEF_PRIOR_PASSES:
            learnt = predict_relief(ruled, mask, relief_net, passes)
            row[f"prior_{passes}"] = error(apply_relief(ruled, mask, learnt))
        for name, member in FAMILIES.items():
            best = min((t for t in grid if member(t)), key=errors.get)
            row[name], row[f"{name}_transform"] = errors[best], best
        fitted = best_relief(est.normals, scene.normals, mask,
                            start=ReliefTransform(*(torch.tensor([v]) for v in row["both_transform"])))
        row["fitted"] = error(apply_relief(est.normals, mask, fitted))
        row["fitted_transform"] = (float(fitted.scale), float(fitted.tilt_x), float(fitted.tilt_y))
        line = (f"{scene.name:<44} default {row['default']:6.2f} | scale {row['scale']:6.2f} tilt {row['tilt']:6.2f}"
                f" both {row['both']:6.2f} at {row['both_transform']} fitted {row['fitted']:6.2f}")
        if args.hypotheses is not None:
            row["hypotheses"] = []
            hypothesis_refine = _converging_refine(cfg, mask) if args.converging else cfg.refine
            for mu, nu in itertools.product((-args.hypotheses, 0.0, args.hypotheses), repeat=2):
                start_normals = bas_relief_normals(est.normals, 1.0, mu, nu) * mask
                lighting = refit_lighting(image, mask, start_normals, valid=cfg.valid_refit).to(image.dtype)
                refined = refine_shape_and_lighting(image, mask, start_normals, lighting, confidence=est.confidence,
                                                    config=hypothesis_refine, silhouette=cfg.silhouette)
                row["hypotheses"].append({
                    "tilt": (mu, nu), "error": error(refined.normals), "loss": float(refined.loss_after[0]),
                    "photometric": float(photometric_residual(refined.normals, refined.lighting, image, mask)[0]),
                })
            for key in ("loss", "photometric"):
                picked = min(row["hypotheses"], key=lambda h: h[key])
                row[f"by_{key}"], row[f"by_{key}_tilt"] = picked["error"], picked["tilt"]
            line += f" | by loss {row['by_loss']:6.2f} at {row['by_loss_tilt']}"
        if args.lighting_prior is not None:
            normals = torch.cat([bas_relief_normals(est.normals, *t) * mask for t in grid])
            images, masks = image.expand(len(grid), -1, -1, -1), mask.expand(len(grid), -1, -1, -1)
            lightings_t = refit_lighting(images, masks, normals, valid=cfg.valid_refit).to(image.dtype)
            photometric = photometric_residual(normals, lightings_t, images, masks)
            photometric = photometric / photometric[grid.index((1.0, 0.0, 0.0))]
            energy = lighting_prior_energy(lightings_t, prior)
            for w in args.lighting_prior:
                picked = grid[int((photometric + w * energy).argmin())]
                row[f"by_prior_{w:g}"], row[f"by_prior_{w:g}_transform"] = errors[picked], picked
                line += f" | prior {w:g}: {errors[picked]:6.2f}"
        rows.append(row)
        print(line + f"  ({time.perf_counter() - start:.0f} s)", flush=True)

    columns = (["prior", "default", "scale", "tilt", "both", "fitted", "rule"]
               + [f"prior_{p}" for p in RELIEF_PRIOR_PASSES])
    if args.hypotheses is not None:
        columns += ["by_loss", "by_photometric"]
    for w in args.lighting_prior or ():
        columns.append(f"by_prior_{w:g}")
    labels = {"prior": "silhouette prior", "default": "the default call", "scale": "oracle scale",
              "tilt": "oracle tilt", "both": "oracle scale and tilt",
              "fitted": "oracle transform, fitted", "by_loss": "tilt by refinement loss",
              "by_photometric": "tilt by photometric residual", "rule": "the default's relief scale",
              **{f"prior_{p}": f"that + {p} relief-prior pass(es)" for p in RELIEF_PRIOR_PASSES}}
    labels.update({f"by_prior_{w:g}": f"by photometric + {w:g} x prior" for w in args.lighting_prior or ()})
    summary = {c: {"median": statistics.median(r[c] for r in rows), "mean": statistics.mean(r[c] for r in rows)}
               for c in columns}
    print(f"\n{len(rows)} images ({args.side} side, {args.degradation}), lighting estimated; "
          "median angular error per image (deg)")
    print(f"{'':<32}{'median':>8}{'mean':>8}")
    for c in columns:
        print(f"{labels[c]:<32}{summary[c]['median']:>8.2f}{summary[c]['mean']:>8.2f}")
    print("\none depth scale for every image (no oracle): median, mean, images better / worse than the default "
          "by > 1 deg")
    fixed = {lam: against_default([r["by_scale"][lam] for r in rows], rows) for lam in (f"{x:g}" for x in FINE_SCALES)}
    for lam, row in fixed.items():
        print(f"  lam {lam:<5}{row['median']:8.2f}{row['mean']:8.2f}{row['better']:5d} /{row['worse']:3d}")
    print(f"\ndepth scale c * (s / {RELIEF_REFERENCE_SLOPE}) ** p, s each image's median slope, c the best on the "
          "mean: median, mean, images better / worse than the default by > 1 deg")
    by_slope = {}
    for p in (f"{x:g}" for x in SLOPE_POWERS):
        best = min(range(len(SLOPE_FACTORS)), key=lambda i: statistics.mean(r["by_slope"][p][i] for r in rows))
        by_slope[p] = {"c": SLOPE_FACTORS[best], **against_default([r["by_slope"][p][best] for r in rows], rows)}
        row = by_slope[p]
        print(f"  p {p:<5}c {row['c']:<6g}{row['median']:8.2f}{row['mean']:8.2f}{row['better']:5d} /{row['worse']:3d}")
    write_results(args, summary=summary, fixed_scale=fixed, slope_scale=by_slope, rows=rows)


if __name__ == "__main__":
    main()
