"""Depth accuracy and run time of the integrability solvers (paper Sec. 5, 9.2).

Surfaces with known depth, their exact normals (and, for the robust and convex variants,
corrupted normals), integrated by:

- ``l2``, ``l1``, ``perspective`` (L2 on log-depth), ``conv``: :mod:`sfs_torch.integrability`;
- ``scipy``: the same masked least-squares problem, assembled as a sparse matrix and
  solved directly (``scipy.sparse.linalg.spsolve``, one pixel pinned per component);
- ``dct``: Simchony et al.'s DCT Poisson solver over the full rectangle (gradients 0
  outside the mask);
- ``fc``: Frankot-Chellappa (FFT projection onto integrable fields) over the full rectangle.

Depth RMSE is in pixels over the mask after removing the best offset per connected
component (perspective: relative error in percent after the best scale).

A second table times the L1 solver (15 IRLS rounds) on the 256x256 sphere two ways in
the same run, alternating: with the coarse pseudo-inverse computed once per mask and
rescaled in later rounds (the solver as it is), and recomputed in float64 on the CPU for
every round (the solver before issue 13, rebuilt here by patching the module).

Run: ``python benchmarks/integration.py [--quick] [--sizes 256 512] [--only coarse]``;
writes ``benchmarks/results/integration.json`` (``--only coarse``:
``benchmarks/results/integration_coarse.json``).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import time
from pathlib import Path

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg
import torch

from sfs_torch import integrability
from sfs_torch.camera import pixel_grid
from sfs_torch.integrability import integrate_convex, integrate_normals

F64 = torch.float64


# ----------------------------------------------------------------------------- surfaces


def _normals(p, q):
    n = torch.stack([-p, -q, torch.ones_like(p)])
    return n / n.norm(dim=0)


def surfaces(size):
    """name -> (height z (H, W), normals (3, H, W), mask (H, W)), float64, orthographic."""
    u, v = pixel_grid(size, size, dtype=F64)
    x, y, s = u / (size / 2), v / (size / 2), size / 2
    out = {}
    # sphere cap on a disk
    r = 0.9
    mask = x * x + y * y < (0.9 * r) ** 2
    z = torch.sqrt((r * r - x * x - y * y).clamp_min(0))
    out["sphere"] = (s * z, torch.stack([x, y, z]) / r, mask)
    # Gaussian bumps on a blob with a hole and a second component
    bumps = [(0.3, 0.2, 0.25, 0.35), (-0.3, -0.1, 0.2, 0.25), (0.1, -0.4, 0.3, -0.2)]
    z = sum(a * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w)) for cx, cy, w, a in bumps)
    zx = sum(-a * (x - cx) / (w * w) * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w)) for cx, cy, w, a in bumps)
    zy = sum(-a * (y - cy) / (w * w) * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w)) for cx, cy, w, a in bumps)
    blob = (x / 0.75) ** 2 + (y / 0.6) ** 2 + 0.2 * torch.sin(5 * x) < 1
    hole = (x - 0.05) ** 2 + (y + 0.05) ** 2 < 0.1**2
    island = ((x - 0.8).abs() < 0.12) & ((y - 0.75).abs() < 0.15)
    out["bumps"] = (s * z, _normals(zx, zy), (blob & ~hole) | island)
    # a roof: crease along x = 0, tilted along y
    z = 0.5 - 0.6 * x.abs() + 0.2 * y
    out["ridge"] = (s * z, _normals(-0.6 * torch.sign(x), torch.full_like(x, 0.2)), (x.abs() < 0.8) & (y.abs() < 0.7))
    return {k: (z, torch.where(m, n, 0.0), m) for k, (z, n, m) in out.items()}


def perspective_sphere(size, focal):
    u, v = pixel_grid(size, size, dtype=F64)
    ray = torch.stack([u / focal, v / focal, -torch.ones_like(u)])
    # centre at distance 3 (world units), radius so that it spans ~70% of the image
    c = torch.tensor([0.3, -0.15, -3.0], dtype=F64)
    radius = 0.35 * size * 3.0 / focal
    rc, r2 = (ray * c[:, None, None]).sum(0), (ray * ray).sum(0)
    disc = rc * rc - r2 * (c @ c - radius**2)
    depth = (rc - disc.clamp_min(0).sqrt()) / r2
    point = depth * ray
    n = (point - c[:, None, None]) / radius
    mask = (disc > 0) & ((n * -point).sum(0) / point.norm(dim=0) > 0.15)
    return torch.where(mask, depth, 0.0), torch.where(mask, n, 0.0), mask


def corrupt(n, mask, fraction, seed):
    g = torch.Generator().manual_seed(seed)
    bad = (torch.rand(mask.shape, generator=g, dtype=F64) < fraction) & mask
    rnd = torch.randn(n.shape, generator=g, dtype=F64)
    rnd[2] = rnd[2].abs() + 0.2
    return torch.where(bad, rnd / rnd.norm(dim=0), n)


def candidates(n, mask, count, spread, seed):
    """The true normal in a random slot, the others perturbed (a stand-in for leaf samples)."""
    g = torch.Generator().manual_seed(seed)
    c = n + spread * torch.randn((count,) + n.shape, generator=g, dtype=F64)
    c[:, 2] = c[:, 2].abs()
    c = c / c.norm(dim=1, keepdim=True)
    slot = torch.randint(0, count, n.shape[1:], generator=g)
    c = torch.where(slot == torch.arange(count)[:, None, None, None], n, c)
    return torch.where(mask, c, 0.0)


# ----------------------------------------------------------------------------- references


def _targets(n, mask):
    """Edge targets of the masked problem (as in sfs_torch.integrability), numpy (H, W)."""
    nz = np.clip(n[2], 0.05, None)
    p, q = -n[0] / nz, -n[1] / nz
    ex = mask[:, 1:] & mask[:, :-1]
    ey = mask[1:, :] & mask[:-1, :]
    tx = np.where(ex, 0.5 * (p[:, 1:] + p[:, :-1]), 0.0)
    ty = np.where(ey, -0.5 * (q[1:, :] + q[:-1, :]), 0.0)
    return tx, ty, ex, ey


def scipy_reference(n, mask):
    """Masked least squares, sparse direct solve (one pixel pinned per component)."""
    h, w = mask.shape
    tx, ty, ex, ey = _targets(n, mask)
    idx = np.full((h, w), -1)
    idx[mask] = np.arange(mask.sum())
    rows, cols, vals, rhs = [], [], [], []
    k = 0
    for e, t, a, b in ((ex, tx, idx[:, :-1], idx[:, 1:]), (ey, ty, idx[:-1, :], idx[1:, :])):
        m = e.ravel()
        cnt = int(m.sum())
        r = np.arange(k, k + cnt)
        rows += [r, r]
        cols += [a.ravel()[m], b.ravel()[m]]
        vals += [-np.ones(cnt), np.ones(cnt)]
        rhs.append(t.ravel()[m])
        k += cnt
    d = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(k, int(mask.sum())))
    a = (d.T @ d).tocsc()
    b = d.T @ np.concatenate(rhs)
    labels, count = scipy.ndimage.label(mask)
    lab = labels[mask]
    first = np.array([np.flatnonzero(lab == c + 1)[0] for c in range(count)])
    keep = np.setdiff1d(np.arange(a.shape[0]), first)
    x = np.zeros(a.shape[0])
    x[keep] = scipy.sparse.linalg.spsolve(a[keep][:, keep].tocsc(), b[keep])
    out = np.zeros((h, w))
    out[mask] = x
    return out


def dct_poisson(n, mask):
    """Simchony et al.: Neumann Poisson over the full rectangle, by DCT."""
    h, w = mask.shape
    tx, ty, _, _ = _targets(n, mask)
    fx = np.pad(tx, ((0, 0), (0, 1)))
    fy = np.pad(ty, ((0, 1), (0, 0)))
    # b = D^T t on the full grid (the Neumann Laplacian's right-hand side)
    b = np.pad(fx[:, :-1], ((0, 0), (1, 0))) - fx + np.pad(fy[:-1, :], ((1, 0), (0, 0))) - fy
    lam = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    bh = scipy.fft.dctn(b, norm="ortho")
    lam[0, 0] = 1.0
    zh = bh / lam
    zh[0, 0] = 0.0
    return scipy.fft.idctn(zh, norm="ortho")


def frankot_chellappa(n, mask):
    """Frankot-Chellappa over the full rectangle (periodic), rows flipped so that v is up."""
    nz = np.clip(n[2], 0.05, None)
    p = np.where(mask, -n[0] / nz, 0.0)
    q = np.where(mask, n[1] / nz, 0.0)  # derivative along the row index (downwards) is -z_v
    h, w = mask.shape
    wx = 2 * np.pi * np.fft.fftfreq(w)[None, :]
    wy = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    denom = wx**2 + wy**2
    denom[0, 0] = 1.0
    zh = (-1j * wx * np.fft.fft2(p) - 1j * wy * np.fft.fft2(q)) / denom
    zh[0, 0] = 0.0
    return np.real(np.fft.ifft2(zh))


# ----------------------------------------------------------------------------- metrics


def rmse(depth, z, mask):
    labels, count = scipy.ndimage.label(mask)
    err = (depth - z)[mask]
    lab = labels[mask]
    for c in range(1, count + 1):
        err[lab == c] -= err[lab == c].mean()
    return float(np.sqrt(np.mean(err**2)))


def timed(fn, repeats):
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def _np(x):
    return x.detach().cpu().double().numpy()


def run(sizes, repeats):
    rows = []
    for size in sizes:
        for name, (z, n, mask) in surfaces(size).items():
            zn, mn = z.numpy(), mask.numpy()
            m = mask[None, None]
            for noise in ("clean", "outliers5%"):
                nin = n if noise == "clean" else corrupt(n, mask, 0.05, seed=size)
                n32 = nin.float()[None]
                methods = {
                    "l2": lambda: _np(integrate_normals(n32, m).depth[0, 0]),
                    "l1": lambda: _np(integrate_normals(n32, m, method="l1").depth[0, 0]),
                    "scipy": lambda: scipy_reference(nin.numpy(), mn),
                    "dct": lambda: dct_poisson(nin.numpy(), mn),
                    "fc": lambda: frankot_chellappa(nin.numpy(), mn),
                }
                for method, fn in methods.items():
                    depth, sec = timed(fn, repeats)
                    rows.append(dict(size=size, surface=name, input=noise, method=method, rmse=rmse(depth, zn, mn), seconds=sec))
            # convex combination of 4 candidates (truth + 3 perturbed by ~30 deg), vs L2 on their mean
            cand = candidates(n, mask, 4, 0.5, seed=size)
            mean = cand.sum(0)
            mean = mean / mean.norm(dim=0).clamp_min(1e-12)
            c32, mean32 = cand.float()[None], mean.float()[None]
            for method, fn in {
                "l2(mean)": lambda: _np(integrate_normals(mean32, m).depth[0, 0]),
                "conv": lambda: _np(integrate_convex(c32, m).depth[0, 0]),
            }.items():
                depth, sec = timed(fn, 1)
                rows.append(dict(size=size, surface=name, input="4 candidates", method=method, rmse=rmse(depth, zn, mn), seconds=sec))
        # perspective: a sphere seen by a pinhole camera (relative depth error, %)
        focal = 1.2 * size
        depth, n, mask = perspective_sphere(size, focal)
        dn, mn = depth.numpy(), mask.numpy()
        n32, m = n.float()[None], mask[None, None]
        for method, fn in {
            "perspective": lambda: _np(integrate_normals(n32, m, focal=focal).depth[0, 0]),
            "l2(ortho)": lambda: _np(integrate_normals(n32, m).depth[0, 0]),
        }.items():
            est, sec = timed(fn, repeats)
            if method == "perspective":
                ratio = np.exp(np.mean(np.log(dn[mn])) - np.mean(np.log(est[mn])))
                rel = np.abs(est[mn] * ratio - dn[mn]) / dn[mn]
                err = float(100 * np.sqrt(np.mean(rel**2)))
            else:
                # best affine fit of the orthographic height to the true depth, relative error
                a = np.stack([est[mn], np.ones(int(mn.sum()))], 1)
                coef, *_ = np.linalg.lstsq(a, dn[mn], rcond=None)
                err = float(100 * np.sqrt(np.mean(((a @ coef - dn[mn]) / dn[mn]) ** 2)))
            rows.append(dict(size=size, surface="persp-sphere", input="clean", method=method, rmse=err, seconds=sec, unit="% rel"))
    return rows


# ----------------------------------------------------------------------------- coarse inverse


@contextlib.contextmanager
def per_round_cpu_pinv():
    """The L1 solver as before issue 13: a float64 CPU pseudo-inverse in every IRLS round."""
    init, devices = integrability._Multigrid.__init__, integrability._FLOAT64_DEVICES

    def every_round(self, level, *args, coarse=None, **kwargs):
        init(self, level, *args, **kwargs)

    integrability._Multigrid.__init__, integrability._FLOAT64_DEVICES = every_round, ("cpu",)
    try:
        yield
    finally:
        integrability._Multigrid.__init__, integrability._FLOAT64_DEVICES = init, devices


@contextlib.contextmanager
def counting_pinv(stats):
    pinv = torch.linalg.pinv

    def counted(*args, **kwargs):
        t = time.perf_counter()
        out = pinv(*args, **kwargs)
        stats["pinv_calls"] += 1
        stats["pinv_seconds"] += time.perf_counter() - t
        return out

    torch.linalg.pinv = counted
    try:
        yield
    finally:
        torch.linalg.pinv = pinv


def coarse_inverse(size, repeats, devices):
    """L1 on the sphere: coarse inverse once per mask (now) vs every round on the CPU (before)."""
    z, n, mask = surfaces(size)["sphere"]
    rows = []
    for device in devices:
        for noise in ("clean", "outliers5%"):
            nin = (n if noise == "clean" else corrupt(n, mask, 0.05, seed=size)).float()[None].to(device)
            m = mask[None, None].to(device)
            variants = {"once per mask": contextlib.nullcontext, "every round, CPU": per_round_cpu_pinv}
            times = {k: [] for k in variants}
            stats = {k: dict(pinv_calls=0, pinv_seconds=0.0) for k in variants}
            depth = {}
            for rep in range(repeats + 1):  # the first round is a warm-up; variants alternate
                for name, variant in variants.items():
                    with variant(), counting_pinv(stats[name]):
                        if device.startswith("cuda"):
                            torch.cuda.synchronize()
                        t = time.perf_counter()
                        out = integrate_normals(nin, m, method="l1").depth[0, 0]
                        if device.startswith("cuda"):
                            torch.cuda.synchronize()
                        sec = time.perf_counter() - t
                    if rep:
                        times[name].append(sec)
                    depth[name] = _np(out)
            before = depth["every round, CPU"]
            for name in variants:
                calls = stats[name]["pinv_calls"] / (repeats + 1)
                rows.append(dict(
                    size=size, surface="sphere", input=noise, device=device, variant=name,
                    best=min(times[name]), median=statistics.median(times[name]),
                    pinv_calls=calls, pinv_seconds=stats[name]["pinv_seconds"] / (repeats + 1),
                    rmse=rmse(depth[name], z.numpy(), mask.numpy()),
                    max_diff_to_before=float(np.abs(depth[name] - before)[mask.numpy()].max()),
                ))
            rows[-2]["speedup_best"] = rows[-1]["best"] / rows[-2]["best"]
            rows[-2]["speedup_median"] = rows[-1]["median"] / rows[-2]["median"]
    return rows


def print_coarse(rows, repeats):
    print(f"\nL1 (15 IRLS rounds), coarse pseudo-inverse once per mask vs every round; "
          f"{repeats} alternating repeats after a warm-up")
    print(f"{'size':>5} {'input':<11} {'device':<6} {'variant':<17} {'pinv calls':>10} {'pinv s':>7} "
          f"{'best s':>7} {'median s':>8} {'before/now':>15} {'rmse px':>8} {'max |d-before|':>14}")
    for r in rows:
        ratio = f"{r['speedup_best']:.2f}x / {r['speedup_median']:.2f}x" if "speedup_best" in r else ""
        print(f"{r['size']:>5} {r['input']:<11} {r['device']:<6} {r['variant']:<17} {r['pinv_calls']:>10.0f} "
              f"{r['pinv_seconds']:>7.4f} {r['best']:>7.3f} {r['median']:>8.3f} {ratio:>15} {r['rmse']:>8.4f} "
              f"{r['max_diff_to_before']:>14.2e}")
    print("before/now: ratio of the best times / of the medians; pinv s: seconds per call inside torch.linalg.pinv")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one small size, no repeats")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", choices=["coarse"], help="only the coarse pseudo-inverse table")
    args = parser.parse_args()
    sizes, repeats = ([128], 1) if args.quick else (args.sizes, args.repeats)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    out = Path(__file__).parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(torch=torch.__version__, threads=torch.get_num_threads(), repeats=repeats, sizes=sizes)
    coarse = coarse_inverse(128 if args.quick else 256, max(repeats, 5), devices)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print_coarse(coarse, max(repeats, 5))
    if args.only == "coarse":
        (out / "integration_coarse.json").write_text(json.dumps(dict(meta=meta, coarse_inverse=coarse), indent=1))
        return
    rows = run(sizes, repeats)
    print(f"\nbest of {repeats} (after a warm-up)")
    print(f"{'size':>5} {'surface':<13} {'input':<13} {'method':<12} {'rmse':>10} {'seconds':>8}")
    for r in rows:
        unit = r.get("unit", "px")
        print(f"{r['size']:>5} {r['surface']:<13} {r['input']:<13} {r['method']:<12} {r['rmse']:>7.4f} {unit:<2} {r['seconds']:>8.3f}")
    (out / "integration.json").write_text(json.dumps(dict(meta=meta, rows=rows, coarse_inverse=coarse), indent=1))


if __name__ == "__main__":
    main()
