"""Argument checks run at public entry points.

Each check names the argument and says what was expected, so that a user sees one
clear ``ValueError`` instead of a stack trace from deep inside an operation.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

__all__ = [
    "check_shape",
    "check_finite",
    "check_mask",
    "check_same_size",
    "is_number",
    "to_batch",
    "from_batch",
]


def check_shape(x: Tensor, name: str, spec: str, floating: bool = True) -> None:
    """Check that ``x`` is a tensor of shape ``spec`` (e.g. ``"B 3 H W"``).

    Named dimensions match anything; digits must match exactly.

    Raises:
        TypeError: ``x`` is not a tensor.
        ValueError: wrong number of dimensions, a fixed size differs, or ``x`` is
            not floating point while ``floating`` is set.
    """
    dims = spec.split()
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape ({', '.join(dims)}), got {type(x).__name__}")
    if x.ndim != len(dims) or any(d.isdigit() and int(d) != n for d, n in zip(dims, x.shape)):
        raise ValueError(f"{name} must have shape ({', '.join(dims)}), got {tuple(x.shape)}")
    if floating and not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {x.dtype}")


def is_number(value, minimum: float = -math.inf, *, strict: bool = False) -> bool:
    """Whether ``value`` is a finite real number (an ``int`` or ``float``, not a ``bool``)
    at least ``minimum``, or above it with ``strict``: the test of a numeric option."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and (value > minimum if strict else value >= minimum))


def is_integer(value, minimum: float = -math.inf, maximum: float = math.inf) -> bool:
    """Whether ``value`` is an ``int`` (not a ``bool``) in ``[minimum, maximum]``: the test
    of an integer option."""
    return isinstance(value, int) and not isinstance(value, bool) and minimum <= value <= maximum


def check_finite(x: Tensor, name: str) -> None:
    """Raise ``ValueError`` when ``x`` holds NaN or infinite values."""
    # NaN and inf propagate into the sum, so a finite sum (one cheap pass, no boolean
    # temporary) clears x; otherwise, or when large finite values overflow it, look closer
    if not x.is_floating_point() or bool(torch.isfinite(x.sum())):
        return
    if not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name} contains {bad} NaN or infinite values")


def check_unit_vectors(x: Tensor, name: str, where: str = "") -> None:
    """``ValueError`` unless every vector along the last axis of ``x`` has length 1 within
    1e-3; ``where`` (e.g. ``" on the mask"``) says which vectors were taken."""
    squared = x.detach().square().sum(-1)  # |v|^2: no square root per vector
    if bool(((squared > (1.0 + 1e-3) ** 2) | (squared < (1.0 - 1e-3) ** 2)).any()):
        raise ValueError(
            f"{name} must have unit length (within 1e-3){where}, got lengths from "
            f"{float(squared.min().sqrt()):.4g} to {float(squared.max().sqrt()):.4g}"
        )


def check_mask(mask: Tensor, name: str = "mask", allow_full: bool = False, allow_empty: bool = False) -> Tensor:
    """Validate a ``(B, 1, H, W)`` mask and return it as ``bool``.

    Accepts ``bool`` or numeric tensors holding only 0 and 1.

    Raises:
        ValueError: wrong shape, values other than 0/1, (unless ``allow_empty``) an empty
            mask in any batch element, or (unless ``allow_full``) a mask that covers the
            whole image, which leaves no silhouette to read.
    """
    if not isinstance(mask, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape (B, 1, H, W), got {type(mask).__name__}")
    if mask.ndim != 4 or mask.shape[1] != 1:
        raise ValueError(f"{name} must have shape (B, 1, H, W), got {tuple(mask.shape)}")
    if mask.dtype != torch.bool:
        if mask.is_complex() or not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError(f"{name} must be boolean or hold only 0 and 1 (dtype {mask.dtype})")
        mask = mask != 0
    counts = mask.flatten(1).sum(1)
    if not allow_empty and bool((counts == 0).any()):
        which = torch.nonzero(counts == 0).flatten().tolist()
        raise ValueError(f"{name} is empty (no object pixel) in batch element(s) {which}")
    if not allow_full and bool((counts == mask[0].numel()).any()):
        which = torch.nonzero(counts == mask[0].numel()).flatten().tolist()
        raise ValueError(
            f"{name} covers the whole image in batch element(s) {which}: the method needs the "
            "object's silhouette, so some background must be visible"
        )
    return mask


def check_same_size(a: Tensor, a_name: str, b: Tensor, b_name: str) -> None:
    """Raise ``ValueError`` when the batch and spatial sizes of two maps differ."""
    if a.shape[0] != b.shape[0] or a.shape[-2:] != b.shape[-2:]:
        raise ValueError(
            f"{a_name} and {b_name} must have the same batch size and height/width, got "
            f"{tuple(a.shape)} and {tuple(b.shape)}"
        )


def to_batch(x: Tensor, name: str, channels: Optional[int], ndim_single: int = 3) -> Tuple[Tensor, bool]:
    """Add a batch axis to single ``(C, H, W)`` input; return ``(batched, was_single)``.

    ``(H, W)`` input is accepted for one-channel maps (``channels == 1``).
    """
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if channels == 1 and x.ndim == 2:
        return x[None, None], True
    if x.ndim == ndim_single:
        return x[None], True
    if x.ndim == ndim_single + 1:
        return x, False
    expected: Sequence[str] = ["C" if channels is None else str(channels), "H", "W"]
    raise ValueError(
        f"{name} must have shape ({', '.join(expected)}) or (B, {', '.join(expected)}), got {tuple(x.shape)}"
    )


def from_batch(x: Optional[Tensor], was_single: bool) -> Optional[Tensor]:
    """Undo :func:`to_batch`: drop the batch axis of single input."""
    if x is None or not was_single:
        return x
    return x[0]
