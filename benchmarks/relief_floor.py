"""What the relief prior leaves when its input is right up to a bas-relief transform: its floor.

The pipeline's relief stage (``sfs_torch.relief_prior``) corrects one bas-relief transform
of an estimated orthographic normal field. This script gives it the best input it could
get: the TRUE normals of random views of one side's shapes, as they are and put through a
random transform (log scale and tilts Gaussian, by default with the spreads of the
transforms that take the pipeline's estimates closest to the truth on the tuning images,
docs/pipeline.md). No image, lighting or forest is involved, so what the corrected field
still errs is what the prior cannot tell from the shape alone: a floor under the relief
stage's error in the pipeline. Per shape and over all views, the median / mean of the
per-view median angular error (deg):

- ``transformed``: the transformed truth, before the prior;
- ``prior on transformed``: after the prior's correction of it;
- ``prior on truth``: the prior given the untransformed truth (0 for a prior that knew).

With ``--benchmark-views`` each shape is seen in the one view the accuracy benchmarks
(``tune.py``, ``bas_relief.py``) render it in, at 256 px: the median of ``prior on
truth`` over those views is then what the relief stage would leave of those benchmarks'
images (each view is one image per lighting) if the estimate before it were exact.

    python benchmarks/relief_floor.py --side validation
    python benchmarks/relief_floor.py --side test
    python benchmarks/relief_floor.py --side test --shapes 6 --benchmark-views
    python benchmarks/relief_floor.py --weights my_relief_prior.npz   # a network of one's own
"""
from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from sfs_torch.datasets import SCENE_SIDES, scene_shapes, synthetic_scenes  # noqa: E402
from sfs_torch.metrics import normal_metrics  # noqa: E402
from sfs_torch.relief_prior import ReliefTransform, apply_relief, load_relief_net, predict_relief  # noqa: E402
from sfs_torch.rendering import random_view_rotations, render_normals  # noqa: E402

from _results import write_results  # noqa: E402

COLUMNS = ("transformed", "prior on transformed", "prior on truth")


def summary(values: list) -> str:
    return f"{statistics.median(values):6.2f} / {statistics.mean(values):6.2f}"


def views(shape, args: argparse.Namespace, generator: torch.Generator):
    """``(truth, mask)`` of each view of ``shape``, batched: ``(1, 3, H, W), (1, 1, H, W)``."""
    if args.benchmark_views:
        ambient = torch.zeros(3, 9)
        ambient[:, 0] = 1.0  # the view's rotation depends on the shape alone; the image is not read
        for scene in synthetic_scenes([shape], [("ambient", ambient)], resolution=args.resolution):
            yield scene.normals.float(), scene.mask
        return
    for rotation in random_view_rotations(args.views, generator):
        view = render_normals(shape.mesh, rotation, args.resolution)
        yield view.normals[None].float(), view.mask[None]


def view_errors(truth: torch.Tensor, mask: torch.Tensor, transform: ReliefTransform, net, passes: int) -> dict:
    """The median error (deg) of one view under each of :data:`COLUMNS`."""
    def error(normals: torch.Tensor) -> float:
        return float(normal_metrics(normals, truth, mask).median[0])

    def corrected(normals: torch.Tensor) -> torch.Tensor:
        return apply_relief(normals, mask, predict_relief(normals, mask, net, passes))

    transformed = apply_relief(truth, mask, transform)
    return dict(zip(COLUMNS, (error(transformed), error(corrected(transformed)), error(corrected(truth)))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=SCENE_SIDES, default="validation")
    parser.add_argument("--shapes", type=int, default=10)
    parser.add_argument("--views", type=int, default=12, help="random views per shape")
    parser.add_argument("--resolution", type=int, default=None, help="default 128; 256 with --benchmark-views")
    parser.add_argument("--benchmark-views", action="store_true",
                        help="each shape in the one view of the accuracy benchmarks instead of --views random ones")
    parser.add_argument("--log-scale-std", type=float, default=0.26)
    parser.add_argument("--tilt-std", type=float, default=0.3)
    parser.add_argument("--passes", type=int, default=2, help="the prior's passes (the call's default: 2)")
    parser.add_argument("--weights", type=Path, default=None, help="a relief network's .npz (default: the shipped one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "relief_floor.json")
    args = parser.parse_args()
    if args.resolution is None:
        args.resolution = 256 if args.benchmark_views else 128
    for name in ("views", "resolution", "passes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.log_scale_std < 0 or args.tilt_std < 0:
        parser.error("--log-scale-std and --tilt-std must be >= 0")
    try:  # both checked before any view is rendered
        shapes = scene_shapes(args.shapes, args.side)
        net = load_relief_net(None if args.weights is None else str(args.weights))
    except ValueError as error:
        parser.error(str(error))
    generator = torch.Generator().manual_seed(args.seed)
    rows = []
    print(f"{'shape':<40}" + "".join(f"{c:>24}" for c in COLUMNS))
    for shape in shapes:
        errors = {c: [] for c in COLUMNS}
        for truth, mask in views(shape, args, generator):
            transform = ReliefTransform((torch.randn(1, generator=generator) * args.log_scale_std).exp(),
                                        torch.randn(1, generator=generator) * args.tilt_std,
                                        torch.randn(1, generator=generator) * args.tilt_std)
            for column, value in view_errors(truth, mask, transform, net, args.passes).items():
                errors[column].append(value)
        rows.append({"shape": shape.name, **errors})
        print(f"{shape.name:<40}" + "".join(f"{summary(errors[c]):>24}" for c in COLUMNS), flush=True)
    overall = {c: [e for row in rows for e in row[c]] for c in COLUMNS}
    print(f"{'all views':<40}" + "".join(f"{summary(overall[c]):>24}" for c in COLUMNS))
    write_results(args, summary={c: {"median": statistics.median(v), "mean": statistics.mean(v)}
                                 for c, v in overall.items()}, rows=rows)


if __name__ == "__main__":
    main()
