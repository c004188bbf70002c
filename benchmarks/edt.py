"""Run time of the exact Euclidean distance transform: torch (every non-CPU device) vs SciPy.

``sfs_torch.silhouette`` sends CPU tensors to ``scipy.ndimage.distance_transform_edt``
and runs its own torch transform (``_edt_squared_torch``: distances and the feature
transform) on every other device. Timed here, side by side in one run, on the CPU:

- ``scipy``: ``distance_transform_edt(mask)``, distances only (what
  ``euclidean_distance_transform`` calls on the CPU);
- ``scipy+feat``: with ``return_indices=True`` (what the medial axis needs);
- ``torch``: ``_edt_squared_torch`` as it is (row pass by monotone-argmin halving,
  ``log2(W) + 1`` rounds of batched ops);
- ``torch loop``: the same transform with the row pass of before issue 13 (a Python loop
  over the columns with a data-dependent ``while`` that pops the parabola stacks), kept
  below as the reference;

and, where CUDA exists, ``torch`` and ``torch loop`` on the GPU (synchronised). Masks: a
disk of radius 0.4 W, and "blobs" (random noise opened by a 5x5 square: many small
components and holes, short distances) at each size, and a batch of 64 random ellipses
of 128^2 (one call, all rows at once, as the database build batches). Every torch result is checked against SciPy
(``max err``: largest difference of the squared distances, integers; 0 is exact).

Run: ``python benchmarks/edt.py [--sizes 256 512 1024] [--repeats 5] [--batch 64]``; prints a table and
writes ``benchmarks/results/edt.json``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Tuple

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy import ndimage  # noqa: E402
from torch import Tensor  # noqa: E402

from sfs_torch import silhouette  # noqa: E402


def loop_lower_envelope(f: Tensor, max_site: int = 0) -> Tuple[Tensor, Tensor]:
    """The row pass before issue 13 (Felzenszwalb-Huttenlocher, a loop over the columns)."""
    r, n = f.shape
    dev, dt = f.device, f.dtype
    ft = f.t().contiguous()
    stack_v = torch.zeros(n + 1, r, dtype=dt, device=dev)
    stack_h = torch.full((n + 1, r), math.inf, dtype=dt, device=dev)
    stack_z = torch.full((n + 1, r), math.inf, dtype=dt, device=dev)
    top = torch.full((r,), -1, dtype=torch.long, device=dev)
    v_top = torch.zeros(r, dtype=dt, device=dev)
    h_top = torch.full((r,), -math.inf, dtype=dt, device=dev)
    z_top = torch.full((r,), -math.inf, dtype=dt, device=dev)
    finite = torch.isfinite(ft)
    for q in range(n):
        hq = ft[q] + q * q
        act = finite[q]
        s = (hq - h_top) / (2 * (q - v_top)).clamp_min(1)
        pop = act & (s <= z_top)
        while bool(pop.any()):
            rows = torch.nonzero(pop).flatten()
            k = top[rows] - 1
            top[rows] = k
            v_top[rows] = stack_v[k, rows]
            h_top[rows] = stack_h[k, rows]
            z_top[rows] = stack_z[k, rows]
            s_rows = (hq[rows] - h_top[rows]) / (2 * (q - v_top[rows])).clamp_min(1)
            s[rows] = s_rows
            pop = torch.zeros_like(pop)
            pop[rows] = s_rows <= z_top[rows]
        s = torch.where(top < 0, -math.inf, s)
        top = top + act.long()
        v_top = torch.where(act, float(q), v_top)
        h_top = torch.where(act, hq, h_top)
        z_top = torch.where(act, s, z_top)
        at = torch.where(act, top, n).view(1, r)
        stack_v.scatter_(0, at, v_top.view(1, r))
        stack_h.scatter_(0, at, h_top.view(1, r))
        stack_z.scatter_(0, at, z_top.view(1, r))
    level = torch.arange(n + 1, device=dev).view(-1, 1)
    stack_z = torch.where(level > top, math.inf, stack_z)
    j = torch.arange(n, device=dev, dtype=dt).expand(r, n).contiguous()
    which = torch.searchsorted(stack_z[1:].t().contiguous(), j, right=True)
    arg = stack_v.t().gather(1, which)
    return (j - arg).square() + stack_h.t().gather(1, which) - arg.square(), arg.long()


def torch_loop(fg: Tensor):
    envelope = silhouette._lower_envelope
    silhouette._lower_envelope = loop_lower_envelope
    try:
        return silhouette._edt_squared_torch(fg)
    finally:
        silhouette._lower_envelope = envelope


def masks(size: int):
    """name -> (B, H, W) bool masks: one disk, one "blobs" mask."""
    j = np.arange(size) + 0.5 - size / 2
    u, v = np.meshgrid(j, j)
    rng = np.random.default_rng(size)
    blobs = ndimage.binary_opening(rng.random((size, size)) < 0.7, np.ones((5, 5)))
    return {"disk": (u * u + v * v < (0.4 * size) ** 2)[None], "blobs": blobs[None]}


def ellipses(count: int, size: int):
    """``count`` random ellipses of ``size``^2 (a batch like the database build's)."""
    rng = np.random.default_rng(count)
    j = np.arange(size) + 0.5 - size / 2
    u, v = np.meshgrid(j, j)
    a, b = rng.uniform(0.15, 0.45, (2, count, 1, 1)) * size
    cu, cv = rng.uniform(-0.1, 0.1, (2, count, 1, 1)) * size
    return (((u - cu) / a) ** 2 + ((v - cv) / b) ** 2) < 1


def timed(fn, sync):
    sync()
    t = time.perf_counter()
    out = fn()
    sync()
    return out, time.perf_counter() - t


def run(sizes, repeats, batch):
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows = []
    workloads = [(size, name, mask) for size in sizes for name, mask in masks(size).items()]
    if batch:
        workloads.append((128, f"{batch} ellipses", ellipses(batch, 128)))
    for size, name, mask in workloads:
        ref2 = np.rint(np.stack([ndimage.distance_transform_edt(m) for m in mask]) ** 2)
        methods = {
            ("cpu", "scipy"): lambda: [ndimage.distance_transform_edt(m) for m in mask],
            ("cpu", "scipy+feat"): lambda: [ndimage.distance_transform_edt(m, return_indices=True) for m in mask],
        }
        for device in devices:
            fg = torch.from_numpy(mask).to(device)
            methods[(device, "torch")] = lambda fg=fg: silhouette._edt_squared_torch(fg)
            methods[(device, "torch loop")] = lambda fg=fg: torch_loop(fg)
        times = {k: [] for k in methods}
        errors = {}
        for rep in range(repeats + 1):  # the first round warms up; methods alternate
            for (device, method), fn in methods.items():
                sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
                out, sec = timed(fn, sync)
                if rep:
                    times[(device, method)].append(sec)
                if method.startswith("torch") and rep == 0:
                    # squared distances are integers: compare them exactly
                    errors[(device, method)] = float(np.abs(out[0].cpu().double().numpy() - ref2).max())
        base = min(times[("cpu", "scipy")])
        for (device, method), ts in times.items():
            rows.append(dict(size=size, mask=name, device=device, method=method, best=min(ts),
                             median=float(np.median(ts)), vs_scipy=min(ts) / base,
                             max_abs_error_vs_scipy_squared=errors.get((device, method))))
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batch", type=int, default=64, help="also a batch of this many 128^2 masks (0: none)")
    args = parser.parse_args()
    rows = run(args.sizes, args.repeats, args.batch)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load {load:.2f}, "
          f"best of {args.repeats} alternating repeats after a warm-up")
    print(f"{'size':>5} {'mask':<11} {'device':<6} {'method':<11} {'best s':>8} {'median s':>8} {'/ scipy':>8} "
          f"{'max err':>8}")
    for r in rows:
        err = r["max_abs_error_vs_scipy_squared"]
        err = "" if err is None else f"{err:g}"
        print(f"{r['size']:>5} {r['mask']:<11} {r['device']:<6} {r['method']:<11} {r['best']:>8.4f} "
              f"{r['median']:>8.4f} {r['vs_scipy']:>7.1f}x {err:>8}")
    out = Path(__file__).parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(torch=torch.__version__, threads=torch.get_num_threads(), repeats=args.repeats, sizes=args.sizes,
                load_average=load, cuda=torch.cuda.get_device_name() if torch.cuda.is_available() else None)
    (out / "edt.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))


if __name__ == "__main__":
    main()
