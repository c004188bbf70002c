"""Natural lighting: a prior over SH lightings and environment maps to render with.

Both come from eight CC0 Poly Haven environment maps that ship in the ``bpy`` wheel on
PyPI (``sfs_torch/data/LICENSES.md``); ``tools/build_natural_lighting.py`` reads them
once and writes ``sfs_torch/data/natural_lighting.npz``, which ships in the package.
Ramamoorthi & Hanrahan's probes (:func:`sfs_torch.lighting.natural_lightings`) are
deliberately not among them: they stay evaluation lightings.

A lighting's overall scale is arbitrary (albedo times exposure), so the prior is
defined on the lighting divided by the root mean square of its 27 coefficients
(:func:`normalise_lighting`), a scale that stays positive for any lighting but zero,
also for a physically impossible one with a negative DC term.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from ._checks import check_finite, check_shape
from .lighting import irradiance_to_sh, sh_basis_vectors

__all__ = ["LightingPrior", "EnvironmentMaps", "load_lighting_prior", "environment_maps", "normalise_lighting",
           "lighting_prior_energy", "equirect_directions", "environment_to_sh", "random_camera_rotations"]


@dataclass(frozen=True)
class LightingPrior:
    """Gaussian prior over scale-normalised SH lightings.

    Attributes:
        mean: :math:`(3, 9)` mean of :func:`normalise_lighting` of natural lightings.
        precision: :math:`(27, 27)` inverse covariance of the same, row-major ``(c, k)``.
    """

    mean: Tensor
    precision: Tensor

    def to(self, device=None, dtype=None) -> "LightingPrior":
        return LightingPrior(self.mean.to(device, dtype), self.precision.to(device, dtype))


@dataclass(frozen=True)
class EnvironmentMaps:
    """Equirectangular radiance maps (row 0 looks straight up, camera frame y up).

    Attributes:
        names: one name per map.
        maps: :math:`(K, H, W, 3)` linear radiance.
        sh: :math:`(K, 3, 9)` each map's SH lighting seen by a camera looking at the
            horizon (along -z), normalised by :func:`normalise_lighting`.
    """

    names: Tuple[str, ...]
    maps: Tensor
    sh: Tensor


@lru_cache(maxsize=1)
def _data() -> dict:
    with resources.files("sfs_torch").joinpath("data/natural_lighting.npz").open("rb") as f:
        with np.load(f, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}


def load_lighting_prior(*, device: Optional[torch.device] = None, dtype: torch.dtype = torch.float32) -> LightingPrior:
    """The natural-lighting prior shipped with the package."""
    data = _data()
    precision = np.linalg.inv(data["prior_cov"])
    return LightingPrior(
        mean=torch.tensor(data["prior_mean"], device=device, dtype=dtype),
        precision=torch.tensor((precision + precision.T) / 2, device=device, dtype=dtype),
    )


def environment_maps(*, device: Optional[torch.device] = None) -> EnvironmentMaps:
    """The eight environment maps the prior was fitted to (32 x 64 each)."""
    data = _data()
    return EnvironmentMaps(
        names=tuple(str(n) for n in data["names"]),
        maps=torch.tensor(data["maps"], device=device),
        sh=torch.tensor(data["sh"], device=device),
    )


def equirect_directions(height: int, width: int, *, device=None, dtype=torch.float64) -> Tuple[Tensor, Tensor]:
    """Pixel directions and solid angles of an equirectangular map.

    Row 0 looks straight up (+y); column ``j`` has azimuth ``2 pi (j + 0.5) / W`` from +z
    towards +x. Camera frame (SPEC): a camera looking at the horizon along -z.

    Returns:
        :math:`(H, W, 3)` unit directions and :math:`(H, W)` solid angles (summing to 4 pi).
    """
    theta = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height * math.pi
    phi = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width * 2 * math.pi
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    d = torch.stack([t.sin() * p.sin(), t.cos(), t.sin() * p.cos()], -1)
    return d, t.sin() * (math.pi / height) * (2 * math.pi / width)


def environment_to_sh(maps: Tensor, albedo: float = 1.0) -> Tensor:
    """SH lighting of equirectangular radiance maps (projection, then Lambertian convolution).

    A diffuse surface of ``albedo`` lit by the map renders, through
    :func:`sfs_torch.lighting.render_sh`, as ``albedo / pi`` times its irradiance: a
    uniform map of radiance 1 renders as ``albedo`` everywhere.

    Args:
        maps: :math:`(K, H, W, 3)` linear radiance, row 0 looking up.

    Returns:
        :math:`(K, 3, 9)` SH lighting in the camera frame of :func:`equirect_directions`.
    """
    check_shape(maps, "maps", "K H W 3")
    check_finite(maps, "maps")
    d, solid_angle = equirect_directions(*maps.shape[1:3], device=maps.device)
    radiance = torch.einsum("khwc,hwj,hw->kcj", maps.double(), sh_basis_vectors(d), solid_angle)
    return irradiance_to_sh(radiance, albedo).to(maps.dtype)


def random_camera_rotations(n: int, generator: torch.Generator, *, pitch_deg: float = 30.0,
                            roll_deg: float = 10.0) -> Tensor:
    """Orientations of a hand-held camera: yaw uniform, pitch and roll uniform in +-their bounds.

    Returns:
        :math:`(n, 3, 3)` float64 rotations ``R = R_z(roll) R_x(pitch) R_y(yaw)`` taking
        the horizon camera's frame to the rotated camera's (for :func:`sfs_torch.lighting.rotate_sh`).
    """
    u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    yaw = 2 * math.pi * u[:, 0]
    pitch = math.radians(pitch_deg) * (2 * u[:, 1] - 1)
    roll = math.radians(roll_deg) * (2 * u[:, 2] - 1)

    def rotation(angle: Tensor, i: int, j: int) -> Tensor:
        r = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
        r[:, i, i], r[:, j, j] = angle.cos(), angle.cos()
        r[:, i, j], r[:, j, i] = -angle.sin(), angle.sin()
        return r

    return rotation(roll, 0, 1) @ rotation(pitch, 1, 2) @ rotation(yaw, 2, 0)


def normalise_lighting(sh: Tensor) -> Tensor:
    """Divide each lighting by the root mean square of its coefficients: :math:`(B, 3, 9) -> (B, 3, 9)`.

    A zero lighting stays zero, with a finite gradient (the identity's).
    """
    check_shape(sh, "sh", "B 3 9")
    mean_square = sh.square().mean((1, 2), keepdim=True)
    # sqrt's gradient at 0 is infinite, NaN once chained through the zero lighting: a zero
    # lighting, which has no scale, is divided by 1 instead
    rms = torch.where(mean_square > 0, mean_square, 1.0).sqrt()
    return sh / rms


def lighting_prior_energy(sh: Tensor, prior: LightingPrior) -> Tensor:
    r"""Half the Mahalanobis distance of the normalised lighting to the prior, per coefficient.

    ``0.5 / 27 * d^T P d`` with ``d = normalise(sh) - mean``; differentiable.

    Args:
        sh: :math:`(B, 3, 9)`.
        prior: :class:`LightingPrior`, used in the device and dtype of ``sh``.

    Returns:
        :math:`(B,)`.
    """
    prior = prior.to(sh.device, sh.dtype)
    d = (normalise_lighting(sh) - prior.mean).flatten(1)
    # a product and a sum: einsum's contraction planning took longer than the sum itself in
    # the refinement's inner loop
    return 0.5 * ((d @ prior.precision) * d).sum(1) / d.shape[1]
