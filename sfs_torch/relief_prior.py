r"""A learnt prior on shapes in their poses, against the bas-relief ambiguity (not in the paper).

Under orthographic projection an estimated lighting leaves one transform of the surface
undetermined: the generalised bas-relief transform ``z -> s z + t_x u + t_y v``
(Belhumeur et al. 1999), which changes a uniform-albedo object's shading only through an
albedo factor (:func:`sfs_torch.integrability.bas_relief_normals`). Neither the image,
the estimated lighting nor the silhouette tells the tilt ``(t_x, t_y)`` (docs/pipeline.md
measured seven such cues); what does is what shapes look like in their poses: a bone seen
obliquely shows the rounded end that faces the camera, and a tilt that puts that end at
the far side gives a surface no real object has.

:class:`ReliefNet` is a small convolutional network that reads an object's normal field
(cropped to the object and resampled to 64x64 by :func:`crop_to_object`) and returns the
transform that takes it back to the shape it most likely is. It is trained by
:func:`fit_relief_net` on normal maps of the database's training shapes in random views
(:func:`relief_training_views`), each put through a random transform and a smooth random
perturbation of its slopes, to minimise the mean angle between the corrected field and
the true one. ``tools/build_relief_prior.py`` builds the weights that ship with the
package (``data/relief_prior.npz``); :func:`load_relief_net` loads them.
:func:`predict_relief` averages the network over three crops of the object (margins 1.0,
1.1, 1.25) and the eight symmetries of each square crop (mirrors, quarter turns), so a
mirrored or turned field gets the mirrored or turned transform exactly.

The pipeline (:func:`sfs_torch.pipeline.estimate`) also corrects perspective estimates,
read in the object's centroid frame, where the object is seen about as an orthographic one
is. There the image does tell transforms apart, so the corrected surface is refined again
and kept only where it explains the image at least as well.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from typing import Callable, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import check_mask, check_same_size, check_shape, check_unit_vectors, is_integer, is_number, to_batch
from .camera import pixel_grid
from .integrability import bas_relief_normals

__all__ = [
    "ReliefTransform", "ReliefNet", "ReliefPrior", "crop_to_object", "predict_relief", "apply_relief",
    "compose_relief", "relief_depth", "load_relief_net", "save_relief_net", "fit_relief_net",
    "relief_training_views", "mean_angle", "best_relief", "RELIEF_CROP_SIZE", "RELIEF_HIDDEN",
]

RELIEF_CROP_SIZE = 64
# the fully connected layer's width; the shipped weights record their own
RELIEF_HIDDEN = 1024
# the square crop's side over the object's larger bounding-box side: a margin of background
CROP_MARGIN = 1.1
# the margins predict_relief reads the network at and averages over (tuning images, docs/pipeline.md)
_READ_MARGINS = (1.0, 1.1, 1.25)


@dataclass
class ReliefTransform:
    """A generalised bas-relief transform per image: ``z -> scale z + tilt_x u + tilt_y v``.

    Attributes:
        scale: :math:`(B,)` depth scale, > 0.
        tilt_x: :math:`(B,)` slope added along ``u`` (right).
        tilt_y: :math:`(B,)` slope added along ``v`` (up).
    """

    scale: Tensor
    tilt_x: Tensor
    tilt_y: Tensor


def _identity(batch: int, device: torch.device) -> ReliefTransform:
    """The transform that leaves each of ``batch`` fields as it is (float32)."""
    return ReliefTransform(*(torch.full((batch,), v, device=device) for v in (1.0, 0.0, 0.0)))


def compose_relief(first: ReliefTransform, then: ReliefTransform) -> ReliefTransform:
    """The transform of applying ``first`` and then ``then``."""
    return ReliefTransform(scale=first.scale * then.scale, tilt_x=then.scale * first.tilt_x + then.tilt_x,
                           tilt_y=then.scale * first.tilt_y + then.tilt_y)


def apply_relief(normals: Tensor, mask: Tensor, transform: ReliefTransform) -> Tensor:
    """Normals after each image's transform: :math:`(B, 3, H, W), (B, 1, H, W) -> (B, 3, H, W)`, 0 off the mask."""
    return bas_relief_normals(normals, transform.scale, transform.tilt_x, transform.tilt_y) * mask


def relief_depth(depth: Tensor, mask: Tensor, transform: ReliefTransform) -> Tensor:
    r"""An orthographic height map after each image's transform: :math:`(B, 1, H, W) -> (B, 1, H, W)`.

    ``scale * depth + tilt_x * u + tilt_y * v`` on the mask (``u`` right, ``v`` up, in
    pixels from the object's centroid, so the object keeps its mean height), 0 off it; its
    normals are :func:`apply_relief`'s.
    """
    u, v = pixel_grid(*depth.shape[-2:], device=depth.device, dtype=depth.dtype)
    out = torch.zeros_like(depth)
    for b in range(depth.shape[0]):
        m = mask[b, 0].bool()
        plane = transform.tilt_x[b] * (u - u[m].mean()) + transform.tilt_y[b] * (v - v[m].mean())
        out[b, 0] = torch.where(m, transform.scale[b] * depth[b, 0] + plane.to(depth.dtype), 0.0)
    return out


def crop_to_object(normals: Tensor, mask: Tensor, size: int = RELIEF_CROP_SIZE,
                   margin: float = CROP_MARGIN) -> Tensor:
    r"""The network's input: :math:`(B, 3, H, W), (B, 1, H, W) -> (B, 4, size, size)`.

    A square around each object's bounding box (its larger side times ``margin``, 1.1 in
    training), resampled bilinearly to ``size x size``: the three normal components,
    renormalised and 0 off the object, and the object mask as a fourth channel (1 where
    the resampled mask is above one half). The crop keeps the image's orientation, so the
    normal components and the tilt keep their meaning.

    Raises:
        ValueError: wrong shapes or sizes, an empty mask, a ``size`` below 2, a ``margin``
            below 1 (the square would cut the object).
    """
    check_shape(normals, "normals", "B 3 H W")
    check_same_size(normals, "normals", mask, "mask")
    mask = check_mask(mask, allow_full=True)
    if not is_integer(size, 2):
        raise ValueError(f"size must be an integer >= 2, got {size!r}")
    if not is_number(margin, 1):
        raise ValueError(f"margin must be a finite number >= 1, got {margin!r}")
    return _crops(normals, mask, size, (margin,))[0]


def _crops(normals: Tensor, mask: Tensor, size: int, margins: Sequence[float]) -> Tensor:
    """:func:`crop_to_object` at each of ``margins``, unchecked, each bounding box found once:
    :math:`(B, 3, H, W), (B, 1, H, W)` bool -> :math:`(M, B, 4, size, size)`."""
    height, width = mask.shape[-2:]
    t = torch.linspace(-1, 1, size, dtype=torch.float64, device=normals.device)
    crops = []
    for b in range(normals.shape[0]):
        m = mask[b, 0]
        rows, cols = torch.nonzero(m, as_tuple=True)
        cy, cx = (rows.min() + rows.max()) / 2, (cols.min() + cols.max()) / 2
        extent = max(int(rows.max() - rows.min()), int(cols.max() - cols.min()))
        fields = torch.cat([normals[b] * m, m[None].to(normals.dtype)])[None].float()
        for margin in margins:
            half = extent / 2 * margin + 1
            gy = (cy + t * half) / max(height - 1, 1) * 2 - 1
            gx = (cx + t * half) / max(width - 1, 1) * 2 - 1
            grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)[None].float()
            sampled = F.grid_sample(fields, grid, mode="bilinear", align_corners=True)[0]
            inside = sampled[3] > 0.5
            n = sampled[:3] / sampled[:3].norm(dim=0, keepdim=True).clamp_min(1e-6)
            crops.append(torch.cat([n * inside, inside[None].float()]))
    return torch.stack(crops).unflatten(0, (normals.shape[0], len(margins))).transpose(0, 1)


class ReliefNet(nn.Module):
    """The network: :math:`(B, 4, 64, 64) -> (B, 3)`: ``(log scale, tilt_x, tilt_y)`` of the
    transform that corrects the cropped field (:func:`crop_to_object`).

    Five 3x3 convolutions (32, 32, 64, 64, 128 channels, the last four of stride 2), each
    with group normalisation and ReLU, then a fully connected layer of ``hidden`` units:
    a flattened map rather than a global average, since where on the object a rounded end
    lies is the cue. The last layer starts at zero, so an untrained network is the identity.
    """

    def __init__(self, hidden: int = RELIEF_HIDDEN):
        super().__init__()
        channels = [4, 32, 32, 64, 64, 128]
        layers = []
        for i in range(5):
            layers += [nn.Conv2d(channels[i], channels[i + 1], 3, stride=1 if i == 0 else 2, padding=1),
                       nn.GroupNorm(8, channels[i + 1]), nn.ReLU()]
        self.features = nn.Sequential(*layers)
        side = RELIEF_CROP_SIZE // 16
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(128 * side * side, hidden), nn.ReLU(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, crops: Tensor) -> Tensor:
        return self.head(self.features(crops))


# the eight symmetries of the square crop: mirror columns, mirror rows, then transpose
_SYMMETRIES = [(fx, fy, t) for t in (False, True) for fx in (False, True) for fy in (False, True)]


def _seen_in(crops: Tensor, flip_x: bool, flip_y: bool, transpose: bool) -> Tensor:
    """The crops under one symmetry of the square. Columns reversed negate ``n_x``, rows
    reversed ``n_y``; a transpose (the reflection ``u -> -v, v -> -u``: rows are ``-v``)
    swaps ``n_x`` and ``n_y`` and negates both."""
    sign = torch.tensor([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0, 1.0, 1.0], device=crops.device)
    dims = [d for d, f in ((-1, flip_x), (-2, flip_y)) if f]
    out = crops * sign[:, None, None]
    out = out.flip(dims) if dims else out
    if transpose:
        out = out.transpose(-2, -1)
        out = torch.stack([-out[:, 1], -out[:, 0], out[:, 2], out[:, 3]], 1)
    return out


def _seen_back(raw: Tensor, flip_x: bool, flip_y: bool, transpose: bool) -> Tensor:
    """The network's ``(B, 3)`` output for :func:`_seen_in`'s crops, in the original crops' frame."""
    log_scale, tilt_x, tilt_y = raw.unbind(1)
    if transpose:
        tilt_x, tilt_y = -tilt_y, -tilt_x
    return torch.stack([log_scale, -tilt_x if flip_x else tilt_x, -tilt_y if flip_y else tilt_y], 1)


def _network_transform(net: ReliefNet, crops: Tensor) -> ReliefTransform:
    """The network's transform for crops :math:`(M, B, 4, S, S)` of each of ``B`` fields (at
    ``M`` margins), averaged over the crops and over the eight symmetries of each square."""
    views = crops.flatten(0, 1)
    raw = net(torch.cat([_seen_in(views, *g) for g in _SYMMETRIES])).chunk(len(_SYMMETRIES))
    back = torch.stack([_seen_back(r, *g) for r, g in zip(raw, _SYMMETRIES)])
    return _as_transform(back.reshape(-1, crops.shape[1], 3).mean(0))


def _as_transform(raw: Tensor) -> ReliefTransform:
    """The network's output ``(B, 3)``, ``(log scale, tilt_x, tilt_y)``, as a transform."""
    return ReliefTransform(scale=raw[:, 0].exp(), tilt_x=raw[:, 1], tilt_y=raw[:, 2])


def predict_relief(normals: Tensor, mask: Tensor, net: ReliefNet, passes: int = 2) -> ReliefTransform:
    r"""The transform the prior expects to correct each orthographic normal field.

    Each pass crops the field (:func:`crop_to_object`) at three margins (1.0, 1.1, 1.25),
    reads the network on the eight symmetries of each crop (mirrors, quarter turns),
    averages the 24 transforms and applies the mean to the field; a second pass reads the
    corrected field again (on the tuning side both took the error further,
    docs/pipeline.md). The result is the composition of the passes.

    Args:
        normals: :math:`(B, 3, H, W)` or :math:`(3, H, W)` unit normals on the mask.
        mask: :math:`(B, 1, H, W)` or :math:`(1, H, W)` bool or {0, 1}, none empty.
        net: a :class:`ReliefNet` (:func:`load_relief_net`), used on its device in float32.
        passes: how often to read and correct, an integer >= 1.

    Returns:
        :class:`ReliefTransform` of :math:`(B,)` tensors, float32 on ``normals``' device;
        not differentiable.

    Raises:
        ValueError: wrong shapes or sizes, an empty mask, non-unit normals on the mask, bad ``passes``.
    """
    normals, _ = to_batch(normals, "normals", 3)
    mask, _ = to_batch(mask, "mask", 1)
    check_shape(normals, "normals", "B 3 H W")
    check_same_size(normals, "normals", mask, "mask")
    mask = check_mask(mask, allow_full=True)
    if not is_integer(passes, 1):
        raise ValueError(f"passes must be an integer >= 1, got {passes!r}")
    normals = normals.detach().float()
    check_unit_vectors(normals.permute(0, 2, 3, 1)[mask[:, 0]], "normals", " on the mask")
    device = next(net.parameters()).device
    batch = normals.shape[0]
    total = _identity(batch, normals.device)
    current = normals * mask
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad():
            for _ in range(passes):
                step = _network_transform(net, _crops(current, mask, RELIEF_CROP_SIZE, _READ_MARGINS).to(device))
                step = ReliefTransform(*(x.to(normals.device) for x in (step.scale, step.tilt_x, step.tilt_y)))
                current = apply_relief(current, mask, step)
                total = compose_relief(total, step)
    finally:
        net.train(was_training)
    return total


class ReliefPrior(nn.Module):
    """Module form of :func:`predict_relief` holding the network (the shipped one by default).

    ``forward(normals, mask) -> ReliefTransform``.
    """

    def __init__(self, net: Optional[ReliefNet] = None, passes: int = 2):
        super().__init__()
        if not is_integer(passes, 1):
            raise ValueError(f"passes must be an integer >= 1, got {passes!r}")
        self.net = load_relief_net() if net is None else net
        self.passes = passes

    def forward(self, normals: Tensor, mask: Tensor) -> ReliefTransform:
        return predict_relief(normals, mask, self.net, self.passes)


RELIEF_PRIOR_FILE = "data/relief_prior.npz"


def load_relief_net(path: Optional[str] = None, *, device: Optional[torch.device] = None) -> ReliefNet:
    """The network whose weights ship with the package (or those saved at ``path`` by
    ``tools/build_relief_prior.py``), in eval mode on ``device``.

    Raises:
        ValueError: ``path`` cannot be read or holds no :func:`save_relief_net` weights.
    """
    source = resources.files("sfs_torch").joinpath(RELIEF_PRIOR_FILE) if path is None else path
    try:
        with (source.open("rb") if path is None else open(source, "rb")) as f:
            with np.load(f, allow_pickle=False) as npz:
                settings = json.loads(str(npz["settings"]))
                state = {k: torch.from_numpy(npz[k].astype(np.float32)) for k in npz.files if k != "settings"}
        net = ReliefNet(hidden=settings["hidden"])
        net.load_state_dict(state)
    except (OSError, ValueError, KeyError, RuntimeError) as error:
        raise ValueError(f"{str(source)!r} holds no relief prior's weights (tools/build_relief_prior.py writes "
                         f"them): {type(error).__name__}: {error}") from None
    return net.to(device).eval()


def save_relief_net(net: ReliefNet, path: str, settings: dict) -> None:
    """Write ``net``'s weights and the ``settings`` it was trained with (JSON) to an ``.npz``."""
    state = {k: v.detach().cpu().numpy() for k, v in net.state_dict().items()}
    hidden = net.head[1].out_features
    np.savez_compressed(path, settings=np.array(json.dumps({**settings, "hidden": hidden})), **state)


def relief_training_views(meshes: Sequence, views_per_shape: int, generator: torch.Generator, *,
                          resolution: int = 128, scale: float = 0.9, min_pixels: int = 200,
                          progress: Optional[Callable] = None) -> Tensor:
    """Cropped true normal maps (:func:`crop_to_object`) of meshes in uniformly random views.

    Args:
        meshes: ``trimesh.Trimesh`` objects normalised to the unit sphere (``sfs_torch.shapes``).
        views_per_shape: random views per mesh (:func:`sfs_torch.rendering.random_view_rotations`).
        generator: the source of the views.
        resolution: of the orthographic render (:func:`sfs_torch.rendering.render_normals`).
        scale: the unit sphere's radius in the render, as a fraction of half the resolution.
        min_pixels: views whose object covers fewer pixels are left out.
        progress: optional wrapper of the mesh iterable (e.g. ``tqdm``).

    Returns:
        :math:`(N, 4, 64, 64)`.

    Raises:
        ValueError: no view has ``min_pixels`` object pixels.
    """
    from .rendering import random_view_rotations, render_normals

    crops = []
    for mesh in (progress(meshes) if progress else meshes):
        for rotation in random_view_rotations(views_per_shape, generator):
            view = render_normals(mesh, rotation, resolution, scale=scale)
            if int(view.mask.sum()) >= min_pixels:
                crops.append(crop_to_object(view.normals[None], view.mask[None])[0])
    if not crops:
        raise ValueError(f"no view of the {len(meshes)} meshes covers min_pixels={min_pixels} pixels at "
                         f"resolution {resolution}")
    return torch.stack(crops)


def _smooth_perturbation(normals: Tensor, amplitude: float, generator: torch.Generator) -> Tensor:
    """Normals whose slopes carry a smooth random field (a bicubic 6x6 grid of Gaussians)."""
    field = torch.randn(normals.shape[0], 2, 6, 6, generator=generator)
    field = F.interpolate(field, size=normals.shape[-2:], mode="bicubic", align_corners=False) * amplitude
    nz = normals[:, 2:].clamp_min(0.05)
    return F.normalize(torch.cat([normals[:, :2] + field * nz, nz], 1), dim=1)


def mean_angle(normals: Tensor, truth: Tensor, mask: Tensor) -> Tensor:
    r"""Per image, the mean angle (radians) between two normal fields on the mask, differentiable:
    :math:`(B, 3, H, W), (B, 3, H, W), (B, 1, H, W) -> (B,)`; :func:`fit_relief_net`'s loss."""
    angle = torch.acos((normals * truth).sum(1).clamp(-1 + 1e-6, 1 - 1e-6))
    return (angle * mask[:, 0]).sum((1, 2)) / mask[:, 0].sum((1, 2)).clamp_min(1)


def best_relief(normals: Tensor, reference: Tensor, mask: Tensor, *, start: Optional[ReliefTransform] = None,
                iterations: int = 100) -> ReliefTransform:
    r"""The bas-relief transform that takes each normal field closest to a reference one.

    Minimises :func:`mean_angle` between the transformed ``normals`` (:func:`apply_relief`)
    and ``reference`` over the log scale and the two tilts of each image, by L-BFGS from
    ``start`` (the identity by default). With the true normals as ``reference`` this is an
    oracle: the error an orthographic estimate keeps once its bas-relief ambiguity is
    resolved exactly (``benchmarks/bas_relief.py``), the usual way to score estimates that
    are only defined up to that transform.

    Args:
        normals: :math:`(B, 3, H, W)` or :math:`(3, H, W)` unit normals on the mask.
        reference: unit normals of the same shape.
        mask: :math:`(B, 1, H, W)` or :math:`(1, H, W)` bool or {0, 1}, none empty.
        start: the transform to start from, :math:`(B,)` fields (e.g. the best of a grid:
            the angle is not convex in the transform).
        iterations: L-BFGS iterations, an integer >= 1.

    Returns:
        :class:`ReliefTransform` of :math:`(B,)` tensors on ``normals``' device, not
        differentiable.

    Raises:
        ValueError: wrong shapes or sizes, an empty mask, non-unit normals on the mask, bad
            ``start`` or ``iterations``.
    """
    normals, _ = to_batch(normals, "normals", 3)
    reference, _ = to_batch(reference, "reference", 3)
    mask, _ = to_batch(mask, "mask", 1)
    check_shape(normals, "normals", "B 3 H W")
    check_shape(reference, "reference", "B 3 H W")
    check_same_size(normals, "normals", reference, "reference")
    check_same_size(normals, "normals", mask, "mask")
    mask = check_mask(mask, allow_full=True)
    if not is_integer(iterations, 1):
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    for name, field in (("normals", normals), ("reference", reference)):
        check_unit_vectors(field.permute(0, 2, 3, 1)[mask[:, 0]], name, " on the mask")
    normals, reference, weights = normals.detach().double(), reference.detach().double(), mask.double()
    batch = normals.shape[0]
    if start is None:
        start = _identity(batch, normals.device)
    elif not isinstance(start, ReliefTransform) or any(
            not isinstance(x, Tensor) or x.numel() != batch for x in (start.scale, start.tilt_x, start.tilt_y)):
        raise ValueError(f"start must be a ReliefTransform of one value per image ({batch}), got {start!r}")
    params = torch.stack([start.scale.log(), start.tilt_x, start.tilt_y]).to(normals).detach().requires_grad_(True)
    optimiser = torch.optim.LBFGS([params], max_iter=iterations, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        optimiser.zero_grad()
        moved = bas_relief_normals(normals, params[0].exp(), params[1], params[2]) * weights
        # a sum of independent per-image terms: its optimum is every image's own
        loss = mean_angle(moved, reference, weights).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        optimiser.step(closure)
    found = params.detach().to(start.scale.dtype)
    return ReliefTransform(scale=found[0].exp(), tilt_x=found[1], tilt_y=found[2])


def fit_relief_net(views: Tensor, *, epochs: int = 16, batch_size: int = 64, tilt_std: float = 0.4,
                   log_scale_std: float = 0.5, perturbation: float = 0.4, learning_rate: float = 2e-3,
                   hidden: int = RELIEF_HIDDEN, seed: int = 0, progress: Optional[Callable] = None) -> ReliefNet:
    """Train a :class:`ReliefNet` on true cropped normal maps (:func:`relief_training_views`), on the CPU.

    Each step draws a batch, mirrors it at random, perturbs its slopes smoothly
    (``perturbation``: a wrong estimate is not a transform of the truth alone), applies a
    random transform (tilts Gaussian of std ``tilt_std``, log scale of std
    ``log_scale_std``) and minimises the mean angle between the network's correction of
    that field and the true one. AdamW with a one-cycle learning rate peaking at
    ``learning_rate``. Everything random comes from ``seed``. The defaults match the
    pipeline's own errors: on cross-fitted estimates of the training shapes the best
    transform's log scale spreads by 0.64 (0.46 on the tuning images), its tilts by 0.4,
    and the slopes left wrong after it by 0.38 rms (``benchmarks/relief_errors.py``,
    docs/pipeline.md).

    Returns:
        the trained network, in eval mode.
    """
    check_shape(views, "views", "N 4 64 64")
    for name, value in (("epochs", epochs), ("batch_size", batch_size), ("hidden", hidden)):
        if not is_integer(value, 1):
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    for name, value in (("tilt_std", tilt_std), ("log_scale_std", log_scale_std), ("perturbation", perturbation)):
        if not is_number(value, 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    if len(views) < batch_size:
        raise ValueError(f"views holds {len(views)} crops, fewer than one batch of {batch_size}")
    generator = torch.Generator().manual_seed(seed)
    torch_state = torch.random.get_rng_state()
    torch.manual_seed(seed)  # the layers' initial weights
    net = ReliefNet(hidden=hidden)
    torch.random.set_rng_state(torch_state)
    steps_per_epoch = len(views) // batch_size
    optimiser = torch.optim.AdamW(net.parameters(), lr=learning_rate / 2, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, learning_rate, total_steps=epochs * steps_per_epoch)
    net.train()
    for _ in (progress(range(epochs)) if progress else range(epochs)):
        order = torch.randperm(len(views), generator=generator)
        for step in range(steps_per_epoch):
            batch = views[order[step * batch_size:(step + 1) * batch_size]]
            flips = torch.rand(2, generator=generator) < 0.5
            batch = _seen_in(batch, bool(flips[0]), bool(flips[1]), False)
            truth, mask = batch[:, :3], batch[:, 3:]
            n = len(batch)
            scale = (torch.randn(n, generator=generator) * log_scale_std).exp()
            tilt = torch.randn(2, n, generator=generator) * tilt_std
            perturbed = _smooth_perturbation(truth, perturbation, generator) if perturbation > 0 else truth
            wrong = bas_relief_normals(perturbed, scale, tilt[0], tilt[1]) * mask
            corrected = apply_relief(wrong, mask, _as_transform(net(torch.cat([wrong, mask], 1))))
            loss = mean_angle(corrected, truth, mask).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
    return net.eval()
