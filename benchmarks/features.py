"""Benchmark: silhouette and texton features (torch) beside scipy / scikit-image.

Stages, each timed for a batch of ``--batch`` 128x128 masks / images and for one
``--size`` x ``--size`` mask / image:

* EDT: ``euclidean_distance_transform`` vs ``scipy.ndimage.distance_transform_edt``
  (one call per image), and the largest difference between them;
* medial axis: ``medial_axis`` (pruned integer medial axis) vs
  ``skimage.morphology.medial_axis``;
* silhouette features: ``silhouette_features`` vs the same recipe with scipy/skimage
  (EDT, skimage medial axis, EDT to the axis, ``np.gradient`` of ``d_rel``);
* textons: ``texton_features`` vs ``skimage.color.rgb2lab`` + 17 ``scipy.ndimage`` filters.

Masks are unions of random ellipses. The machine is shared with other jobs: wall times
are noisy; each entry is the best of ``--repeat`` runs.

Training set (issue 13): ``sfs_torch.pipeline.training_set`` on the default geometry
database (150000 5 x 5 patches: shading, jitter, noise, clamp, textons), once with the
library's ``render_sh`` / ``texton_features`` and once with the reference formulation
they replaced (the 9-term basis ``einsum`` and kornia's ``rgb_to_lab`` of
``linear_rgb_to_rgb``, i.e. an sRGB round trip), called alternately, ``--train-repeat``
times each; medians, their ratio and the largest feature difference.

    python benchmarks/features.py            # 1000 x 128^2, one 1024^2, training set
    python benchmarks/features.py --quick    # 50 x 128^2, one 256^2, training set
    python benchmarks/features.py --training-set-only
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from unittest import mock

# Idle OpenMP threads spin by default, which stalls every parallel op on a shared machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from kornia.color import linear_rgb_to_rgb, rgb_to_lab  # noqa: E402
from scipy import ndimage  # noqa: E402
from skimage.color import rgb2lab  # noqa: E402
from skimage.morphology import medial_axis as sk_medial_axis  # noqa: E402

from sfs_torch import pipeline  # noqa: E402
from sfs_torch._checks import check_finite  # noqa: E402
from sfs_torch.datasets import evaluation_lightings  # noqa: E402
from sfs_torch.geometry_db import DatabaseConfig, load_database  # noqa: E402
from sfs_torch.lighting import sh_basis  # noqa: E402
from sfs_torch.silhouette import euclidean_distance_transform, medial_axis, silhouette_features  # noqa: E402
from sfs_torch.texton import TextonConfig, texton_features, texton_filter_bank  # noqa: E402


def random_masks(n: int, size: int, seed: int) -> np.ndarray:
    """(n, size, size) bool: unions of 1-4 random ellipses."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] / size
    masks = np.zeros((n, size, size), bool)
    for i in range(n):
        for _ in range(rng.integers(1, 5)):
            cy, cx = rng.uniform(0.25, 0.75, 2)
            ry, rx = rng.uniform(0.08, 0.3, 2)
            t = rng.uniform(0, np.pi)
            dy, dx = yy - cy, xx - cx
            a, b = dx * np.cos(t) + dy * np.sin(t), -dx * np.sin(t) + dy * np.cos(t)
            masks[i] |= (a / rx) ** 2 + (b / ry) ** 2 < 1
    return masks


def reference_silhouette_features(mask: np.ndarray) -> np.ndarray:
    """The same recipe with scipy / skimage on one (H, W) mask: (3, H, W)."""
    d_b = ndimage.distance_transform_edt(mask) - 0.5
    axis = sk_medial_axis(mask)
    d_m = ndimage.distance_transform_edt(~axis)
    d_rel = np.where(mask, np.clip(d_b, 0, None) / np.maximum(d_b + d_m, 1e-6), 0.0)
    gy, gx = np.gradient(d_rel)
    beta = np.arctan2(gy, -gx)  # rows grow downwards, y up
    return np.stack([d_rel, np.cos(beta) * mask, np.sin(beta) * mask])


def reference_textons(image: np.ndarray) -> np.ndarray:
    """(3, H, W) linear RGB -> (17, H, W) with skimage Lab and scipy.ndimage filters."""
    srgb = np.where(image > 0.0031308, 1.055 * np.clip(image, 0.0031308, None) ** (1 / 2.4) - 0.055, 12.92 * image)
    lab = rgb2lab(srgb.transpose(1, 2, 0)).transpose(2, 0, 1)
    kw = dict(mode="constant", radius=2)
    out = [ndimage.gaussian_filter(lab[c], s, **kw) for c in range(3) for s in (1, 2, 4)]
    out += [ndimage.gaussian_laplace(lab[0], s, **kw) for s in (1, 2, 4, 8)]
    for s in (2, 4):
        out += [ndimage.gaussian_filter(lab[0], s, order=(0, 1), **kw), -ndimage.gaussian_filter(lab[0], s, order=(1, 0), **kw)]
    return np.stack(out)


def reference_render_sh(normals: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
    """The 9-term basis sum: (B, 3, H, W) normals, (B, 3, 9) lighting -> (B, 3, H, W)."""
    return torch.einsum("bck,bkhw->bchw", sh.to(normals.dtype), sh_basis(normals))


def reference_texton_features(image, mask=None, *, kernel_size=5, padding="same"):
    """kornia's sRGB round trip to Lab, then the bank: (B, 3, H, W) -> (B, 17, H', W').

    With the library's input checks (finite image, boolean mask), as the replaced code had.
    """
    check_finite(image, "image")
    if mask is not None:
        image = torch.where(mask.bool(), image, torch.zeros((), dtype=image.dtype))
    lab = rgb_to_lab(linear_rgb_to_rgb(image))
    weights = texton_filter_bank(kernel_size, device=image.device, dtype=image.dtype)
    return F.conv2d(lab, weights, padding=kernel_size // 2 if padding == "same" else 0)


def run_training_set(repeat: int) -> list:
    """pipeline.training_set with the library's functions vs the reference ones, alternately."""
    db = load_database(DatabaseConfig())
    sh = evaluation_lightings(1)[0][1]
    args = (db, sh, pipeline.FeatureConfig(), TextonConfig(), 0.001, 0, 0.3, 0.05)

    def ours():
        return pipeline.training_set(*args)

    def reference():
        with mock.patch.object(pipeline, "render_sh", reference_render_sh), \
                mock.patch.object(pipeline, "texton_features", reference_texton_features):
            return pipeline.training_set(*args)

    diff = float((ours().features - reference().features).abs().max())
    times = {"torch": [], "reference": []}
    for _ in range(repeat):
        for name, fn in (("reference", reference), ("torch", ours)):
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    t_ours, t_ref = statistics.median(times["torch"]), statistics.median(times["reference"])
    name = f"{db.normals.shape[0]}x{db.normals.shape[-1]}^2"
    note = f"median of {repeat}, alternating; max |diff| features {diff:.1e}"
    print(f"{name:>14} {'training_set':>20} {t_ours:10.3f} {t_ref:10.3f} {t_ref / t_ours:8.2f}  {note}", flush=True)
    return [dict(workload=name, stage="training_set", torch_s=t_ours, reference_s=t_ref, speedup=t_ref / t_ours,
                 note=note, torch_times=times["torch"], reference_times=times["reference"], max_abs_diff=diff)]


def best_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def run_workload(name: str, masks: np.ndarray, repeat: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    images = rng.random((len(masks), 3) + masks.shape[1:]) * masks[:, None]
    m = torch.from_numpy(masks)[:, None]
    img = torch.from_numpy(images).float()
    rows = []

    def add(stage, ours, ref, note=""):
        t_ours, t_ref = best_time(ours, repeat), best_time(ref, repeat)
        rows.append(dict(workload=name, stage=stage, torch_s=t_ours, reference_s=t_ref, speedup=t_ref / t_ours, note=note))
        print(f"{name:>14} {stage:>20} {t_ours:10.3f} {t_ref:10.3f} {t_ref / t_ours:8.2f}  {note}", flush=True)

    edt = euclidean_distance_transform(m)[:, 0].numpy()
    ref = np.stack([ndimage.distance_transform_edt(x) for x in masks])
    add("EDT", lambda: euclidean_distance_transform(m), lambda: [ndimage.distance_transform_edt(x) for x in masks],
        f"max |diff| {np.abs(edt - ref).max():.1e} px")
    add("medial axis", lambda: medial_axis(m), lambda: [sk_medial_axis(x) for x in masks], "skimage: unpruned")
    add("silhouette features", lambda: silhouette_features(m), lambda: [reference_silhouette_features(x) for x in masks])
    add("textons", lambda: texton_features(img, m), lambda: [reference_textons(x * y) for x, y in zip(images, masks)])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="50 small masks and one 256^2 (well under a minute)")
    parser.add_argument("--batch", type=int, default=None, help="number of 128x128 masks (default 1000, quick 50)")
    parser.add_argument("--size", type=int, default=None, help="side of the single large mask (default 1024, quick 256)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (scipy is single-threaded)")
    parser.add_argument("--repeat", type=int, default=None, help="best of this many runs (default 2, quick 1)")
    parser.add_argument("--train-repeat", type=int, default=5, help="training_set runs of each implementation")
    parser.add_argument("--training-set-only", action="store_true", help="only the training_set comparison")
    parser.add_argument("--threads-training-set", type=int, default=None,
                        help="torch threads for the training_set comparison (default: torch's own)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON (default results/features.json, or features_training_set.json)")
    args = parser.parse_args()
    batch = args.batch or (50 if args.quick else 1000)
    size = args.size or (256 if args.quick else 1024)
    repeat = args.repeat or (1 if args.quick else 2)
    default_threads = torch.get_num_threads()
    rows = []
    if not args.training_set_only:
        torch.set_num_threads(args.threads)
        print(f"torch {torch.__version__}, {args.threads} thread(s); times in seconds, best of {repeat}")
        print(f"{'workload':>14} {'stage':>20} {'torch':>10} {'scipy/sk':>10} {'speedup':>8}")
        rows += run_workload(f"{batch}x128^2", random_masks(batch, 128, 0), repeat, 1)
        rows += run_workload(f"1x{size}^2", random_masks(1, size, 2), repeat, 3)
    train_threads = args.threads_training_set or default_threads
    torch.set_num_threads(train_threads)
    print(f"training set: torch {torch.__version__}, {train_threads} thread(s); seconds, median of {args.train_repeat}")
    print(f"{'workload':>14} {'stage':>20} {'torch':>10} {'reference':>10} {'speedup':>8}")
    rows += run_training_set(args.train_repeat)

    if args.out is None:
        name = "features_training_set.json" if args.training_set_only else "features.json"
        args.out = Path(__file__).parent / "results" / name
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(torch=torch.__version__, threads=None if args.training_set_only else args.threads,
                repeat=repeat, batch=batch, size=size,
                training_set_threads=train_threads, train_repeat=args.train_repeat,
                load_average=os.getloadavg(), cpu_count=os.cpu_count(), note="shared machine: wall times are noisy")
    args.out.write_text(json.dumps(dict(meta=meta, results=rows), indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
