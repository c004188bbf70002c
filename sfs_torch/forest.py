r"""Regression forest with von Mises-Fisher leaves (Richter & Roth 2015, Sec. 5).

The forest is retrained for every test lighting, so training speed dominates the
method's cost. Trees grow one level per Python iteration, with histogram split search;
on the CPU each tree grows on its own and ``n_jobs`` trees at once in threads, its split
search and routing compiled by Numba (``sfs_torch._forest_kernel``, float32; the loops
release the GIL); on other devices (and in float64) all trees grow together in torch
ops:

1. every feature is cut once into ``n_bins`` quantile bins (the edges are data values,
   so a bin threshold is also an exact threshold on the raw feature);
2. each tree draws a random ``sample_fraction`` of the rows (without replacement); the
   (tree, row) pairs of the nodes still growing are kept grouped by node (a stable
   partition per level), so the histogram of one node is built from one contiguous run
   of pairs; pairs of nodes that cannot split are dropped;
3. per level, every node draws its ``max_features`` features by hashing (seed, node key,
   feature) on the device (no generator, no host transfer), where a node's key hashes
   its tree's index and its path from the root, so the draws (and the forest) do not
   depend on which trees grow together or on ``n_jobs``; per node and feature the
   count and the vector sum of the normals are accumulated per bin, prefix sums over
   bins give both children of every threshold, and all thresholds that change the
   partition and leave ``min_samples_leaf`` rows on each side are scored by the
   children's count-weighted vMF entropy ``n_L H(kappa_L) + n_R H(kappa_R)`` (in torch
   ops: ``scatter_add_`` of two complex streams ``count + i n_x``, ``n_y + i n_z`` per
   feature slot, a ``cumsum`` and one batched scoring of the level);
4. a node splits at its best threshold when that lowers the entropy below the
   parent's ``n H(kappa)`` and the depth is below ``max_depth``; otherwise it is a leaf.

On a GPU the level loop syncs with the host twice per level (the number of candidate
thresholds; the next level's sizes). Nodes of all trees live in
one flat table in level order; a leaf points to itself with threshold ``+inf``, so
prediction is ``depth`` rounds of 1-D gathers. See ``docs/forest.md`` for the choices
and measurements.
"""
from __future__ import annotations

import json
import logging
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Optional, Union

import numpy as np
import torch
from torch import Tensor

from ._checks import check_finite, check_shape, check_unit_vectors, is_integer

__all__ = [
    "VMF",
    "MAX_KAPPA",
    "vmf_fit",
    "vmf_entropy",
    "sample_vmf",
    "ForestConfig",
    "VMFForest",
    "NotFittedError",
]

logger = logging.getLogger(__name__)

#: Cap on the concentration. Dhillon-Sra's estimate diverges as the mean resultant
#: length R -> 1 (one sample, or identical normals); 1e4 is a spread of about 0.6 deg,
#: finer than any normal the method can resolve, and keeps every entropy finite.
MAX_KAPPA = 1e4

# Below this kappa the entropy formula loses precision in float32; H is flat there
# (log 4 pi up to O(kappa^2)), so clamping changes nothing measurable.
_MIN_KAPPA = 1e-4


@dataclass(frozen=True)
class VMF:
    """Von Mises-Fisher distributions on the unit sphere S^2.

    Attributes:
        mean: unit mean directions, :math:`(..., 3)`.
        kappa: concentrations, :math:`(...)`, ``>= 0``.
    """

    mean: Tensor
    kappa: Tensor


def _kappa_from_r2(r2: Tensor, max_kappa: float) -> Tensor:
    # Dhillon & Sra for p = 3: kappa = R (3 - R^2) / (1 - R^2), from R^2 in [0, 1].
    r2 = r2.clamp(0.0, 1.0)
    r = r2.sqrt()
    denom = (1.0 - r2).clamp_min(torch.finfo(r2.dtype).tiny)
    return (r * (3.0 - r2) / denom).clamp(max=max_kappa)


def vmf_fit(normal_sum: Tensor, count: Tensor, max_kappa: float = MAX_KAPPA) -> VMF:
    r"""Fit vMF distributions from sufficient statistics (Dhillon & Sra 2003).

    ``mean = r / |r|``, ``kappa = (3R - R^3) / (1 - R^2)`` with ``R = |r| / count``.
    Degenerate input stays finite: ``R -> 1`` (one sample, identical normals) gives
    ``max_kappa``; a zero vector sum or ``count == 0`` gives ``kappa = 0`` and the
    mean ``(0, 0, 1)`` (the viewing direction; any unit vector is a valid mean of a
    uniform distribution).

    Args:
        normal_sum: vector sums of unit normals, :math:`(..., 3)`.
        count: numbers of normals summed, :math:`(...)`.
        max_kappa: upper bound on the concentration.

    Returns:
        :class:`VMF` with ``mean`` :math:`(..., 3)` and ``kappa`` :math:`(...)`.

    Example:
        >>> v = vmf_fit(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([2.0]))
        >>> v.kappa
        tensor([10000.])
    """
    check_shape(normal_sum, "normal_sum", " ".join(["D"] * (normal_sum.ndim - 1) + ["3"]))
    if not isinstance(count, Tensor) or count.shape != normal_sum.shape[:-1]:
        got = tuple(count.shape) if isinstance(count, Tensor) else type(count).__name__
        raise ValueError(f"count must be a tensor of shape {tuple(normal_sum.shape[:-1])}, got {got}")
    count = count.to(normal_sum.dtype)
    length = normal_sum.norm(dim=-1)
    positive = length > 0
    safe = torch.where(positive, length, torch.ones_like(length))
    up = normal_sum.new_tensor([0.0, 0.0, 1.0])
    mean = torch.where(positive[..., None], normal_sum / safe[..., None], up)
    r2 = (length / count.clamp_min(1.0)).square()
    kappa = torch.where(positive, _kappa_from_r2(r2, max_kappa), torch.zeros_like(length))
    return VMF(mean=mean, kappa=kappa)


def vmf_entropy(kappa: Tensor) -> Tensor:
    r"""Differential entropy (nats) of a vMF distribution on S^2.

    ``H = -log C(kappa) - kappa A(kappa)`` with ``C = kappa / (4 pi sinh kappa)`` and
    ``A = coth kappa - 1/kappa``, written as
    ``log(2 pi) + 1 + log((1 - e^{-2 kappa}) / kappa) - 2 kappa / (e^{2 kappa} - 1)``
    so that it neither overflows for large kappa nor cancels for small kappa.
    Tends to ``log(4 pi)`` (uniform) as ``kappa -> 0``.

    Args:
        kappa: concentrations, any shape, ``>= 0``.

    Returns:
        entropies, same shape, dtype and device.

    Example:
        >>> vmf_entropy(torch.tensor([0.0, 10.0]))
        tensor([2.5310, 0.5353])
    """
    k = kappa.clamp_min(_MIN_KAPPA)
    m = torch.expm1(-2.0 * k)  # e^{-2k} - 1, in (-1, 0)
    # 2k / (e^{2k} - 1) = -2k e^{-2k} / (e^{-2k} - 1)
    return torch.log(m / -k).add_(2.0 * k * (1.0 + m) / m).add_(math.log(2.0 * math.pi) + 1.0)


def _orthonormal_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    # Duff et al. 2017 branchless basis: continuous except on n_z = 0 sign flips,
    # which is harmless for sampling a rotation-invariant tangent direction.
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    t2 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return t1, t2


def sample_vmf(vmf: VMF, n_samples: int, generator: Optional[torch.Generator] = None) -> Tensor:
    r"""Draw samples from vMF distributions on S^2 (Wood 1994).

    Wood's construction: draw the cosine ``w`` to the mean from its marginal, a
    uniform direction in the tangent plane, and combine. On S^2 the marginal of ``w``
    has a closed-form inverse CDF, ``w = 1 + log(u + (1 - u) e^{-2 kappa}) / kappa``,
    so no rejection loop is needed; it is evaluated in the stable ``log1p``/``expm1``
    form (Jakob 2012) and is uniform (``w = 2u - 1``) for ``kappa -> 0``.

    Args:
        vmf: distributions with ``mean`` :math:`(..., 3)`, ``kappa`` :math:`(...)`.
        n_samples: samples per distribution.
        generator: random generator on the distributions' device (reproducibility).

    Returns:
        unit vectors, :math:`(..., n\_samples, 3)`.
    """
    if not isinstance(vmf, VMF):
        raise TypeError(f"vmf must be a VMF(mean, kappa) (e.g. VMFForest.predict's output), got {type(vmf).__name__}")
    check_shape(vmf.mean, "vmf.mean", " ".join(["D"] * (vmf.mean.ndim - 1) + ["3"]))
    if vmf.kappa.shape != vmf.mean.shape[:-1]:
        raise ValueError(f"vmf.kappa must have shape {tuple(vmf.mean.shape[:-1])}, got {tuple(vmf.kappa.shape)}")
    if not is_integer(n_samples, 1):
        raise ValueError(f"n_samples must be a positive int, got {n_samples!r}")
    mean, dtype, device = vmf.mean, vmf.mean.dtype, vmf.mean.device
    shape = (*vmf.kappa.shape, n_samples)
    u = torch.rand(shape, generator=generator, dtype=dtype, device=device)
    phi = torch.rand(shape, generator=generator, dtype=dtype, device=device) * (2.0 * math.pi)
    k = vmf.kappa.to(dtype)[..., None].clamp_min(torch.finfo(dtype).tiny)
    # log(u + (1-u) e^{-2k}) = log1p(-(1-u)(1 - e^{-2k}))
    w = 1.0 + torch.log1p((1.0 - u) * torch.expm1(-2.0 * k)) / k
    w = w.clamp(-1.0, 1.0)
    s = (1.0 - w * w).clamp_min(0.0).sqrt()
    t1, t2 = _orthonormal_basis(mean)
    out = (
        w[..., None] * mean[..., None, :]
        + (s * phi.cos())[..., None] * t1[..., None, :]
        + (s * phi.sin())[..., None] * t2[..., None, :]
    )
    return out / out.norm(dim=-1, keepdim=True)


def _weighted_entropy(n: Tensor, sx: Tensor, sy: Tensor, sz: Tensor, max_kappa: float) -> Tensor:
    # n * H(kappa(R)) for node statistics of any shape; n = 0 gives 0. Bit for bit
    # vmf_entropy(_kappa_from_r2(R^2)) * n, with the same operations done in place on
    # a few temporaries (this scores every candidate threshold).
    r2 = sx * sx
    r2.addcmul_(sy, sy).addcmul_(sz, sz)
    r2.div_(n.clamp_min(1.0).square()).clamp_(0.0, 1.0)
    k = r2.sqrt().mul_(torch.rsub(r2, 3.0))  # R (3 - R^2)
    # R = 1 divides by 0: inf, clamped to max_kappa as any tiny denominator would be
    k.div_(r2.neg_().add_(1.0)).clamp_(_MIN_KAPPA, max_kappa)
    m = torch.mul(k, -2.0).expm1_()
    h = torch.div(m, k).neg_().log_()
    h.addcdiv_(m.add(1.0).mul_(k), m, value=2.0)  # + 2 kappa (1 + m) / m
    return h.add_(math.log(2.0 * math.pi) + 1.0).mul_(n)


@dataclass
class ForestConfig:
    """Hyper-parameters of :class:`VMFForest` (defaults chosen in ``docs/forest.md``, the
    number of trees for the whole method in ``docs/pipeline.md``)."""

    _target_: str = "sfs_torch.forest.VMFForest"
    n_trees: int = 16
    max_depth: int = 14
    min_samples_leaf: int = 10
    max_features: Union[int, float] = 8
    n_bins: int = 64
    sample_fraction: float = 0.9
    seed: int = 0
    n_jobs: Optional[int] = None


class NotFittedError(ValueError, AttributeError):
    """``predict`` / ``save`` was called before ``fit`` (like scikit-learn's, a ``ValueError``)."""


_TENSORS = ("feature", "threshold", "child", "mean", "kappa")


class VMFForest:
    """Regression forest predicting unit normals with vMF leaves.

    Args:
        n_trees: number of trees.
        max_depth: number of split levels (0 gives one leaf per tree).
        min_samples_leaf: fewest in-bag rows a leaf may hold.
        max_features: features tried per node: an int, or a fraction of the features.
        n_bins: quantile bins per feature for split search (2 to 256).
        sample_fraction: share of the rows each tree trains on (without replacement).
        seed: seed of every random draw (row subsets, feature subsets).
        device: device to train on; ``None`` trains where ``X`` lives.
        n_jobs: trees grown at once in threads on the CPU; ``None`` is
            ``torch.get_num_threads()``. The forest does not depend on it (bit for bit);
            ignored on other devices, where all trees grow together.

    Attributes (after :meth:`fit`; nodes of all trees in one flat level-ordered table):
        feature_: split feature per node, :math:`(M,)` int64 (0 in leaves).
        threshold_: rows with ``X[:, feature] > threshold`` go right, :math:`(M,)`;
            ``+inf`` in leaves.
        child_: index of the left child (right is ``+1``); a leaf points to itself.
        mean_: vMF mean per node, :math:`(M, 3)`; kappa_: concentration, :math:`(M,)`.
        n_features_in_: number of features; depth_: levels actually grown.

    Example:
        >>> X = torch.rand(2000, 3)
        >>> n = torch.nn.functional.normalize(torch.stack([X[:, 0] - 0.5, X[:, 1] - 0.5, torch.ones(2000)], 1), dim=1)
        >>> forest = VMFForest(n_trees=4, max_depth=6, max_features=3).fit(X, n)
        >>> forest.predict(X[:5]).mean.shape
        torch.Size([5, 3])
    """

    def __init__(
        self,
        n_trees: int = ForestConfig.n_trees,
        max_depth: int = ForestConfig.max_depth,
        min_samples_leaf: int = ForestConfig.min_samples_leaf,
        max_features: Union[int, float] = ForestConfig.max_features,
        n_bins: int = ForestConfig.n_bins,
        sample_fraction: float = ForestConfig.sample_fraction,
        seed: int = ForestConfig.seed,
        device: Optional[Union[str, torch.device]] = None,
        n_jobs: Optional[int] = ForestConfig.n_jobs,
    ) -> None:
        self.n_trees = n_trees
        self.max_depth = max_depth
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.n_bins = n_bins
        self.sample_fraction = sample_fraction
        self.seed = seed
        self.device = device
        self.n_jobs = n_jobs

    # ------------------------------------------------------------------ params
    def get_params(self) -> dict:
        """Constructor arguments (``device`` as a string)."""
        return {
            "n_trees": self.n_trees,
            "max_depth": self.max_depth,
            "min_samples_leaf": self.min_samples_leaf,
            "max_features": self.max_features,
            "n_bins": self.n_bins,
            "sample_fraction": self.sample_fraction,
            "seed": self.seed,
            "device": None if self.device is None else str(self.device),
            "n_jobs": self.n_jobs,
        }

    def _validate_params(self, n_features: int) -> int:
        def positive_int(name: str, minimum: int) -> None:
            value = getattr(self, name)
            if not is_integer(value, minimum):
                raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")

        positive_int("n_trees", 1)
        positive_int("max_depth", 0)
        positive_int("min_samples_leaf", 1)
        positive_int("seed", 0)
        j = self.n_jobs
        if j is not None and not is_integer(j, 1):
            raise ValueError(f"n_jobs must be None (torch.get_num_threads()) or an int >= 1, got {j!r}")
        if not is_integer(self.n_bins, 2, 256):
            raise ValueError(f"n_bins must be an int in [2, 256], got {self.n_bins!r}")
        if not (isinstance(self.sample_fraction, (int, float)) and 0.0 < self.sample_fraction <= 1.0):
            raise ValueError(f"sample_fraction must be in (0, 1], got {self.sample_fraction!r}")
        m = self.max_features
        if isinstance(m, bool) or not isinstance(m, (int, float)):
            raise ValueError(f"max_features must be an int or a float fraction, got {m!r}")
        if isinstance(m, float):
            if not 0.0 < m <= 1.0:
                raise ValueError(f"max_features as a fraction must be in (0, 1], got {m!r}")
            m = max(1, round(m * n_features))
        if m < 1:
            raise ValueError(f"max_features must be >= 1, got {m!r}")
        return min(m, n_features)

    # --------------------------------------------------------------------- fit
    def fit(self, X: Tensor, normals: Tensor) -> "VMFForest":
        """Grow the forest.

        Args:
            X: features, :math:`(N, F)` floating point, finite.
            normals: unit normals, :math:`(N, 3)`.

        Returns:
            ``self``.

        Raises:
            ValueError: bad shapes, NaN/inf, non-unit normals or bad hyper-parameters.
        """
        check_shape(X, "X", "N F")
        check_shape(normals, "normals", "N 3")
        if normals.shape[0] != X.shape[0]:
            raise ValueError(f"X and normals must have the same number of rows, got {X.shape[0]} and {normals.shape[0]}")
        if X.shape[0] < 1 or X.shape[1] < 1:
            raise ValueError(f"X must have at least one row and one feature, got {tuple(X.shape)}")
        check_finite(X, "X")
        check_finite(normals, "normals")
        check_unit_vectors(normals, "normals")
        m = self._validate_params(X.shape[1])
        device = torch.device(self.device) if self.device is not None else X.device
        # hard splits carry no gradient: training data that requires grad is read as constants
        X = X.detach().to(device).contiguous()
        normals = normals.detach().to(device=device, dtype=X.dtype)
        generator = torch.Generator().manual_seed(self.seed)

        edges = _quantile_edges(X, self.n_bins, generator)
        binned = _bin(X, edges)
        rows = _sample_rows(X.shape[0], self.n_trees, self.sample_fraction, generator, device)
        tree = _grow(
            binned,
            normals,
            rows,
            n_jobs=torch.get_num_threads() if self.n_jobs is None else self.n_jobs,
            max_depth=self.max_depth,
            min_samples_leaf=self.min_samples_leaf,
            max_features=m,
            n_bins=self.n_bins,
            seed=self.seed,
        )
        leaf = tree["child"] == torch.arange(tree["child"].numel(), device=device)
        threshold = edges[tree["feature"], tree["bin"].clamp(max=self.n_bins - 2)]
        self.feature_ = tree["feature"]
        self.threshold_ = torch.where(leaf, torch.full_like(threshold, math.inf), threshold)
        self.child_ = tree["child"]
        vmf = vmf_fit(tree["sum"], tree["count"])
        self.mean_, self.kappa_ = vmf.mean, vmf.kappa
        self.n_features_in_ = X.shape[1]
        self.depth_ = tree["depth"]
        return self

    # ----------------------------------------------------------------- predict
    def _check_fitted(self) -> None:
        if not hasattr(self, "child_"):
            raise NotFittedError("this VMFForest is not fitted yet: call fit(X, normals) first")

    def _leaf_index(self, X: Tensor) -> Tensor:
        self._check_fitted()
        check_shape(X, "X", "N F")
        if X.shape[1] != self.n_features_in_:
            raise ValueError(f"X must have {self.n_features_in_} features (as in fit), got {X.shape[1]}")
        check_finite(X, "X")
        X = X.to(device=self.threshold_.device, dtype=self.threshold_.dtype).contiguous()
        n_rows, n_features = X.shape
        # flat (row, tree) layout: every step is a handful of 1-D gathers
        node = torch.arange(self.n_trees, device=X.device).repeat(n_rows)
        row_start = torch.arange(0, n_rows * n_features, n_features, device=X.device).repeat_interleave(self.n_trees)
        values = X.view(-1)
        for _ in range(self.depth_):
            x = values.index_select(0, self.feature_.index_select(0, node).add_(row_start))
            node = self.child_.index_select(0, node).add_(x > self.threshold_.index_select(0, node))
        return node.view(n_rows, self.n_trees)

    def predict_leaves(self, X: Tensor) -> VMF:
        """Per-tree leaf distributions of each row (to draw samples from).

        Args:
            X: features, :math:`(N, F)`.

        Returns:
            :class:`VMF` with ``mean`` :math:`(N, T, 3)`, ``kappa`` :math:`(N, T)`.
        """
        node = self._leaf_index(X)
        flat = node.view(-1)
        mean = self.mean_.index_select(0, flat).view(*node.shape, 3)
        return VMF(mean=mean, kappa=self.kappa_.index_select(0, flat).view(node.shape))

    def predict(self, X: Tensor) -> VMF:
        r"""One normal and concentration per row.

        The trees' leaves are pooled by the normalised geometric mean of their
        densities, :math:`\prod_t f_t^{1/T}`, which is again a vMF: mean
        ``s / |s|``, ``kappa = |s| / T`` with ``s = sum_t kappa_t mu_t``. The mean is
        the kappa-weighted mean direction; unlike the plain product of densities
        (``kappa = |s|``) it does not treat the strongly correlated trees as
        independent evidence, so kappa stays on the leaves' scale for any ``T`` and
        drops where the trees disagree.

        Args:
            X: features, :math:`(N, F)`.

        Returns:
            :class:`VMF` with ``mean`` :math:`(N, 3)`, ``kappa`` :math:`(N,)`.
        """
        leaves = self.predict_leaves(X)
        s = (leaves.kappa[..., None] * leaves.mean).sum(1)
        pooled = vmf_fit(s, torch.full(s.shape[:1], float(self.n_trees), dtype=s.dtype, device=s.device))
        return VMF(mean=pooled.mean, kappa=s.norm(dim=1) / self.n_trees)

    # ------------------------------------------------------------- device / io
    def to(self, device: Union[str, torch.device]) -> "VMFForest":
        """Move the fitted forest to ``device`` (in place); returns ``self``."""
        self._check_fitted()
        for name in _TENSORS:
            setattr(self, name + "_", getattr(self, name + "_").to(device))
        return self

    def save(self, path: Union[str, Path]) -> None:
        """Write the fitted forest to a safetensors file (parameters as JSON metadata)."""
        from safetensors.torch import save_file

        self._check_fitted()
        tensors = {name: getattr(self, name + "_").detach().cpu().contiguous() for name in _TENSORS}
        meta = {
            "params": json.dumps(self.get_params()),
            "n_features_in": str(self.n_features_in_),
            "depth": str(self.depth_),
        }
        save_file(tensors, str(path), metadata=meta)

    @classmethod
    def load(cls, path: Union[str, Path], device: Optional[Union[str, torch.device]] = None) -> "VMFForest":
        """Read a forest written by :meth:`save` (bit-exact), onto ``device`` (default CPU)."""
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata()
            tensors = {name: f.get_tensor(name) for name in _TENSORS}
        forest = cls(**json.loads(meta["params"]))
        for name, value in tensors.items():
            setattr(forest, name + "_", value)
        forest.n_features_in_ = int(meta["n_features_in"])
        forest.depth_ = int(meta["depth"])
        return forest.to(device) if device is not None else forest


def _quantile_edges(X: Tensor, n_bins: int, generator: torch.Generator, max_rows: int = 50_000) -> Tensor:
    # Edges are order statistics of (a subsample of) X itself, so that
    # "bin <= b" <=> "x <= edges[b]" holds exactly in X's dtype.
    n = X.shape[0]
    if n > max_rows:
        rows = torch.randperm(n, generator=generator)[:max_rows].to(X.device)
        X, n = X.index_select(0, rows), max_rows
    ranks = (torch.arange(1, n_bins, device=X.device) * n) // n_bins
    columns = X.detach().T.contiguous()
    if columns.device.type == "cpu":
        # NumPy's vectorised sort is about 10x faster than torch's here (the same values)
        ordered = torch.from_numpy(np.sort(columns.numpy(), axis=1))
    else:
        ordered = columns.sort(dim=1).values
    return ordered[:, ranks]  # (F, n_bins - 1)


def _bin(X: Tensor, edges: Tensor) -> Tensor:
    # bin = number of edges strictly below x, as (F, N) uint8 (feature-major), by a
    # branch-free binary search over each feature's sorted edges padded with +inf to
    # 2^p - 1: p rounds of one flat gather and one comparison, 3x faster than counting
    # edge by edge at 64 bins and 10x at 256, with equal results (the predicate
    # "edge < x" is monotone along the sorted edges, ties included).
    n_features, n_edges = edges.shape
    p = n_edges.bit_length()
    width = 1 << p
    table = torch.cat([edges, edges.new_full((n_features, width - n_edges), math.inf)], 1).view(-1)
    start = torch.arange(0, n_features * width, width, dtype=torch.int32, device=X.device)[:, None]
    columns = X.T.contiguous()
    pos = start.expand(columns.shape).contiguous()  # flat table index of each value's lower bound
    probe, hit, value = torch.empty_like(pos), torch.empty_like(pos), torch.empty_like(columns)
    step = width >> 1
    while step:
        torch.index_select(table, 0, torch.add(pos, step - 1, out=probe).view(-1), out=value.view(-1))
        pos.add_(torch.gt(columns, value, out=hit), alpha=step)
        step >>= 1
    return pos.sub_(start).to(torch.uint8)


_MASK32 = 0xFFFFFFFF
# Index tensors are int32 (faster gathers, half the traffic) while what they address is
# smaller than this; a module constant so that tests can force the int64 path.
_INT32_LIMIT = 2**31


def _mix32(x):
    # Wellons' "lowbias32" integer hash of 32-bit values held in int64 tensors (or Python
    # ints). The second product is split in 16-bit halves so that no intermediate
    # reaches 2^63: no signed overflow, the same bits on every device.
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _MASK32
    x = x ^ (x >> 15)
    x = ((x * 0xA68B) + (((x * 0x846C) & 0xFFFF) << 16)) & _MASK32  # x * 0x846CA68B mod 2^32
    return x ^ (x >> 16)


def _draw_features(seed: int, node: Tensor, n_features: int, max_features: int) -> Tensor:
    """``max_features`` distinct features per node, uniformly at random: ``(len(node), max_features)`` int64.

    Counter-based: a node's draw is the order of ``n_features`` hashes of ``(seed,
    node id, feature)``, computed on the nodes' device. So it needs no generator, no
    host transfer and no sync, and a seed gives the same draws on every device.
    """
    key = 0x5BD1E995
    for shift in range(0, max(seed.bit_length(), 1), 32):
        key = _mix32(key ^ ((seed >> shift) & _MASK32))
    weyl = (torch.arange(n_features, device=node.device) * 0x9E3779B9) & _MASK32  # one stream per feature
    keys = _mix32((_mix32((node & _MASK32) ^ key)[:, None] + weyl) & _MASK32)
    return keys.argsort(dim=1, stable=True)[:, :max_features]


def _compact(mask: Tensor, size: int) -> Tensor:
    # mask.nonzero().squeeze(1) when its size is already known on the host: no sync.
    pos = torch.where(mask, mask.cumsum(0) - 1, size)
    out = torch.empty(size + 1, dtype=torch.long, device=mask.device)
    return out.index_copy_(0, pos, torch.arange(mask.numel(), device=mask.device))[:size]


def _stats(c0: Tensor, c1: Tensor) -> list[Tensor]:
    # the two complex streams (count + i n_x, n_y + i n_z) -> strided real views
    # [count, n_x, n_y, n_z], without copying.
    a, b = torch.view_as_real(c0), torch.view_as_real(c1)
    return [a[..., 0], a[..., 1], b[..., 0], b[..., 1]]


def _child_keys(parent: Tensor, side: Tensor) -> Tensor:
    # A node's key for _draw_features, from its parent's key and its side (0 left, 1
    # right): a bijective 32-bit hash, so siblings never share a key. Roots are keyed by
    # their tree's index, so a node's draws depend on its tree and its path from the
    # root only, not on the other trees or on which of them grow together.
    return _mix32((parent + 0x9E3779B9 * (1 + side)) & _MASK32)


def _sample_rows(
    n_rows: int, n_trees: int, sample_fraction: float, generator: torch.Generator, device: torch.device
) -> Tensor:
    """In-bag rows of each tree, ``(n_trees, n_in)`` int64 on ``device``, ascending within a tree.

    Drawn without replacement on the CPU generator, tree after tree, so that a seed
    gives the same rows on every device and for any grouping of the trees; one
    transfer and one ``nonzero`` (a host sync on a GPU).
    """
    n_in = max(1, round(sample_fraction * n_rows))
    in_bag = torch.zeros(n_trees, n_rows, dtype=torch.bool)
    for tree in range(n_trees):
        in_bag[tree, torch.randperm(n_rows, generator=generator)[:n_in]] = True
    return in_bag.to(device).nonzero()[:, 1].view(n_trees, n_in)


class _Level(NamedTuple):
    """One tree level of a group of trees, nodes in level order: split feature and bin
    (0 where not split), whether the node split, in-bag count and normal sum (M, 3)."""

    feature: Tensor
    bin: Tensor
    split: Tensor
    count: Tensor
    sum: Tensor


class _Workspace:
    """Buffers one group of trees reuses at every level: the histogram, and per-pair
    scratch sliced to the level's pair count (pairs only ever drop out)."""

    def __init__(self, n_pairs: int, index_dtype: torch.dtype, stat_dtype: torch.dtype, device: torch.device):
        self.hist = torch.empty(0, dtype=stat_dtype, device=device)
        self.pair_index = torch.arange(n_pairs, device=device)
        self.where = torch.empty(n_pairs, dtype=index_dtype, device=device)
        self.code = torch.empty(n_pairs, dtype=torch.uint8, device=device)
        self.cell = torch.empty(n_pairs, dtype=torch.int64, device=device)


def _grow(
    binned: Tensor,
    normals: Tensor,
    rows: Tensor,
    *,
    n_jobs: int,
    max_depth: int,
    min_samples_leaf: int,
    max_features: int,
    n_bins: int,
    seed: int,
) -> dict:
    """Grow the trees whose in-bag ``rows`` (T, n_in) are given, on binned features ``(F, N)`` uint8.

    On the CPU every tree grows on its own (:func:`_grow_trees` on one tree), ``n_jobs``
    of them at a time in threads, on the compiled loops in float32 (:func:`_rows_table`
    is built once for all trees) and on torch ops in float64; both release the GIL, so
    the threads use the cores. A tree's work does not depend on the others, so the forest
    is the same bit for bit for any ``n_jobs``. On other devices all trees grow as one
    group in the calling thread (a GPU parallelises within each op).

    Returns a dict of flat node tensors in level order (the nodes of level ``l`` of all
    trees, tree after tree): ``feature`` (M,), ``bin`` (M,) (rows whose bin exceeds it
    go right), ``child`` (M,) (left child, self for leaves), ``count`` (M,), ``sum``
    (M, 3), and ``depth`` (int, levels grown).
    """
    n_trees, n_in = rows.shape
    n_features, n_rows = binned.shape
    index_dtype = torch.int32 if max(n_trees * n_in, n_features * n_rows) < _INT32_LIMIT else torch.int64
    kw = dict(
        max_depth=max_depth, min_samples_leaf=min_samples_leaf, max_features=max_features, n_bins=n_bins,
        seed=seed, index_dtype=index_dtype,
    )
    stream = _row_streams(normals)
    if normals.device.type != "cpu":
        return _assemble_levels([_grow_trees(binned, stream, rows, 0, **kw)])
    if normals.dtype == torch.float32:  # the compiled loops' tables, shared by the trees
        kw["rows_table"] = _rows_table(binned, stream)

    def grow_one(tree: int) -> list[_Level]:
        return _grow_trees(binned, stream, rows[tree : tree + 1], tree, **kw)

    workers = min(n_jobs, n_trees)
    if workers == 1:
        return _assemble_levels([grow_one(tree) for tree in range(n_trees)])
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="sfs_torch.forest") as pool:
        return _assemble_levels(list(pool.map(grow_one, range(n_trees))))


def _grow_trees(
    binned: Tensor,
    stream: list[Tensor],
    rows: Tensor,
    first_tree: int,
    *,
    max_depth: int,
    min_samples_leaf: int,
    max_features: int,
    n_bins: int,
    seed: int,
    index_dtype: torch.dtype,
    rows_table: Optional[tuple[Tensor, Tensor]] = None,
) -> list[_Level]:
    """Grow a group of trees (trees ``first_tree, first_tree + 1, ...``) level by level.

    ``stream`` holds the rows' statistics (:func:`_row_streams`), ``rows`` (T, n_in)
    each tree's in-bag rows.

    State per level: the *active* nodes (those that may split; ``cand`` indexes them in
    the level's node list, ``key`` holds their draw keys) and one (tree, row) *pair* per
    in-bag row of an active node, held as its row ``offset`` and active-node index
    ``pnode``, grouped by node with rows ascending inside. Pairs of nodes that cannot
    split are dropped when routed, so no later pass reads them. On a GPU there are two
    host syncs per level, the number of candidate thresholds and the next level's sizes.
    With ``rows_table`` (:func:`_rows_table`; float32 on the CPU) the compiled search and
    routing run instead of the torch ops, on the pairs' own copies of their bins and
    statistics (:class:`_PairBuffers`), finding each node's pairs from ``node_pairs``;
    no ``pnode`` is kept.
    """
    device = rows.device
    n_trees, n_in = rows.shape
    flat_bins = binned.view(-1)
    offset = rows.reshape(-1).to(index_dtype)  # rows, ascending within each tree
    count, vsum = _root_statistics(stream, offset, n_trees, n_in)
    n_cand = n_trees if n_in >= 2 * min_samples_leaf else 0
    cand = torch.arange(n_cand, device=device)
    key = cand + first_tree  # a root's key is its tree's index
    # the compiled loops (rows_table given: float32 on the CPU) find each node's pairs from
    # node_pairs and read the pairs' own bins and statistics; the torch ops need pnode
    compiled = rows_table is not None
    if compiled:
        pairs = _PairBuffers(*rows_table, offset)
        node_pairs = torch.full((n_cand,), n_in, dtype=torch.int64)  # pairs per active node
    else:
        pnode = torch.arange(n_trees, dtype=index_dtype, device=device).repeat_interleave(n_in)
        work = _Workspace(offset.numel(), index_dtype, stream[0].dtype, device)

    levels = []
    for level in range(max_depth + 1):
        n_level = count.numel()
        feature = torch.zeros(n_level, dtype=torch.long, device=device)
        split_bin = torch.zeros(n_level, dtype=torch.long, device=device)
        is_split = torch.zeros(n_level, dtype=torch.bool, device=device)
        levels.append(_Level(feature, split_bin, is_split, count, vsum))
        if level == max_depth or n_cand == 0:
            break
        feats = _draw_features(seed, key, binned.shape[0], max_features)  # (n_cand, m)
        if compiled:
            best, slot, b, left, total = _search_splits_compiled(
                pairs, feats, node_pairs, n_bins=n_bins, min_samples_leaf=min_samples_leaf,
            )
        else:
            best, slot, b, left, total = _search_splits(
                flat_bins, feats, offset, pnode, stream, n_rows=binned.shape[1], n_bins=n_bins,
                min_samples_leaf=min_samples_leaf, work=work,
            )
        split, best_feature, b = _choose_splits(
            best, slot, b, feats, count.index_select(0, cand), vsum.index_select(0, cand)
        )
        feature[cand] = best_feature
        split_bin[cand] = b
        is_split[cand] = split
        child_stats = torch.stack([left, total - left], dim=1)  # (n_cand, 2, 4)
        active = (split[:, None] & (child_stats[..., 0] >= 2 * min_samples_leaf)).view(-1)  # (2 n_cand,)
        if level + 1 < max_depth and compiled:
            n_split, n_cand, next_active, node_pairs = _route_compiled(pairs, node_pairs, best_feature, b, split, active)
        elif level + 1 < max_depth:
            n_pairs = offset.numel()
            where = (best_feature * binned.shape[1]).to(index_dtype).index_select(0, pnode).add_(offset)
            n_split, n_cand, offset, pnode, next_active = _route(
                flat_bins, where, offset, pnode, b, split, active, work.code[:n_pairs], work.pair_index[:n_pairs],
            )
        else:  # the children are leaves: no pair needs routing
            n_split, n_cand, next_active = int(split.sum()), 0, cand[:0]
        if n_split == 0:
            break
        count, vsum = _child_statistics(child_stats, split, n_split)
        # active children, as indices into the next level's node list (2 rank + side)
        parent, side = next_active // 2, next_active % 2
        cand = 2 * (split.cumsum(0) - 1).index_select(0, parent) + side
        key = _child_keys(key.index_select(0, parent), side)
        logger.debug("trees %d+%d, level %d: %d of %d nodes split, %d pairs",
                     first_tree, n_trees, level, n_split, n_level, pairs.count if compiled else offset.numel())
    return levels


def _row_streams(normals: Tensor) -> list[Tensor]:
    # Per-row statistics (1, n_x, n_y, n_z) as two complex streams: one scatter-add then
    # accumulates two statistics.
    return [torch.complex(torch.ones_like(normals[:, 0]), normals[:, 0]), torch.complex(normals[:, 1], normals[:, 2])]


def _root_statistics(stream: list[Tensor], offset: Tensor, n_trees: int, n_in: int) -> tuple[Tensor, Tensor]:
    """In-bag count ``(T,)`` and normal sum ``(T, 3)`` of each tree's root."""
    pair_stats = torch.stack([s.index_select(0, offset) for s in stream], 1)
    vsum = torch.view_as_real(pair_stats.view(n_trees, n_in, 2).sum(1)).reshape(n_trees, 4)[:, 1:]
    count = torch.full((n_trees,), float(n_in), dtype=vsum.dtype, device=vsum.device)
    return count, vsum


def _search_splits(
    flat_bins: Tensor,
    feats: Tensor,
    offset: Tensor,
    pnode: Tensor,
    stream: list[Tensor],
    *,
    n_rows: int,
    n_bins: int,
    min_samples_leaf: int,
    work: _Workspace,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The best threshold of every active node of a level, over its drawn features ``feats`` (n, m), in torch ops.

    The path of other devices and of float64 on the CPU; float32 on the CPU runs
    :func:`_search_splits_compiled`, which returns the same. ``offset`` and ``pnode``
    (active-node index) describe the level's pairs, grouped by node. Returns per node the
    best score (``inf`` without any valid threshold), its feature slot and bin, and the
    left child's and the node's statistics ``(count, n_x, n_y, n_z)`` :math:`(n, 4)`.
    """
    n_nodes, max_features = feats.shape
    slot_start = (feats * n_rows).T.to(offset.dtype).contiguous()  # where each slot's feature starts in flat_bins
    sources = [s.index_select(0, offset) for s in stream]
    n_pairs = offset.numel()
    where, code, cell = work.where[:n_pairs], work.code[:n_pairs], work.cell[:n_pairs]
    # Histogram, laid out (stream, slot, node, bin): per slot, every pair adds its two
    # complex statistics to its node's bin of the slot's feature. Pairs are grouped by
    # node, so the writes of one slot sweep its block once, in order.
    cells = n_nodes * n_bins
    if work.hist.numel() < 2 * max_features * cells:
        work.hist = torch.empty(2 * max_features * cells, dtype=work.hist.dtype, device=work.hist.device)
    hist = work.hist[: 2 * max_features * cells].view(2, max_features, cells).zero_()
    base = pnode.to(torch.int64, copy=True).mul_(n_bins)
    for j in range(max_features):
        torch.index_select(slot_start[j], 0, pnode, out=where).add_(offset)
        cell.copy_(torch.index_select(flat_bins, 0, where, out=code)).add_(base)
        hist[0, j].scatter_add_(0, cell, sources[0])
        hist[1, j].scatter_add_(0, cell, sources[1])
    del base, sources

    # Score only thresholds that change the partition (the bin is not empty) and
    # leave min_samples_leaf rows on both sides: deep nodes hold fewer rows than
    # bins, so this skips most candidates there.
    hist = hist.view(2, max_features, n_nodes, n_bins)
    ok = torch.view_as_real(hist[0])[..., :-1, 0] > 0
    cum = hist.cumsum_(dim=3)
    cum_count = torch.view_as_real(cum[0])[..., 0]
    n_left = cum_count[..., :-1]
    ok &= n_left >= min_samples_leaf
    ok &= n_left <= cum_count[..., -1:] - min_samples_leaf
    cand_slot, owner, cand_bin = ok.nonzero().unbind(1)  # candidates (slot, node, bin); host sync
    del ok, n_left, cum_count
    cum0, cum1 = cum[0].view(-1), cum[1].view(-1)
    at = (cand_slot * n_nodes + owner).mul_(n_bins)  # cell of bin 0 of (slot, node)
    total = [cum0.index_select(0, at + n_bins - 1), cum1.index_select(0, at + n_bins - 1)]
    at += cand_bin
    left = [cum0.index_select(0, at), cum1.index_select(0, at)]
    score = _weighted_entropy(*_stats(*left), max_kappa=MAX_KAPPA)
    score += _weighted_entropy(*_stats(total[0].sub_(left[0]), total[1].sub_(left[1])), max_kappa=MAX_KAPPA)
    del left, total, cand_slot, cand_bin
    # argmin per node, ties to the lowest (slot, bin) as a dense argmin would: for a
    # fixed node, the cell grows with (slot, bin)
    best = torch.full((n_nodes,), math.inf, dtype=score.dtype, device=score.device)
    best.scatter_reduce_(0, owner, score, "amin")
    winner = score == best.index_select(0, owner)
    none = max_features * cells  # past every cell
    arg = torch.full((n_nodes,), none, dtype=torch.long, device=best.device)
    arg.scatter_reduce_(0, owner, torch.where(winner, at, none), "amin")
    arg.masked_fill_(arg == none, 0)  # nodes without a valid threshold
    slot = torch.div(arg, cells, rounding_mode="floor")
    b = torch.remainder(arg, n_bins)
    left_stats = torch.stack(_stats(cum0.index_select(0, arg), cum1.index_select(0, arg)), dim=1)
    at = arg - b + (n_bins - 1)
    total_stats = torch.stack(_stats(cum0.index_select(0, at), cum1.index_select(0, at)), dim=1)
    return best, slot, b, left_stats, total_stats


def _rows_table(binned: Tensor, stream: list[Tensor]) -> tuple[Tensor, Tensor]:
    """Each row's bins ``(N, F)`` uint8 and statistics ``(N, 4)`` float32 (1, n_x, n_y, n_z), row-major."""
    return binned.T.contiguous(), torch.cat([torch.view_as_real(s) for s in stream], 1)


class _PairBuffers:
    """The bins and statistics of a tree group's (tree, row) pairs, in pair order, for the
    compiled loops: gathered once from the rows' tables, then moved with the pairs by
    each routing into a second buffer (the two swap roles), so that every read of the
    loops is sequential. ``count`` pairs are current."""

    def __init__(self, row_bins: Tensor, row_stats: Tensor, rows: Tensor):
        self.bins = row_bins.index_select(0, rows)
        self.stats = row_stats.index_select(0, rows)
        self.spare_bins, self.spare_stats = torch.empty_like(self.bins), torch.empty_like(self.stats)
        self.count = rows.numel()

    def swap(self, count: int) -> None:
        self.bins, self.spare_bins = self.spare_bins, self.bins
        self.stats, self.spare_stats = self.spare_stats, self.stats
        self.count = count


def _node_starts(node_pairs: Tensor) -> Tensor:
    # where each node's pairs start, and the end: (n + 1,)
    starts = torch.zeros(node_pairs.numel() + 1, dtype=torch.int64)
    torch.cumsum(node_pairs, 0, out=starts[1:])
    return starts


def _search_splits_compiled(
    pairs: _PairBuffers,
    feats: Tensor,
    node_pairs: Tensor,
    *,
    n_bins: int,
    min_samples_leaf: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`_search_splits` on the CPU, by the compiled loop of ``sfs_torch._forest_kernel``.

    ``node_pairs`` (n,) counts each active node's pairs (they are grouped by node). The
    loop releases the GIL. Its per-bin float32 sums and float64 prefix sums run as the
    torch ops' do (the node's total is summed over its pairs rather than its bins), and
    its entropies may differ from theirs in the last bit (another ``log``), so a split
    whose two best thresholds score within that rounding may go the other way.
    """
    from ._forest_kernel import best_splits  # Numba loads at the first CPU fit, not at import

    n_cand = feats.shape[0]
    best = torch.empty(n_cand)
    slot = torch.empty(n_cand, dtype=torch.long)
    b = torch.empty(n_cand, dtype=torch.long)
    left = torch.empty(n_cand, 4)
    total = torch.empty(n_cand, 4)
    best_splits(
        pairs.bins[: pairs.count].numpy(), pairs.stats[: pairs.count].numpy(), feats.contiguous().numpy(),
        _node_starts(node_pairs).numpy(), n_bins, min_samples_leaf, np.float32(MAX_KAPPA), np.float32(_MIN_KAPPA),
        best.numpy(), slot.numpy(), b.numpy(), left.numpy(), total.numpy(),
    )
    return best, slot, b, left, total


def _choose_splits(
    best: Tensor, slot: Tensor, b: Tensor, feats: Tensor, node_count: Tensor, node_sum: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Which active nodes split: those whose best score is below their own ``n H(kappa)``.

    Returns the split mask and, per node, the split feature and bin (0 where not split).
    """
    parent = _weighted_entropy(node_count, *node_sum.unbind(1), max_kappa=MAX_KAPPA)
    # A split must lower the entropy by more than float rounding of the sums.
    tol = 1e-5 * (node_count + parent.abs())
    split = torch.isfinite(best) & (best < parent - tol)
    slot, b = torch.where(split, slot, 0), torch.where(split, b, 0)
    best_feature = torch.where(split, feats.gather(1, slot[:, None]).squeeze(1), 0)
    return split, best_feature, b


def _child_statistics(child_stats: Tensor, split: Tensor, n_split: int) -> tuple[Tensor, Tensor]:
    """Count ``(2 S,)`` and normal sum ``(2 S, 3)`` of the children of the S split nodes, left before right."""
    child_stats = child_stats.index_select(0, _compact(split, n_split)).reshape(-1, 4)
    return child_stats[:, 0], child_stats[:, 1:].contiguous()


def _assemble_levels(groups: list[list[_Level]]) -> dict:
    """One flat level-ordered node table from the levels of groups of trees (in tree order).

    Level ``l`` of the table holds level ``l`` of every group, group after group; a
    split node's left child is at the next level's start plus twice its rank among the
    level's split nodes (children keep their parents' order), a leaf points to itself.
    """
    depth = max(len(levels) for levels in groups) - 1
    parts: dict[str, list[Tensor]] = {name: [] for name in ("feature", "bin", "child", "count", "sum")}
    start = 0  # index of the level's first node in the table
    for level in range(depth + 1):
        nodes = [levels[level] for levels in groups if len(levels) > level]
        split = torch.cat([n.split for n in nodes])
        n_level = split.numel()
        own = torch.arange(start, start + n_level, device=split.device)
        parts["child"].append(torch.where(split, (start + n_level) + 2 * (split.cumsum(0) - 1), own))
        for name in ("feature", "bin", "count", "sum"):
            parts[name].append(torch.cat([getattr(n, name) for n in nodes]))
        start += n_level
    return {**{name: torch.cat(value) for name, value in parts.items()}, "depth": depth}


def _route(
    flat_bins: Tensor,
    where: Tensor,
    offset: Tensor,
    pnode: Tensor,
    split_bin: Tensor,
    split: Tensor,
    active: Tensor,
    code: Tensor,
    pair_index: Tensor,
) -> tuple[int, int, Tensor, Tensor, Tensor]:
    """Send every pair to its child (``bin > split_bin`` goes right); keep those of active children.

    ``where`` locates each pair's bin of its node's split feature in ``flat_bins``.
    Returns the numbers of split nodes and of active children, the kept pairs'
    ``offset`` and ``pnode`` (grouped by child, rows still ascending inside), and the
    active children as ``2 node + side``. One host sync.
    """
    device = offset.device
    n_pairs = offset.numel()
    go_right = torch.index_select(flat_bins, 0, where, out=code) > split_bin.to(torch.uint8).index_select(0, pnode)
    pair_child = torch.add(go_right, pnode, alpha=2)  # 2 node + side
    per_child = torch.zeros(active.numel(), dtype=torch.int64, device=device)
    per_child.index_add_(0, pair_child, torch.ones(1, dtype=torch.int64, device=device).expand(n_pairs))
    kept = per_child * active
    n_split, n_active, n_kept = torch.stack([split.sum(), active.sum(), kept.sum()]).tolist()
    # Stable partition of the kept pairs by child, as a counting sort: a pair's new
    # position is its child's start plus the number of same-side pairs before it in
    # its node; `same_side` counts those from the array start, `earlier` those in
    # earlier nodes. Pairs of unsplit nodes and of leaves go to a trash slot at the end.
    right_before = go_right.cumsum(0)
    same_side = torch.where(go_right, right_before - 1, pair_index - right_before)
    earlier = (per_child.view(-1, 2).cumsum(0) - per_child.view(-1, 2)).view(-1)
    start = kept.cumsum(0) - kept
    shift = torch.where(active, start - earlier, 2 * n_pairs + n_kept)
    pos = shift.index_select(0, pair_child).add_(same_side).clamp_(max=n_kept)
    offset = torch.empty(n_kept + 1, dtype=offset.dtype, device=device).scatter_(0, pos, offset)[:n_kept]
    next_active = _compact(active, n_active)
    counts = kept.index_select(0, next_active)
    pnode = torch.repeat_interleave(torch.arange(n_active, dtype=pnode.dtype, device=device), counts, output_size=n_kept)
    return n_split, n_active, offset, pnode, next_active


def _route_compiled(
    pairs: _PairBuffers,
    node_pairs: Tensor,
    split_feature: Tensor,
    split_bin: Tensor,
    split: Tensor,
    active: Tensor,
) -> tuple[int, int, Tensor, Tensor]:
    """:func:`_route` on the CPU, by the compiled loop of ``sfs_torch._forest_kernel``.

    The same kept pairs in the same order, found by node from ``node_pairs`` (their pair
    counts); their bins and statistics move into ``pairs``' other buffer. Returns the
    numbers of split nodes and of active children, the active children as ``2 node +
    side`` and their pair counts.
    """
    from ._forest_kernel import route

    counts = torch.empty(active.numel(), dtype=torch.int64)
    n_kept, n_active = route(
        pairs.bins[: pairs.count].numpy(), pairs.stats[: pairs.count].numpy(), _node_starts(node_pairs).numpy(),
        split_feature.numpy(), split_bin.to(torch.uint8).numpy(), active.numpy(), pairs.spare_bins.numpy(),
        pairs.spare_stats.numpy(), counts.numpy(),
    )
    pairs.swap(n_kept)
    return int(split.sum()), n_active, _compact(active, n_active), counts[:n_active]
