"""The on-disk cache of trained forests, keyed by the lighting and every option that shapes a forest.

A forest is reused when the same lighting and options come again: a given lighting
(the same light stage, dataset or probe for many images). An estimated lighting is new
for nearly every image, so by default (``training.cache_forests="given"``) its forests
are not written at all. Entries are verified like the geometry database: a SHA-256
sidecar written after the data, so a crash in between leaves a mismatch that is
retrained, never a wrong pairing; a corrupt or non-finite entry is deleted with a
warning. The cache keeps the ``training.max_cached_forests`` most recently used.
"""
from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np
import torch
from torch import Tensor

from ._checks import is_integer
from .forest import VMFForest
from .geometry_db import _sha256, cache_dir

__all__ = ["CACHE_POLICIES", "forest_path", "load_forest", "save_forest", "evict_forests"]

log = logging.getLogger(__name__)

CACHE_POLICIES = ("given", "always", "never")


def forest_path(sh: Tensor, options: Dict[str, Any]) -> Path:
    """Where the forest for lighting ``sh`` (:math:`(3, 9)`) and ``options`` (a dict of plain values) lives."""
    payload = {"lighting": np.round(sh.detach().double().cpu().numpy(), 6).tolist(), **options}
    key = hashlib.sha256(repr(payload).encode()).hexdigest()[:24]
    return cache_dir() / "forests" / f"{key}.safetensors"


def _checksum_path(path: Path) -> Path:
    return path.with_suffix(".sha256")


def load_forest(path: Path, device: torch.device) -> Optional[VMFForest]:
    """The cached forest at ``path`` if it verifies, else ``None``; a corrupt entry is deleted, never trusted."""
    if not path.exists():
        return None
    try:
        if _checksum_path(path).read_text().strip() != _sha256(path):
            raise ValueError("checksum mismatch")
        forest = VMFForest.load(path)
        if not (bool(torch.isfinite(forest.mean_).all()) and bool(torch.isfinite(forest.kappa_).all())):
            raise ValueError("non-finite leaves")
    except Exception as err:  # whatever fails to load would fail every later run: corrupt
        log.warning("deleting unusable cached forest %s (%s); training a new one", path, err)
        path.unlink(missing_ok=True)
        _checksum_path(path).unlink(missing_ok=True)
        return None
    log.info("reusing the forest trained for this lighting: %s", path)
    path.touch()  # the cache evicts the least recently used forests
    return forest.to(device)


def save_forest(forest: VMFForest, path: Path) -> None:
    """Write the forest, then its checksum, each atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    forest.save(tmp)
    digest = _sha256(tmp)
    os.replace(tmp, path)
    tmp_sum = tmp.with_suffix(".sha256tmp")
    tmp_sum.write_text(digest)
    os.replace(tmp_sum, _checksum_path(path))


def evict_forests(folder: Path, keep: int) -> None:
    """Delete all but the ``keep`` most recently used forests in ``folder``.

    Raises:
        ValueError: ``keep`` is not an integer >= 0.
    """
    # a bad keep would slice wrongly (None keeps nothing, -1 deletes only the oldest)
    if not is_integer(keep, 0):
        raise ValueError(f"keep must be an integer >= 0, got {keep!r}")

    def last_used(path: Path) -> float:
        try:
            return path.stat().st_mtime
        except FileNotFoundError:  # another process evicted it meanwhile
            return float("-inf")

    for path in sorted(folder.glob("*.safetensors"), key=last_used, reverse=True)[keep:]:
        path.unlink(missing_ok=True)
        _checksum_path(path).unlink(missing_ok=True)
