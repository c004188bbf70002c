"""The preview renderers side by side: pyrender (OpenGL) against the Embree ray caster.

Both draw the same mesh from the same view with the same camera, and shade the normals
with the same SH lighting (:func:`sfs_torch.preview.render_shaded`). Meshes:

- ``sphere``: an icosphere (subdivision 5, 10k vertices), frontal, orthographic; its mask is
  also scored against the analytic disk;
- ``sphere-persp``: the same, perspective with f = 1.2 x resolution;
- ``blobby``: a procedural shape of the training database (:func:`sfs_torch.shapes.blobby_mesh`),
  from the novel view's default viewpoint (azimuth 35, elevation 20 degrees);
- ``depth-mesh``: what ``novel_view.png`` draws: the mesh of a 256x256 depth map (a bumpy
  sphere cap, one vertex per pixel, 100k faces, open at its rim) from that viewpoint.

Scores, on the pixels both masks hold: the angle between the two normal maps (median,
99th percentile, share over 5 degrees), the shading's absolute difference (linear, median
and 99th percentile) and, on every pixel, the share whose 8-bit sRGB preview values
differ by more than 2 levels. Timing: median of ``--repeats`` warm renders per view (the
context made and the shaders compiled beforehand), wall-clock and CPU time of the whole
process (llvmpipe rasterises on threads of its own); ``cold`` is the first pyrender call
of the process (context + shader compilation + one render).

Run: ``python benchmarks/renderers.py [--quick] [--sizes 256 512] [--repeats 5]``; writes
``benchmarks/results/renderers.json``. Without an OpenGL context only the ray caster is timed.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

# spinning OpenMP threads inflate every timing on a loaded machine (docs/forest.md)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402

from sfs_torch.integrability import depth_to_mesh  # noqa: E402
from sfs_torch.io import linear_to_srgb  # noqa: E402
from sfs_torch.lighting import natural_lightings  # noqa: E402
from sfs_torch.novel_view import view_rotation  # noqa: E402
from sfs_torch.preview import gl_context, render_shaded  # noqa: E402
from sfs_torch.shapes import blobby_mesh, normalize_mesh  # noqa: E402


def unit(mesh):
    """Centred and scaled into the unit sphere, as render_novel_view does."""
    mesh = mesh.copy()
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2)
    mesh.apply_scale(1.0 / np.linalg.norm(mesh.vertices, axis=1).max())
    return mesh


def depth_surface(size=256):
    """A bumpy sphere cap as a depth map mesh (the integrated surfaces' kind), in pixels."""
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    radius = 0.45 * size
    r2 = (xx**2 + yy**2) / radius**2
    mask = r2 < 1
    bumps = 0.04 * size * torch.sin(xx / size * 14) * torch.cos(yy / size * 11)
    depth = (radius * torch.sqrt((1 - r2).clamp_min(0)) + bumps) * mask
    return depth_to_mesh(depth, mask)


def scenes():
    """name -> (unit mesh, rotation, focal factor or None)."""
    sphere = trimesh.creation.icosphere(subdivisions=5)
    novel = view_rotation(35.0, 20.0).numpy()
    return {
        "sphere": (sphere, np.eye(3), None),
        "sphere-persp": (sphere, np.eye(3), 1.2),
        "blobby": (normalize_mesh(blobby_mesh(3)), novel, None),
        "depth-mesh": (unit(depth_surface()), novel, None),
    }


def timed(fn, repeats):
    """The result, and the median wall-clock and CPU (all threads of the process) milliseconds."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return out, 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def disk(size):
    c = (np.arange(size) + 0.5 - size / 2) / (0.9 * size / 2)
    yy, xx = np.meshgrid(-c, c, indexing="ij")
    return xx**2 + yy**2 < 1


def compare(a, b):
    """Scores of pyrender's view ``a`` against the ray caster's ``b``."""
    ma, mb = a.mask[0].numpy(), b.mask[0].numpy()
    both = ma & mb
    cos = (a.normals.numpy() * b.normals.numpy()).sum(0)[both]
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    shade = np.abs(a.image.numpy() - b.image.numpy())[:, both]
    levels = np.abs(np.round(255 * linear_to_srgb(a.image).numpy()) - np.round(255 * linear_to_srgb(b.image).numpy()))
    return dict(
        mask_agreement=float((ma == mb).mean()),
        mask_pixels_differing=int((ma != mb).sum()),
        angle_median_deg=float(np.median(angle)),
        angle_p99_deg=float(np.percentile(angle, 99)),
        angle_over_5deg=float((angle > 5).mean()),
        shading_median=float(np.median(shade)),
        shading_p99=float(np.percentile(shade, 99)),
        srgb_over_2_levels=float((levels.max(0) > 2).mean()),
    )


def run(sizes, repeats):
    sh = natural_lightings(0.7)["grace_cathedral"]
    t = time.perf_counter()
    context = gl_context()  # makes the context: the cold start's first part
    cold = None
    rows = []
    for size in sizes:
        for name, (mesh, rot, focal_factor) in scenes().items():
            focal = None if focal_factor is None else focal_factor * size
            row = dict(size=size, mesh=name, vertices=len(mesh.vertices), faces=len(mesh.faces))

            def draw(renderer):
                return render_shaded(mesh, sh, rot, size, renderer=renderer, focal=focal, background=0.0)

            if context.available and cold is None:
                draw("pyrender")
                cold = time.perf_counter() - t
            ray, row["embree_ms"], row["embree_cpu_ms"] = timed(lambda: draw("embree"), repeats)
            if name == "sphere":
                row["embree_vs_disk_pixels"] = int((ray.mask[0].numpy() != disk(size)).sum())
            if context.available:
                gl, row["pyrender_ms"], row["pyrender_cpu_ms"] = timed(lambda: draw("pyrender"), repeats)
                row.update(compare(gl, ray))
                if name == "sphere":
                    row["pyrender_vs_disk_pixels"] = int((gl.mask[0].numpy() != disk(size)).sum())
            rows.append(row)
    return context, cold, rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one small size, one repeat")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    sizes, repeats = ([128], 1) if args.quick else (args.sizes, args.repeats)
    context, cold, rows = run(sizes, repeats)
    if context.available:
        print(f"pyrender on {context.platform}: {context.device}; cold start (context + shaders + 1 render) {cold:.2f} s")
    else:
        print(f"no OpenGL context ({context.reason}): the ray caster only")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}; median of {repeats} warm renders, wall-clock ms (CPU ms of all threads)")
    head = f"{'size':>5} {'mesh':<13} {'embree ms (cpu)':>15} {'pyrender ms (cpu)':>17}"
    if context.available:
        head += f" {'mask agree':>10} {'px diff':>7} {'angle med':>9} {'p99':>6} {'>5deg':>6} {'shade med':>9} {'p99':>6} {'sRGB>2':>6}"
    print(head)
    for r in rows:
        line = f"{r['size']:>5} {r['mesh']:<13} {r['embree_ms']:>7.0f} ({r['embree_cpu_ms']:>5.0f})"
        if context.available:
            line += (f" {r['pyrender_ms']:>9.0f} ({r['pyrender_cpu_ms']:>5.0f}) {100 * r['mask_agreement']:>9.2f}% {r['mask_pixels_differing']:>7d}"
                     f" {r['angle_median_deg']:>9.3f} {r['angle_p99_deg']:>6.2f} {100 * r['angle_over_5deg']:>5.2f}%"
                     f" {r['shading_median']:>9.5f} {r['shading_p99']:>6.4f} {100 * r['srgb_over_2_levels']:>5.2f}%")
        print(line)
    for r in rows:
        if "embree_vs_disk_pixels" in r:
            print(f"sphere {r['size']}: mask pixels off the analytic disk: embree {r['embree_vs_disk_pixels']}, "
                  f"pyrender {r.get('pyrender_vs_disk_pixels', '-')}")
    out = Path(__file__).parent / "results"
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(torch=torch.__version__, threads=torch.get_num_threads(), cores=os.cpu_count(),
                load_average=os.getloadavg()[0], repeats=repeats, sizes=sizes,
                machine=platform.machine(), gl_available=context.available, gl_platform=context.platform,
                gl_device=context.device, gl_reason=context.reason, pyrender_cold_s=cold)
    (out / "renderers.json").write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))


if __name__ == "__main__":
    main()
