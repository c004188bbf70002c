"""Large batches computed in blocks along the batch axis.

On CPU a fresh temporary the size of a whole large batch (the 150000 training patches:
45 MB) costs about as much as the arithmetic on it (first-touch page faults), while
block-sized temporaries stay in cache and are reused.
"""
from __future__ import annotations

from typing import Callable, Sequence

from torch import Tensor

BLOCK_VALUES = 1 << 18  # input values per block


def in_blocks(fn: Callable[[slice], Tensor], batch: int, values_per_item: int, out_shape: Sequence[int],
              like: Tensor) -> Tensor:
    """``fn(slice(None))``, computed as ``fn(part)`` over blocks of about :data:`BLOCK_VALUES` input values.

    Args:
        fn: the result for the batch items of a slice.
        batch: number of items; values_per_item: input values of one item.
        out_shape: shape of the whole result; like: a tensor whose dtype and device it takes.

    Returns:
        the whole result (the blocks written into one tensor; differentiable like ``fn``).
    """
    step = max(1, BLOCK_VALUES // max(1, values_per_item))
    if batch <= step:
        return fn(slice(None))
    out = like.new_empty(tuple(out_shape))
    for start in range(0, batch, step):
        part = slice(start, start + step)
        out[part] = fn(part)
    return out
