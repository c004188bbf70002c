r"""Image formation beyond exact 9-term SH shading, for realistic evaluation images.

The method assumes Lambertian shading by a second-order SH lighting (SPEC). Photographs
break that in known ways; each function here adds one of them so that a benchmark can
measure what each costs:

* **cast shadows**: the radiance the SH lighting describes, integrated over the part of
  the hemisphere each point actually sees (:func:`shadow_visibility` by ray casting,
  :func:`shade_environment`). Without occlusion this converges to
  :func:`sfs_torch.lighting.render_sh` (up to the radiance's clipping at zero);
* **a specular lobe**: Blinn-Phong highlights from the lighting's dominant direction
  (:func:`dominant_light`, :func:`blinn_phong`);
* **exposure and white-balance errors**: a global gain and per-channel gains (:func:`expose`);
* **sensor noise and 8-bit sRGB files**: Poisson-Gaussian noise (:func:`poisson_gaussian_noise`)
  and quantisation in sRGB (:func:`quantise_srgb`); :func:`estimate_noise_sigma` reads
  the resulting noise level back off an image.

:func:`sfs_torch.datasets.synthetic_scenes` composes them. The radiance is the 9-term
one, so shadows here are softer than under a real environment map with a sun.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor

from ._checks import check_finite, check_mask, check_same_size, check_shape, check_unit_vectors, is_integer, is_number
from .io import linear_to_srgb, srgb_to_linear
from .lighting import _BAND_OF_COEFFICIENT, _LAMBERT_OVER_PI, sh_basis_vectors

__all__ = [
    "sphere_directions",
    "sh_radiance",
    "shadow_visibility",
    "shade_environment",
    "dominant_light",
    "blinn_phong",
    "expose",
    "poisson_gaussian_noise",
    "quantise_srgb",
    "MAX_BITS",
    "estimate_noise_sigma",
]


def sphere_directions(n: int, *, dtype: torch.dtype = torch.float64) -> Tensor:
    """``n`` nearly uniform unit directions (a Fibonacci lattice): :math:`(n, 3)`.

    Deterministic, so a shading integral over them has no per-pixel Monte Carlo noise.
    """
    if not is_integer(n, 1):
        raise ValueError(f"n must be a positive integer, got {n!r}")
    i = torch.arange(n, dtype=dtype) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = (1 - z * z).clamp_min(0).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1)


def sh_radiance(directions: Tensor, sh: Tensor, *, iterations: int = 1000) -> Tensor:
    r"""A non-negative radiance over ``directions`` whose Lambertian shading is the SH lighting.

    SPEC lightings fold the Lambertian convolution in (``L[c, k] = albedo A_l / pi L_lm``),
    so the 9-term radiance is ``sum_k L[c, k] / (A_l / pi) Y_k(w)``. That reconstruction
    rings negative for natural lightings, and clipping it adds light (up to ~20 % on R&H's
    probes); instead the clipped radiance is projected, alternately, back onto the
    radiances with exactly these 9 coefficients and onto the non-negative ones, which
    converges to one that is both (it exists for any lighting of a real environment).
    Its shading differs from :func:`render_sh` by what its bands above 2 pass through the
    clamped cosine: at most 0.1-2.7 % of the brightest shading on R&H's probes with 400
    directions, the error of the 9-term model itself.

    Args:
        directions: :math:`(K, 3)` uniform unit vectors, camera frame (:func:`sphere_directions`).
        sh: :math:`(3, 9)` lighting.
        iterations: alternating projections.

    Returns:
        :math:`(K, 3)` non-negative albedo-weighted radiance.

    Raises:
        ValueError: bad shapes, NaN or infinite values, directions that are not unit
            vectors (the quadrature's basis values assume them), or a negative ``iterations``.
    """
    check_shape(directions, "directions", "K 3")
    check_shape(sh, "sh", "3 9")
    check_finite(directions, "directions")
    check_finite(sh, "sh")
    check_unit_vectors(directions, "directions")
    if not is_integer(iterations, 0):
        raise ValueError(f"iterations must be an integer >= 0, got {iterations!r}")
    factors = torch.tensor([_LAMBERT_OVER_PI[b] for b in _BAND_OF_COEFFICIENT], dtype=directions.dtype,
                           device=directions.device)
    basis = sh_basis_vectors(directions)  # (K, 9)
    target = (sh.to(directions.dtype) / factors).T  # (9, 3) radiance coefficients
    project = (4 * math.pi / directions.shape[0]) * basis.T  # quadrature of the SH projection
    correction = torch.linalg.pinv(project)  # least-norm change of the radiance that fixes its coefficients
    radiance = (basis @ target).clamp_min(0)
    for _ in range(iterations):
        radiance = (radiance + correction @ (target - project @ radiance)).clamp_min(0)
    return radiance


def shadow_visibility(mesh: trimesh.Trimesh, points: Tensor, normals: Tensor, directions: Tensor,
                      rotation: Tensor, *, offset: float = 1e-3) -> Tensor:
    """Which directions each surface point sees unoccluded (one shadow ray each, Embree).

    Args:
        mesh: the mesh the points lie on, in its own (world) frame.
        points: :math:`(N, 3)` world-frame surface points (:attr:`NormalRender.points`).
        normals: :math:`(N, 3)` camera-frame unit normals at them.
        directions: :math:`(K, 3)` camera-frame unit directions.
        rotation: :math:`(3, 3)` world-to-camera rotation of the view.
        offset: how far along the normal the rays start, against self-intersection.

    Returns:
        :math:`(N, K)` bool, True where the direction is above the tangent plane and the
        ray escapes the mesh.
    """
    rot = rotation.detach().cpu().double().numpy()
    n_world = normals.detach().cpu().double().numpy() @ rot
    d_world = directions.detach().cpu().double().numpy() @ rot
    above = n_world @ d_world.T > 0
    pixel, k = np.nonzero(above)
    origins = points.detach().cpu().double().numpy()[pixel] + offset * n_world[pixel]
    blocked = mesh.ray.intersects_any(origins, d_world[k]) if len(pixel) else np.zeros(0, bool)
    visible = np.zeros(above.shape, bool)
    visible[pixel[~blocked], k[~blocked]] = True
    return torch.from_numpy(visible)


def shade_environment(normals: Tensor, directions: Tensor, radiance: Tensor,
                      visibility: Optional[Tensor] = None) -> Tensor:
    r"""Lambertian shading integrated over the visible directions.

    ``I(n) = 1/pi * integral radiance(w) V(w) max(0, n . w) dw``, the integral over ``K``
    uniform directions (solid angle ``4 pi / K`` each).

    Args:
        normals: :math:`(N, 3)` unit normals.
        directions: :math:`(K, 3)` uniform unit directions (:func:`sphere_directions`).
        radiance: :math:`(K, 3)` albedo-weighted radiance from each direction.
        visibility: :math:`(N, K)` bool; ``None`` for no occlusion.

    Returns:
        :math:`(N, 3)` linear intensities.

    Raises:
        ValueError: bad or disagreeing shapes, NaN or infinite values, or directions that
            are not unit vectors (each stands for the solid angle ``4 pi / K``).
    """
    check_shape(normals, "normals", "N 3")
    check_shape(directions, "directions", "K 3")
    check_shape(radiance, "radiance", "K 3")
    if radiance.shape[0] != directions.shape[0]:
        raise ValueError(
            f"radiance must have one row per direction, ({directions.shape[0]}, 3), got {tuple(radiance.shape)}"
        )
    if visibility is not None:
        check_shape(visibility, "visibility", "N K", floating=False)
        if visibility.shape != (normals.shape[0], directions.shape[0]):
            raise ValueError(
                f"visibility must have shape (N, K) = ({normals.shape[0]}, {directions.shape[0]}) for these "
                f"normals and directions, got {tuple(visibility.shape)}"
            )
    check_finite(normals, "normals")
    check_finite(directions, "directions")
    check_finite(radiance, "radiance")
    check_unit_vectors(directions, "directions")
    cosine = (normals.to(directions.dtype) @ directions.T).clamp_min(0)
    if visibility is not None:
        cosine = cosine * visibility.to(cosine.device, cosine.dtype)
    return 4.0 / directions.shape[0] * cosine @ radiance.to(cosine.dtype)


def dominant_light(sh: Tensor) -> Tuple[Tensor, Tensor]:
    """The direction and colour of a lighting's linear (dipole) band.

    Returns:
        :math:`(3,)` unit direction (camera frame) of the luminance dipole (zero for a
        lighting without one) and :math:`(3,)` RGB intensity of a surface facing it
        (:func:`render_sh` at that normal).
    """
    check_shape(sh, "sh", "3 9")
    luminance = torch.tensor([0.2126, 0.7152, 0.0722], dtype=sh.dtype, device=sh.device) @ sh
    direction = torch.stack([luminance[3], luminance[1], luminance[2]])  # Y3 ~ x, Y1 ~ y, Y2 ~ z
    direction = direction / direction.norm().clamp_min(torch.finfo(sh.dtype).tiny)
    return direction, sh @ sh_basis_vectors(direction)


def blinn_phong(normals: Tensor, view: Tensor, light: Tensor, colour: Tensor, shininess: float) -> Tensor:
    """Blinn-Phong highlights ``colour * max(0, n . h)^shininess`` with ``h`` the half vector.

    Args:
        normals: :math:`(N, 3)` unit normals; view: :math:`(N, 3)` or :math:`(3,)` unit
            vectors towards the camera; light: :math:`(3,)` unit direction towards the light,
            or zero for none (what :func:`dominant_light` gives a lighting without a dipole);
            colour: :math:`(3,)` peak intensity.

    Returns:
        :math:`(N, 3)`, zero where the light is behind the surface (everywhere without one).

    Raises:
        ValueError: bad shapes, NaN or infinite values, a light direction that is not a
            unit vector (its length would rescale ``n . light`` and tilt ``h``), or a
            negative ``shininess`` (``0 ** shininess`` would be infinite).
    """
    check_shape(normals, "normals", "N 3")
    if not isinstance(view, Tensor):
        raise TypeError(f"view must be a torch.Tensor of shape (N, 3) or (3,), got {type(view).__name__}")
    if view.shape not in ((normals.shape[0], 3), (3,)):
        raise ValueError(f"view must have shape (N, 3) = ({normals.shape[0]}, 3) or (3,), got {tuple(view.shape)}")
    check_shape(light, "light", "3")
    check_shape(colour, "colour", "3")
    for name, value in (("normals", normals), ("view", view), ("light", light), ("colour", colour)):
        check_finite(value, name)
    if bool(light.any()):  # a zero light is no light: no highlight anywhere
        check_unit_vectors(light, "light")
    if not is_number(shininess, 0):
        raise ValueError(f"shininess must be a number >= 0, got {shininess!r}")
    half = view + light
    half = half / half.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    lit = (normals @ light > 0).to(normals.dtype)
    return (lit * (normals * half).sum(-1).clamp_min(0) ** shininess)[:, None] * colour


def expose(image: Tensor, gains: Tensor) -> Tensor:
    """A camera's exposure and white-balance error: :math:`(B, 3, H, W) -> (B, 3, H, W)`, ``gains[c] * I_c``.

    ``gains`` :math:`(3,)` is the exposure times each channel's white-balance gain
    (:func:`sfs_torch.datasets.camera_gains`).

    Raises:
        TypeError: ``image`` or ``gains`` is not a tensor.
        ValueError: bad shapes, or ``gains`` holds NaN or infinite values.
    """
    check_shape(image, "image", "B 3 H W")
    check_shape(gains, "gains", "3", floating=False)
    check_finite(gains, "gains")
    return image * gains.to(image).view(1, 3, 1, 1)


def poisson_gaussian_noise(image: Tensor, gain: float, sigma: float, generator: torch.Generator) -> Tensor:
    r"""Sensor noise of variance ``gain * I + sigma^2`` (shot noise plus read noise), any shape.

    ``gain`` is the intensity of one photo-electron: ``1 / gain`` electrons fill the range [0, 1].

    Raises:
        ValueError: ``gain`` or ``sigma`` is not a finite number >= 0 (a negative variance
            would make the noise NaN).
    """
    for name, value in (("gain", gain), ("sigma", sigma)):
        if not is_number(value, 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    noise = torch.randn(image.shape, generator=generator, dtype=image.dtype)
    return image + noise.to(image.device) * (gain * image.clamp_min(0) + sigma ** 2).sqrt()


MAX_BITS = 16  # the deepest common image files (16-bit PNG / TIFF)


def quantise_srgb(image: Tensor, bits: int = 8) -> Tensor:
    """Store as a ``bits``-bit sRGB file and read it back: clip to [0, 1], encode, round, decode; any shape.

    Raises:
        ValueError: ``bits`` is not an integer in [1, MAX_BITS] (0 bits leave no level to
            round to; image files stop at 16 bits, and past 127 the levels overflowed float32).
    """
    if not is_integer(bits, 1, MAX_BITS):
        raise ValueError(f"bits must be an integer in [1, {MAX_BITS}], got {bits!r}")
    levels = 2 ** bits - 1
    return srgb_to_linear(torch.round(linear_to_srgb(image.clamp(0, 1)) * levels) / levels)


_LAPLACIAN = ((0.0, 1.0, 0.0), (1.0, -4.0, 1.0), (0.0, 1.0, 0.0))


def estimate_noise_sigma(image: Tensor, mask: Tensor) -> Tensor:
    r"""The standard deviation of an image's pixel noise on its object: :math:`(B, 3, H, W), (B, 1, H, W) -> (B,)`.

    The median absolute 3x3 Laplacian over the object's interior (the mask eroded by two
    pixels, away from the rim's steep shading), scaled to a Gaussian's standard deviation
    (``1.4826 / sqrt(20)``). Smooth shading has almost no Laplacian at a few hundred pixels
    across, so what is measured is the noise (sensor noise, quantisation). Exact for
    white Gaussian noise on a locally linear image; 0 for an object with no interior.

    Raises:
        ValueError: bad shapes, a mask of another size than the image, or a mask with
            values other than 0 and 1.
    """
    check_shape(image, "image", "B 3 H W")
    # an empty mask has no interior (0) and a full one is all interior: both are defined
    mask = check_mask(mask, allow_full=True, allow_empty=True)
    check_same_size(image, "image", mask, "mask")
    kernel = torch.tensor(_LAPLACIAN, dtype=image.dtype, device=image.device).view(1, 1, 3, 3).repeat(3, 1, 1, 1)
    laplacian = F.conv2d(image, kernel, groups=3).abs()
    interior = (-F.max_pool2d(-mask.to(image.dtype), 5, 1, 2))[..., 1:-1, 1:-1] > 0.5
    sigma = torch.zeros(image.shape[0], dtype=image.dtype, device=image.device)
    for b in range(image.shape[0]):
        values = laplacian[b][interior[b].expand(3, -1, -1)]
        if values.numel():
            sigma[b] = 1.4826 / math.sqrt(20.0) * values.median()
    return sigma
