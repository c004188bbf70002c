"""Analytic test scenes shared by the end-to-end tests."""
import torch


def sphere(size=64, radius=26.0, centre=(0.0, 0.0)):
    """Orthographic sphere: normals ``(3, S, S)`` (0 outside) and mask ``(1, S, S)``.

    ``centre`` offsets the sphere's centre in pixels, as (columns to the right, rows up).
    """
    c = torch.arange(size, dtype=torch.float32) + 0.5 - size / 2
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    x = (xx - centre[0]) / radius
    y = -(yy + centre[1]) / radius
    r2 = x * x + y * y
    mask = (r2 < 1)[None]
    normals = torch.stack([x, y, torch.sqrt((1 - r2).clamp_min(0))]) * mask
    return normals, mask
