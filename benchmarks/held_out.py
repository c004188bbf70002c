"""The held-out scenes of the end-to-end benchmarks, shared so that every script scores the same images.

Shapes from the EVALUATION side of the database's shape split (never trained on), spread
over its groups, each seen from one random view, under R&H's natural light probes
(albedo 0.8), with Gaussian noise sigma 0.001 clipped to [0, 1] (the paper's setting).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Optional

import torch
from torch import Tensor

from sfs_torch.geometry_db import DatabaseConfig, evaluation_shapes
from sfs_torch.lighting import natural_lightings, render_sh
from sfs_torch.rendering import random_view_rotations, render_normals

LIGHTINGS = ["grace_cathedral", "campus_sunset", "uffizi_gallery", "eucalyptus_grove", "st_peters_basilica",
             "galileos_tomb", "funston_beach_sunset"]


@dataclass(frozen=True)
class Scene:
    """One image: ``image (1, 3, H, W)``, ``mask (1, 1, H, W)``, true ``normals`` and ``lighting (1, 3, 9)``."""

    shape: str
    lighting_name: str
    image: Tensor
    mask: Tensor
    normals: Tensor
    lighting: Tensor


def held_out_scenes(n_shapes: int, n_lightings: int, resolution: int = 256, focal: Optional[float] = None,
                    collection: str = "default") -> Iterator[Scene]:
    """``n_shapes x n_lightings`` scenes, the same for the same arguments (seed 0)."""
    shapes = evaluation_shapes(DatabaseConfig(collection=collection))
    shapes = shapes[:: max(1, len(shapes) // n_shapes)][:n_shapes]
    lights = natural_lightings(0.8)
    generator = torch.Generator().manual_seed(0)
    for shape in shapes:
        view = render_normals(shape.mesh, random_view_rotations(1, generator)[0], resolution, focal=focal)
        normals, mask = view.normals[None], view.mask[None]
        for name in LIGHTINGS[:n_lightings]:
            sh = lights[name][None]
            noise = 0.001 * torch.randn(normals.shape, generator=generator)
            image = (render_sh(normals, sh) + noise).clamp(0, 1) * mask
            yield Scene(shape.name, name, image, mask, normals, sh)
