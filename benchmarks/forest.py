"""Benchmark: VMFForest vs scikit-learn's RandomForestRegressor on synthetic SfS-like data.

Data: random visible normals shaded by a coloured 9-term SH lighting (plus noise), with
silhouette-like features (a noisy relative contour distance and contour direction) and
texton-like features (noisy random filters of the shading of the normal's neighbourhood):
23 features, as in the method. Train and test rows are drawn independently.

Both forests get the same trees / depth / max_features / min_samples_leaf / row share
(sklearn draws its 90% with replacement, ours without). sklearn's 3-output mean is
normalised to a unit normal. Timings are taken with 1 and 2 threads; the machine is
shared with other jobs, so wall times are noisy and 2-thread numbers suffer most.

    python benchmarks/forest.py            # full: 150k train rows, sweep + sklearn
    python benchmarks/forest.py --quick    # 30k rows, one configuration
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

# Idle OpenMP threads spin by default; on a machine shared with other busy processes
# a spinning thread that is descheduled stalls every parallel op (we measured 1M-element
# adds going from 0.1 ms to 8 ms with 2 threads). Must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from sfs_torch.forest import ForestConfig, VMFForest

SH_CONST = (0.282095, 0.488603, 0.488603, 0.488603, 1.092548, 1.092548, 0.315392, 1.092548, 0.546274)


def sh_basis(n: torch.Tensor) -> torch.Tensor:
    x, y, z = n.unbind(-1)
    c = SH_CONST
    return torch.stack(
        [torch.full_like(x, c[0]), c[1] * y, c[2] * z, c[3] * x, c[4] * x * y, c[5] * y * z,
         c[6] * (3 * z * z - 1), c[7] * x * z, c[8] * (x * x - y * y)], dim=-1
    )


LIGHT = torch.tensor(
    [[0.80, 0.10, 0.35, 0.25, 0.05, 0.10, -0.05, 0.08, 0.02],
     [0.75, 0.25, 0.30, -0.05, -0.04, 0.06, -0.03, 0.02, 0.05],
     [0.70, 0.15, 0.30, -0.20, 0.03, -0.02, -0.06, -0.05, 0.01]]
)


def make_data(n: int, seed: int, noise: float = 0.01):
    """(features (n, 23), normals (n, 3)) for the fixed lighting ``LIGHT``."""
    g = torch.Generator().manual_seed(seed)
    # normals of a sphere seen orthographically: uniform in the image disk
    r = torch.rand(n, generator=g).sqrt() * 0.999
    phi = torch.rand(n, generator=g) * 2 * math.pi
    normals = torch.stack([r * phi.cos(), r * phi.sin(), (1 - r * r).sqrt()], 1)

    def shade(nrm):
        return (sh_basis(nrm) @ LIGHT.T + noise * torch.randn(n, 3, generator=g)).clamp(0, 1)

    colour = shade(normals)
    # silhouette-like: relative distance and contour direction, corrupted because real
    # shapes are not spheres
    d_rel = (1 - r + 0.15 * torch.randn(n, generator=g)).clamp(0, 1)
    beta = phi + 0.4 * torch.randn(n, generator=g)
    silhouette = torch.stack([d_rel, beta.cos(), beta.sin()], 1)
    # texton-like: random filters of the shading of 4 neighbouring normals (local curvature)
    neighbours = []
    curvature = 0.3 * torch.randn(n, 1, generator=g)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        step = torch.tensor([dx, dy, 0.0]) * 0.15 * (1 + curvature)
        neighbours.append(shade(torch.nn.functional.normalize(normals + step, dim=1)))
    patch = torch.cat([colour] + neighbours, 1)  # (n, 15)
    filters = torch.randn(15, 17, generator=torch.Generator().manual_seed(1234))
    texton = patch @ filters + 0.02 * torch.randn(n, 17, generator=g)
    return torch.cat([colour, silhouette, texton], 1), normals


def median_angle(pred: torch.Tensor, truth: torch.Tensor) -> float:
    cos = (torch.nn.functional.normalize(pred, dim=1) * truth).sum(1).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos)).median())


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def run_ours(cfg: dict, data, threads: int) -> dict:
    torch.set_num_threads(threads)
    (X, n), (Xt, nt) = data
    forest = VMFForest(**cfg)
    _, fit_wall, fit_cpu = timed(lambda: forest.fit(X, n))
    pred, pred_wall, pred_cpu = timed(lambda: forest.predict(Xt))
    return {"model": "VMFForest", "threads": threads, **cfg, "fit_s": fit_wall, "fit_cpu_s": fit_cpu,
            "predict_s": pred_wall, "predict_cpu_s": pred_cpu, "median_deg": median_angle(pred.mean, nt),
            "nodes": forest.child_.numel()}


def run_sklearn(cfg: dict, data, threads: int) -> dict:
    from sklearn.ensemble import RandomForestRegressor

    (X, n), (Xt, nt) = data
    rf = RandomForestRegressor(
        n_estimators=cfg["n_trees"], max_depth=cfg["max_depth"], min_samples_leaf=cfg["min_samples_leaf"],
        max_features=cfg["max_features"], max_samples=cfg["sample_fraction"], n_jobs=threads, random_state=0,
    )
    Xn, nn_, Xtn = X.numpy(), n.numpy(), Xt.numpy()
    _, fit_wall, fit_cpu = timed(lambda: rf.fit(Xn, nn_))
    pred, pred_wall, pred_cpu = timed(lambda: rf.predict(Xtn))
    return {"model": "sklearn RF", "threads": threads, **cfg, "fit_s": fit_wall, "fit_cpu_s": fit_cpu,
            "predict_s": pred_wall, "predict_cpu_s": pred_cpu,
            "median_deg": median_angle(torch.from_numpy(pred).float(), nt),
            "nodes": sum(e.tree_.node_count for e in rf.estimators_)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30k rows, one configuration (< 1 min)")
    parser.add_argument("--train", type=int, default=None, help="training rows (default 150k, quick 30k)")
    args = parser.parse_args()
    n_train = args.train or (30_000 if args.quick else 150_000)
    data = (make_data(n_train, seed=0), make_data(100_000, seed=1))
    base = {k: v for k, v in vars(ForestConfig()).items() if k != "_target_"}

    # Warm-up at full size: the first large fit of a process pays ~0.7 s of page faults
    # for fresh allocations (measured: 3.3 s first vs 2.6 s later for the same forest).
    VMFForest(**base).fit(*data[0]).predict(data[1][0])
    rows = []
    if args.quick:
        rows.append(run_ours(base, data, threads=1))
        rows.append(run_sklearn(base, data, threads=1))
    else:
        sweep = [
            {},
            {"n_trees": 4}, {"n_trees": 16},
            {"max_depth": 10}, {"max_depth": 12}, {"max_depth": 16},
            {"max_features": 4}, {"max_features": 12},
            {"n_bins": 32}, {"n_bins": 128},
            {"min_samples_leaf": 5}, {"min_samples_leaf": 20},
        ]
        for change in sweep:
            rows.append(run_ours({**base, **change}, data, threads=1))
            print(_format(rows[-1]), flush=True)
        for threads in (1, 2):
            if threads == 2:
                rows.append(run_ours(base, data, threads=2))
            rows.append(run_sklearn(base, data, threads=threads))
        rows.append(run_sklearn({**base, "min_samples_leaf": 5}, data, threads=1))

    print()
    print(f"train rows {n_train}, test rows 100000, 23 features; load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} cores (shared machine)")
    print(_header())
    for row in rows:
        print(_format(row))
    ratios = []
    for s in (r for r in rows if r["model"] == "sklearn RF"):
        ours = [r for r in rows if r["model"] == "VMFForest" and r["threads"] == s["threads"]
                and all(r[k] == s[k] for k in base)]
        if ours:
            o = ours[-1]
            ratios.append({"threads": s["threads"], **{k: s[k] for k in ("max_depth", "min_samples_leaf")},
                           "train_speedup": s["fit_s"] / o["fit_s"], "train_cpu_speedup": s["fit_cpu_s"] / o["fit_cpu_s"],
                           "predict_speedup": s["predict_s"] / o["predict_s"],
                           "median_deg_ours": o["median_deg"], "median_deg_sklearn": s["median_deg"]})
    for r in ratios:
        print(f"threads {r['threads']} depth {r['max_depth']} leaf {r['min_samples_leaf']}: train {r['train_speedup']:.2f}x faster "
              f"(cpu time {r['train_cpu_speedup']:.2f}x), predict {r['predict_speedup']:.2f}x, "
              f"median error {r['median_deg_ours']:.2f} vs {r['median_deg_sklearn']:.2f} deg")
    out = Path(__file__).parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    result = {"train_rows": n_train, "test_rows": 100_000, "features": 23, "loadavg": os.getloadavg(),
              "torch": torch.__version__, "rows": rows, "ratios": ratios}
    (out / "forest.json").write_text(json.dumps(result, indent=2))


def _header() -> str:
    return (f"{'model':<11} {'thr':>3} {'T':>3} {'depth':>5} {'m':>3} {'bins':>4} {'leaf':>4} "
            f"{'fit s':>7} {'fit cpu':>7} {'pred s':>7} {'median deg':>10} {'nodes':>8}")


def _format(r: dict) -> str:
    return (f"{r['model']:<11} {r['threads']:>3} {r['n_trees']:>3} {r['max_depth']:>5} {r['max_features']:>3} "
            f"{r['n_bins']:>4} {r['min_samples_leaf']:>4} {r['fit_s']:>7.2f} {r['fit_cpu_s']:>7.2f} "
            f"{r['predict_s']:>7.3f} {r['median_deg']:>10.2f} {r['nodes']:>8}")


if __name__ == "__main__":
    main()
