"""Benchmark: VMFForest vs scikit-learn's RandomForestRegressor, both tables in one run.

1. The project's own training sets: the geometry database (``DatabaseConfig()``) shaded
   by natural lightings (``sfs_torch.lighting.natural_lightings()``), features as the
   pipeline computes them (``pipeline.training_set(..., noise_sigma=0.001, seed=0)``,
   23 features). Test rows are the database rows of held-out shapes (every 5th shape),
   so the forests train on ~120k of the ~150k rows.
2. A generic synthetic regression of unit vectors (``unit_regression``): normals that
   are a smooth non-linear function of half the features, the other half noise; a sweep
   over depth 12/15/18 x 20/30/40 features.

Both forests get the same trees / depth / max_features / min_samples_leaf / row share
(``ForestConfig`` defaults; sklearn draws its rows with replacement, ours without) and
all cores (``torch.set_num_threads(cores)``, which our ``n_jobs=None`` follows, and
sklearn's ``n_jobs=cores``). sklearn's 3-output mean
is normalised to a unit normal. Times are wall and CPU (process) seconds, each the best
of ``--repeat`` fits, ours and sklearn's alternating; the machine may be shared, so the
load average is printed with the tables.

    python benchmarks/forest.py            # both tables (~12 min on 2 busy cores)
    python benchmarks/forest.py --quick    # 30k training rows, one lighting, depth 12/18 x 20/40 features (~1 min)
    # the fit of another forest.py (e.g. the previous commit's) side by side with this one,
    # at 1 thread and at --threads:
    git show HEAD:sfs_torch/forest.py > /tmp/forest_old.py
    python benchmarks/forest.py --quick --baseline /tmp/forest_old.py
    python benchmarks/forest.py --defaults-sweep   # our hyper-parameters around the defaults
    python benchmarks/forest.py --threads-sweep    # our fit: tree threads (n_jobs) x intra-op threads
"""
from __future__ import annotations

import argparse
import importlib.util
import inspect
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

# Idle OpenMP threads spin by default; on a machine shared with other busy processes
# a spinning thread that is descheduled stalls every parallel op (we measured 1M-element
# adds going from 0.1 ms to 8 ms with 2 threads). Must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from sfs_torch.forest import ForestConfig, VMFForest  # noqa: E402

DEFAULTS = {k: v for k, v in vars(ForestConfig()).items() if k != "_target_"}
RESULTS = Path(__file__).parent / "results" / "forest.json"


# ------------------------------------------------------------------------------ data
def project_sets(n_lightings: int, max_train: int | None) -> list[dict]:
    """The pipeline's training sets for the first ``n_lightings`` natural lightings, split by shape."""
    from sfs_torch.geometry_db import DatabaseConfig, load_database
    from sfs_torch.lighting import natural_lightings
    from sfs_torch.pipeline import FeatureConfig, training_set
    from sfs_torch.texton import TextonConfig

    db = load_database(DatabaseConfig(), progress=False)
    test = db.shape_id % 5 == 0
    sets = []
    for name, sh in list(natural_lightings().items())[:n_lightings]:
        data = training_set(db, sh, FeatureConfig(), TextonConfig(), 0.001, 0)
        X, n = data.features, data.normals
        train = (~test).nonzero().squeeze(1)
        if max_train is not None and len(train) > max_train:
            train = train[torch.randperm(len(train), generator=torch.Generator().manual_seed(0))[:max_train].sort().values]
        sets.append({"name": name, "train": (X[train], n[train]), "test": (X[test], n[test]), "all": (X, n)})
    return sets


def unit_regression(n: int, n_features: int, seed: int, noise: float = 0.05):
    """``(X (n, F), normals (n, 3))``: unit vectors, a smooth function of the first F/2 features.

    ``normals = normalise(sin(X[:, :F/2] A) + (0, 0, 1.5) + noise)`` with ``X`` uniform in
    ``[0, 1]`` and a fixed random ``A`` per feature count (shared by train and test sets),
    scaled so that every informative feature matters about equally; the other half of
    the features is pure noise the forests must learn to ignore.
    """
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, n_features, generator=g)
    k = n_features // 2
    A = torch.randn(k, 3, generator=torch.Generator().manual_seed(1000 + n_features)) * (4.0 / math.sqrt(k))
    z = torch.sin(X[:, :k] @ A) + torch.tensor([0.0, 0.0, 1.5]) + noise * torch.randn(n, 3, generator=g)
    return X, torch.nn.functional.normalize(z, dim=1)


SH_CONST = (0.282095, 0.488603, 0.488603, 0.488603, 1.092548, 1.092548, 0.315392, 1.092548, 0.546274)
LIGHT = torch.tensor(
    [[0.80, 0.10, 0.35, 0.25, 0.05, 0.10, -0.05, 0.08, 0.02],
     [0.75, 0.25, 0.30, -0.05, -0.04, 0.06, -0.03, 0.02, 0.05],
     [0.70, 0.15, 0.30, -0.20, 0.03, -0.02, -0.06, -0.05, 0.01]]
)


def sh_basis(n: torch.Tensor) -> torch.Tensor:
    x, y, z = n.unbind(-1)
    c = SH_CONST
    return torch.stack(
        [torch.full_like(x, c[0]), c[1] * y, c[2] * z, c[3] * x, c[4] * x * y, c[5] * y * z,
         c[6] * (3 * z * z - 1), c[7] * x * z, c[8] * (x * x - y * y)], dim=-1
    )


def sfs_like(n: int, seed: int, noise: float = 0.01):
    """SfS-like synthetic rows (features (n, 23), normals (n, 3)), for ``--defaults-sweep``.

    Random visible normals shaded by a coloured SH lighting plus noise; silhouette-like
    features (a noisy relative contour distance and contour direction) and texton-like
    ones (noisy random filters of the shading of the normal's neighbourhood).
    """
    g = torch.Generator().manual_seed(seed)
    r = torch.rand(n, generator=g).sqrt() * 0.999
    phi = torch.rand(n, generator=g) * 2 * math.pi
    normals = torch.stack([r * phi.cos(), r * phi.sin(), (1 - r * r).sqrt()], 1)

    def shade(nrm):
        return (sh_basis(nrm) @ LIGHT.T + noise * torch.randn(n, 3, generator=g)).clamp(0, 1)

    colour = shade(normals)
    d_rel = (1 - r + 0.15 * torch.randn(n, generator=g)).clamp(0, 1)
    beta = phi + 0.4 * torch.randn(n, generator=g)
    silhouette = torch.stack([d_rel, beta.cos(), beta.sin()], 1)
    neighbours = []
    curvature = 0.3 * torch.randn(n, 1, generator=g)
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        step = torch.tensor([dx, dy, 0.0]) * 0.15 * (1 + curvature)
        neighbours.append(shade(torch.nn.functional.normalize(normals + step, dim=1)))
    patch = torch.cat([colour] + neighbours, 1)
    filters = torch.randn(15, 17, generator=torch.Generator().manual_seed(1234))
    texton = patch @ filters + 0.02 * torch.randn(n, 17, generator=g)
    return torch.cat([colour, silhouette, texton], 1), normals


# --------------------------------------------------------------------------- fitting
def median_angle(pred: torch.Tensor, truth: torch.Tensor) -> float:
    cos = (torch.nn.functional.normalize(pred, dim=1) * truth).sum(1).clamp(-1, 1)
    return float(torch.rad2deg(torch.acos(cos)).median())


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def fit_ours(cfg: dict, train, test, forest_cls=VMFForest) -> dict:
    forest = forest_cls(**cfg)
    _, wall, cpu = timed(lambda: forest.fit(*train))
    return {"fit_s": wall, "fit_cpu_s": cpu, "median_deg": median_angle(forest.predict(test[0]).mean, test[1]),
            "nodes": forest.child_.numel()}


def fit_sklearn(cfg: dict, train, test, threads: int) -> dict:
    from sklearn.ensemble import RandomForestRegressor

    rf = RandomForestRegressor(
        n_estimators=cfg["n_trees"], max_depth=cfg["max_depth"], min_samples_leaf=cfg["min_samples_leaf"],
        max_features=cfg["max_features"], max_samples=cfg["sample_fraction"], n_jobs=threads, random_state=0,
    )
    X, n = train[0].numpy(), train[1].numpy()
    _, wall, cpu = timed(lambda: rf.fit(X, n))
    pred = torch.from_numpy(rf.predict(test[0].numpy())).float()
    return {"fit_s": wall, "fit_cpu_s": cpu, "median_deg": median_angle(pred, test[1]),
            "nodes": sum(e.tree_.node_count for e in rf.estimators_)}


def best_of(runs: list[dict]) -> dict:
    best = dict(runs[0])
    best["fit_s"] = min(r["fit_s"] for r in runs)
    best["fit_cpu_s"] = min(r["fit_cpu_s"] for r in runs)
    return best


def compare(cfg: dict, train, test, threads: int, repeat: int) -> dict:
    ours, theirs = [], []
    for r in range(repeat):  # alternate the order, so that neither always runs second
        for which in (("ours", "sklearn") if r % 2 == 0 else ("sklearn", "ours")):
            if which == "ours":
                ours.append(fit_ours(cfg, train, test))
            else:
                theirs.append(fit_sklearn(cfg, train, test, threads))
    o, s = best_of(ours), best_of(theirs)
    return {"ours": o, "sklearn": s, "speedup": s["fit_s"] / o["fit_s"], "cpu_speedup": s["fit_cpu_s"] / o["fit_cpu_s"]}


def load_baseline(path: str):
    # imported as a module of the package, so that its relative imports resolve
    spec = importlib.util.spec_from_file_location("sfs_torch._baseline_forest", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module.VMFForest


def accepted(cls, cfg: dict) -> dict:
    """The part of ``cfg`` that ``cls`` takes (an older forest.py may lack newer options, e.g. ``n_jobs``)."""
    params = inspect.signature(cls).parameters
    return {k: v for k, v in cfg.items() if k in params}


def baseline_ratio(baseline_cls, cfg: dict, train, repeat: int) -> dict:
    times = {"baseline": [], "this": []}
    for r in range(repeat):
        for which in (("baseline", "this") if r % 2 == 0 else ("this", "baseline")):
            cls = baseline_cls if which == "baseline" else VMFForest
            forest = cls(**accepted(cls, cfg))
            _, wall, cpu = timed(lambda: forest.fit(*train))
            times[which].append((wall, cpu))
    out = {k: {"fit_s": min(w for w, _ in v), "fit_cpu_s": min(c for _, c in v),
               "fit_s_median": statistics.median(w for w, _ in v)} for k, v in times.items()}
    out["speedup"] = out["baseline"]["fit_s"] / out["this"]["fit_s"]
    out["cpu_speedup"] = out["baseline"]["fit_cpu_s"] / out["this"]["fit_cpu_s"]
    return out


# ------------------------------------------------------------------------------ main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30k training rows, one lighting, sweep corners")
    parser.add_argument("--threads", type=int, default=os.cpu_count(), help="torch threads and sklearn n_jobs")
    parser.add_argument("--repeat", type=int, default=2, help="fits per model and setting (the best is kept)")
    parser.add_argument("--baseline", help="another forest.py whose fit to time side by side with this one")
    parser.add_argument("--defaults-sweep", action="store_true", help="only sweep our hyper-parameters around the defaults")
    parser.add_argument("--threads-sweep", action="store_true", help="only time our fit over n_jobs x intra-op threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    repeat = args.repeat
    if args.defaults_sweep:
        return defaults_sweep(args.threads)
    if args.threads_sweep:
        return threads_sweep(args.threads, max(repeat, 5))

    n_train = 30_000 if args.quick else 150_000
    result = {"threads": args.threads, "repeat": repeat, "torch": torch.__version__, "config": DEFAULTS}
    sets = project_sets(1 if args.quick else 2, 30_000 if args.quick else None)
    # Warm-up at full size: the first large fit of a process pays for page faults of
    # fresh allocations.
    VMFForest(**DEFAULTS).fit(*sets[0]["train"])

    if args.baseline:
        baseline_cls = load_baseline(args.baseline)
        data = sets[0]["all"]  # all ~150k rows: the size the pipeline trains on
        baseline_cls(**accepted(baseline_cls, DEFAULTS)).fit(*data)
        reps = max(repeat, 3)
        result["baseline"] = []
        for threads in sorted({1, args.threads}):
            torch.set_num_threads(threads)
            b = {"file": args.baseline, "rows": len(data[0]), "lighting": sets[0]["name"], "threads": threads,
                 **baseline_ratio(baseline_cls, DEFAULTS, data, reps)}
            result["baseline"].append(b)
            print(f"baseline {args.baseline} vs this forest.py, default ForestConfig on {sets[0]['name']} "
                  f"({b['rows']} rows x 23), {threads} threads, best of {reps}: fit {b['baseline']['fit_s']:.2f} s -> "
                  f"{b['this']['fit_s']:.2f} s ({b['speedup']:.2f}x; CPU {b['baseline']['fit_cpu_s']:.2f} -> "
                  f"{b['this']['fit_cpu_s']:.2f} s, {b['cpu_speedup']:.2f}x; load {os.getloadavg()[0]:.1f})", flush=True)
        torch.set_num_threads(args.threads)

    project = []
    for s in sets:
        row = {"lighting": s["name"], "train_rows": len(s["train"][0]), "test_rows": len(s["test"][0]),
               **compare(DEFAULTS, s["train"], s["test"], args.threads, repeat)}
        project.append(row)
        print(_line(row["lighting"], row), flush=True)
    result["project"] = project

    depths, widths = ((12, 18), (20, 40)) if args.quick else ((12, 15, 18), (20, 30, 40))
    sweep = []
    for n_features in widths:
        train, test = unit_regression(n_train, n_features, seed=0), unit_regression(50_000, n_features, seed=1)
        for depth in depths:
            row = {"max_depth": depth, "features": n_features, "train_rows": n_train, "test_rows": 50_000,
                   **compare({**DEFAULTS, "max_depth": depth}, train, test, args.threads, repeat)}
            sweep.append(row)
            print(_line(f"depth {depth}, {n_features} features", row), flush=True)
    result["synthetic"] = sweep
    result["loadavg"] = os.getloadavg()

    print(f"\n{args.threads} threads / n_jobs, best of {repeat}; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores; defaults {DEFAULTS}\n")
    print("| lighting | train rows | VMFForest fit s (CPU s) | sklearn fit s (CPU s) | speed-up (CPU) | median error ours / sklearn |")
    print("|---|---|---|---|---|---|")
    for r in project:
        print(_row(f"{r['lighting']} | {r['train_rows']}", r))
    print()
    print("| depth | features | VMFForest fit s (CPU s) | sklearn fit s (CPU s) | speed-up (CPU) | median error ours / sklearn |")
    print("|---|---|---|---|---|---|")
    for r in sweep:
        print(_row(f"{r['max_depth']} | {r['features']}", r))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2))


def _line(name: str, r: dict) -> str:
    o, s = r["ours"], r["sklearn"]
    return (f"{name}: ours {o['fit_s']:.2f} s (cpu {o['fit_cpu_s']:.2f}) {o['median_deg']:.2f} deg {o['nodes']} nodes | "
            f"sklearn {s['fit_s']:.2f} s (cpu {s['fit_cpu_s']:.2f}) {s['median_deg']:.2f} deg {s['nodes']} nodes | "
            f"{r['speedup']:.2f}x (cpu {r['cpu_speedup']:.2f}x)")


def _row(head: str, r: dict) -> str:
    o, s = r["ours"], r["sklearn"]
    return (f"| {head} | {o['fit_s']:.2f} ({o['fit_cpu_s']:.2f}) | {s['fit_s']:.2f} ({s['fit_cpu_s']:.2f}) | "
            f"{r['speedup']:.1f}x ({r['cpu_speedup']:.1f}x) | {o['median_deg']:.2f} / {s['median_deg']:.2f} deg |")


def threads_sweep(threads: int, repeat: int) -> None:
    """Our default fit on the first project set (all ~150k rows) for each (n_jobs, intra-op threads).

    ``n_jobs`` trees grow at once in threads; each of those threads runs torch's
    intra-op parallelism with ``torch.get_num_threads()`` threads, which a worker takes
    from the process setting when it starts: so ``torch.set_num_threads(1)`` around a
    fit with ``n_jobs=threads`` is the "one intra-op thread per tree thread" option.
    """
    data = project_sets(1, None)[0]["all"]
    options = sorted({(jobs, intra) for jobs in (1, threads) for intra in (1, threads)})
    VMFForest(**DEFAULTS).fit(*data)
    times: dict = {o: [] for o in options}
    for r in range(repeat):  # alternate the order
        for jobs, intra in (options if r % 2 == 0 else options[::-1]):
            torch.set_num_threads(intra)
            forest = VMFForest(**{**DEFAULTS, "n_jobs": jobs})
            times[(jobs, intra)].append(timed(lambda: forest.fit(*data))[1:])
    torch.set_num_threads(threads)
    print(f"default ForestConfig, {len(data[0])} rows; best / median of {repeat} (wall s, CPU s); "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}; load average {os.getloadavg()[0]:.1f}")
    print("| n_jobs | intra-op threads | wall s best (median) | CPU s best (median) |\n|---|---|---|---|")
    for (jobs, intra), t in times.items():
        wall, cpu = [w for w, _ in t], [c for _, c in t]
        print(f"| {jobs} | {intra} | {min(wall):.2f} ({statistics.median(wall):.2f}) | "
              f"{min(cpu):.2f} ({statistics.median(cpu):.2f}) |")


def defaults_sweep(threads: int) -> None:
    """Our forest alone around the defaults (SfS-like synthetic data, 150k / 100k rows)."""
    train, test = sfs_like(150_000, seed=0), sfs_like(100_000, seed=1)
    VMFForest(**DEFAULTS).fit(*train)
    sweep = [{}, {"n_trees": 4}, {"n_trees": 8}, {"n_trees": 32}, {"max_depth": 10}, {"max_depth": 12}, {"max_depth": 16},
             {"max_features": 4}, {"max_features": 12}, {"n_bins": 32}, {"n_bins": 128},
             {"min_samples_leaf": 5}, {"min_samples_leaf": 20}]
    print(f"{threads} threads; load average {os.getloadavg()[0]:.1f}")
    for change in sweep:
        r = fit_ours({**DEFAULTS, **change}, train, test)
        print(f"{str(change or 'defaults'):<24} fit {r['fit_s']:.2f} s (cpu {r['fit_cpu_s']:.2f})  "
              f"median {r['median_deg']:.2f} deg  {r['nodes']} nodes", flush=True)


if __name__ == "__main__":
    main()
