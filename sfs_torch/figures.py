"""Pictures people would rather look at than read: normal maps, error maps, the summary page."""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
from torch import Tensor

from .lighting import render_sphere

__all__ = ["confidence_display_max", "normals_to_rgb", "summary_figure"]


def normals_to_rgb(normals: Tensor, mask: Optional[Tensor] = None) -> np.ndarray:
    """``(3, H, W)`` normals -> ``(H, W, 3)`` colours ``(n + 1) / 2``, white outside ``mask``."""
    rgb = ((normals.detach().float().cpu() + 1) / 2).clamp(0, 1).permute(1, 2, 0).numpy()
    if mask is not None:
        rgb[~mask.detach().cpu()[0].numpy()] = 1.0
    return rgb


def _display(image: Tensor) -> np.ndarray:
    """Linear ``(3, H, W)`` -> sRGB-encoded ``(H, W, 3)`` for display."""
    x = image.detach().float().cpu().clamp(0, 1)
    srgb = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055)
    return srgb.permute(1, 2, 0).numpy()


def confidence_display_max(confidence: Tensor, mask: Tensor) -> float:
    """Top of the colour scale for the forest's kappa: its 99th percentile on the object.

    kappa has a long tail where the trees agree exactly; clipping it there keeps the
    rest visible. ``confidence`` and ``mask``: ``(1, H, W)``.
    """
    return float(confidence[mask].float().quantile(0.99).clamp_min(1e-6))


def _outside_as_nan(values: Tensor, mask: Tensor) -> np.ndarray:
    """``(H, W)`` values -> array with NaN (drawn blank) outside the ``(1, H, W)`` mask."""
    out = values.detach().float().cpu().numpy().copy()
    out[~mask[0].cpu().numpy()] = np.nan
    return out


def summary_figure(
    path: Path,
    image: Tensor,
    mask: Tensor,
    normals: Tensor,
    lighting: Tensor,
    *,
    true_normals: Optional[Tensor] = None,
    true_lighting: Optional[Tensor] = None,
    confidence: Optional[Tensor] = None,
    depth: Optional[Tensor] = None,
    numbers: Optional[Dict[str, float]] = None,
    title: str = "sfs-torch",
) -> None:
    """Write the one-page summary: input, estimated (and true) normals, error map,
    estimated (and true) reflectance maps, confidence, depth, and the key numbers.

    Args:
        image: ``(3, H, W)`` linear RGB; mask ``(1, H, W)`` bool; normals ``(3, H, W)``;
            lighting ``(3, 9)``; optional ground truth of the same shapes; confidence
            (the forest's kappa) and depth ``(1, H, W)``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    background = ~mask[0].cpu().numpy()
    shown = _display(image)
    shown[background] = 1.0
    panels = [("input", shown, None), ("estimated normals", normals_to_rgb(normals, mask), None)]
    if true_normals is not None:
        panels.append(("true normals", normals_to_rgb(true_normals, mask), None))
        cos = (normals * true_normals).sum(0).clamp(-1, 1)
        err = _outside_as_nan(torch.rad2deg(torch.acos(cos)), mask)
        panels.append(("angular error (deg)", err, {"cmap": "inferno", "vmin": 0, "vmax": 45}))
    panels.append(("estimated reflectance map", _display(render_sphere(lighting.float().cpu(), 128)), None))
    if true_lighting is not None:
        panels.append(("true reflectance map", _display(render_sphere(true_lighting.float().cpu(), 128)), None))
    if confidence is not None:
        scale = {"cmap": "cividis", "vmin": 0, "vmax": confidence_display_max(confidence.cpu(), mask.cpu())}
        panels.append(("confidence (kappa)", _outside_as_nan(confidence[0], mask), scale))
    if depth is not None:
        panels.append(("depth", _outside_as_nan(depth[0], mask), {"cmap": "viridis"}))

    cols = min(4, len(panels))
    rows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(
        rows, cols, figsize=(3.4 * cols, 3.4 * rows + (0.9 if numbers else 0.3)), squeeze=False, layout="constrained"
    )
    for ax in axes.flat:
        ax.axis("off")
    for ax, (name, data, colour_scale) in zip(axes.flat, panels):
        if colour_scale is None:
            ax.imshow(data)
        else:
            fig.colorbar(ax.imshow(data, **colour_scale), ax=ax, fraction=0.046, pad=0.04)
        ax.set_title(name, fontsize=10)
    fig.suptitle(title, fontsize=12)
    if numbers:
        text = "   ".join(f"{k}: {v:.3g}" for k, v in numbers.items())
        fig.supxlabel(text, fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)
