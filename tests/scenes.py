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


def with_highlight(image, normals, mask, sh, peak=0.3, shininess=40.0):
    """``image`` (3, S, S) plus the realistic formation's Blinn-Phong highlight of lighting
    ``sh`` (3, 9) on ``normals`` (3, S, S) inside ``mask`` (1, S, S), orthographic view,
    clipped to [0, 1]; and the highlight itself, ``(N, 3)`` over the mask's pixels."""
    from sfs_torch.image_formation import blinn_phong, dominant_light

    direction, colour = dominant_light(sh)
    inside = mask[0]
    lobe = blinn_phong(normals[:, inside].T, torch.tensor([0.0, 0.0, 1.0]), direction, peak * colour, shininess)
    glossy = image.clone()
    glossy[:, inside] += lobe.T
    return glossy.clamp(0, 1), lobe
