r"""Denoising the test image before anything reads it (not in the paper).

A camera's shot noise and 8-bit steps leave a noise of 0.5-1 % of white on each pixel
(:func:`sfs_torch.image_formation.estimate_noise_sigma` reads it off the image), while the
shading of a smooth object changes little within a pixel or two. The forest reads each
pixel's own colour, so that noise goes straight into its normals. A Gaussian average of
each object pixel with its object neighbours, the background left out
(normalised convolution: ``blur(I M) / blur(M)``), removes most of it: a white noise's
standard deviation falls by ``1 / (2 sigma sqrt(pi))``, to 0.28x at ``sigma = 1`` px.

The pipeline denoises only images whose estimated noise is above ``min_noise`` (on exact
images it would blur detail the forest reads). With a given lighting every stage then
reads the denoised image (``given="image"``); with an estimated lighting only the forest's
colour feature does (``estimated="colour"``): there the lighting fits, the textons and the
refinement read the image as it is, since a wholly denoised image made the estimate
worse. Both measured in docs/pipeline.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.filters import gaussian_blur2d
from torch import Tensor, nn

from ._checks import check_mask, check_same_size, check_shape, is_number

__all__ = ["DenoiseConfig", "check_denoise_config", "denoise_image", "ImageDenoiser", "DENOISE_MODES"]

# what of the pipeline reads the denoised image: nothing, the forest's colour feature, everything
DENOISE_MODES = ("none", "colour", "image")


@dataclass
class DenoiseConfig:
    """Options of the denoising stage of :func:`sfs_torch.estimate` (Hydra group ``denoise``).

    Attributes:
        given: with a given lighting, what reads the denoised image: ``"image"`` (every
            stage), ``"colour"`` (the forest's colour feature alone) or ``"none"``.
        estimated: the same with an estimated lighting. The defaults are the measured
            ones (docs/pipeline.md).
        sigma: standard deviation of the Gaussian, in pixels.
        min_noise: an image is denoised only when its estimated noise
            (:func:`sfs_torch.image_formation.estimate_noise_sigma`, linear RGB) is above
            this; the exact synthetic images read 0.001-0.002, 8-bit camera images 0.006-0.011.
    """

    given: str = "image"
    estimated: str = "colour"
    sigma: float = 1.0
    min_noise: float = 0.004


def check_denoise_config(cfg: DenoiseConfig, prefix: str = "denoise.") -> None:
    """``ValueError`` naming the first bad option of ``cfg`` (``prefix`` + its key)."""
    for name in ("given", "estimated"):
        if getattr(cfg, name) not in DENOISE_MODES:
            raise ValueError(f"{prefix}{name} must be one of {DENOISE_MODES}, got {getattr(cfg, name)!r}")
    for name in ("sigma", "min_noise"):
        _check_non_negative(getattr(cfg, name), prefix + name)


def _check_non_negative(value: float, name: str) -> None:
    if not is_number(value, 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


def denoise_image(image: Tensor, mask: Tensor, sigma: float = DenoiseConfig.sigma) -> Tensor:
    r"""Average each object pixel with its object neighbours: :math:`(B, C, H, W), (B, 1, H, W) -> (B, C, H, W)`.

    ``blur(I M) / blur(M)`` with a Gaussian of ``sigma`` pixels (kornia's, truncated at
    3 sigma): background pixels never mix into the object, so a constant object stays
    constant up to its rim and a linear ramp is unchanged wherever the kernel fits inside.
    Pixels outside the mask keep their values. Differentiable in ``image``.

    Args:
        image: :math:`(B, C, H, W)` floating point.
        mask: :math:`(B, 1, H, W)` bool or {0, 1}, the object pixels.
        sigma: the Gaussian's standard deviation in pixels; 0 returns ``image`` itself.

    Returns:
        :math:`(B, C, H, W)`, the dtype and device of ``image``.

    Example:
        >>> image, mask = torch.full((1, 3, 8, 8), 0.5), torch.ones(1, 1, 8, 8, dtype=torch.bool)
        >>> torch.allclose(denoise_image(image, mask), image)
        True
    """
    check_shape(image, "image", "B C H W")
    mask = check_mask(mask, allow_full=True)
    check_same_size(image, "image", mask, "mask")
    _check_non_negative(sigma, "sigma")
    if sigma == 0:
        return image
    size = 2 * math.ceil(3 * sigma) + 1
    weight = mask.to(image.dtype)
    # selected, not multiplied by the mask: NaN or inf in the background times 0 is NaN,
    # which the blur would carry into the object
    inside = torch.where(mask, image, 0.0)
    blurred = gaussian_blur2d(torch.cat([inside, weight], 1), size, (float(sigma), float(sigma)),
                              border_type="constant")
    total, covered = blurred[:, :-1], blurred[:, -1:]
    return torch.where(mask, total / covered.clamp_min(torch.finfo(image.dtype).tiny), image)


class ImageDenoiser(nn.Module):
    """:func:`denoise_image` as a module: ``ImageDenoiser(sigma)(image, mask)``."""

    def __init__(self, sigma: float = DenoiseConfig.sigma) -> None:
        super().__init__()
        self.sigma = sigma

    def forward(self, image: Tensor, mask: Tensor) -> Tensor:
        return denoise_image(image, mask, self.sigma)
