"""Pictures people would rather look at than read: normal maps, error maps, the summary page."""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from .lighting import render_sphere

__all__ = ["confidence_display_max", "normals_to_rgb", "summary_figure", "error_map_figure"]


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


def _object_box(mask: Tensor, margin: int = 4) -> tuple:
    """Row and column slices around the ``(1, H, W)`` mask's object, widened by ``margin``."""
    m = mask[0].cpu()
    rows = torch.nonzero(m.any(1)).flatten()
    cols = torch.nonzero(m.any(0)).flatten()
    if rows.numel() == 0:
        return slice(None), slice(None)
    return (slice(max(int(rows[0]) - margin, 0), int(rows[-1]) + 1 + margin),
            slice(max(int(cols[0]) - margin, 0), int(cols[-1]) + 1 + margin))


def error_map_figure(
    path: Path,
    image: Tensor,
    mask: Tensor,
    normals: Mapping[str, Tensor],
    *,
    true_normals: Optional[Tensor] = None,
    title: str = "",
    max_error: float = 45.0,
) -> None:
    """Write one row of panels as in the paper's Fig. 7 and 9: the input, then each
    method's angular-error map with its median error below it.

    Without ``true_normals`` each method's normal map is shown instead (no error to map).
    The panels are cropped to the object.

    Args:
        path: the PNG to write.
        image: ``(3, H, W)`` linear RGB; mask ``(1, H, W)`` bool.
        normals: method name -> ``(3, H, W)`` estimated normals, in panel order.
        true_normals: ``(3, H, W)`` ground truth, or ``None``.
        max_error: top of the error colour scale, degrees.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .metrics import angular_error, normal_metrics

    mask = mask.detach().cpu().bool()
    rows, cols = _object_box(mask)
    background = ~mask[0].numpy()
    shown = _display(image)
    shown[background] = 1.0
    count = len(normals) + 1
    fig, axes = plt.subplots(1, count, figsize=(2.3 * count + (0.8 if true_normals is not None else 0), 2.9),
                             squeeze=False, layout="constrained")
    panels = axes[0]
    for ax in panels:
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    panels[0].imshow(shown[rows, cols])
    panels[0].set_title("input", fontsize=10)
    scale = None
    for ax, (name, est) in zip(panels[1:], normals.items()):
        est = est.detach().float().cpu()
        ax.set_title(name, fontsize=10)
        if true_normals is None:
            ax.imshow(normals_to_rgb(est, mask)[rows, cols])
            ax.set_xlabel("normals (no ground truth)", fontsize=9)
            continue
        gt = true_normals.detach().float().cpu()
        err = _outside_as_nan(angular_error(est, gt, mask)[0], mask)
        median = float(normal_metrics(est, gt, mask).median)
        scale = ax.imshow(err[rows, cols], cmap="inferno", vmin=0, vmax=max_error)
        ax.set_xlabel(f"median {median:.1f}\N{DEGREE SIGN}", fontsize=10)
    if scale is not None:
        fig.colorbar(scale, ax=list(panels[1:]), fraction=0.046, pad=0.02, label="angular error (deg)")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
