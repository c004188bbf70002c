r"""Regression forest with von Mises-Fisher leaves (Richter & Roth 2015, Sec. 5).

The forest is retrained for every test lighting, so training speed dominates the
method's cost. All trees grow at once, one tree level per Python iteration, with
histogram split search:

1. every feature is cut once into ``n_bins`` quantile bins (the edges are data values,
   so a bin threshold is also an exact threshold on the raw feature);
2. each tree draws a random ``sample_fraction`` of the rows (without replacement); the
   (tree, row) pairs of the nodes still growing are kept grouped by node, so the
   histogram writes of one node stay in a small, cache-resident block;
3. per level, for every node of every tree and each of its ``max_features`` random
   features, ``index_add_`` accumulates per bin the count and the vector sum of the
   normals (packed as two complex numbers, ``count + i n_x`` and ``n_y + i n_z``, which
   halves the scatter work); a cumulative sum over bins gives both children of every
   threshold, and all thresholds that change the partition and leave
   ``min_samples_leaf`` rows on each side are scored at once by the children's
   count-weighted vMF entropy ``n_L H(kappa_L) + n_R H(kappa_R)``;
4. a node splits at its best threshold when that lowers the entropy below the
   parent's ``n H(kappa)`` and the depth is below ``max_depth``; otherwise it is a leaf.

Nodes of all trees live in one flat table in level order; a leaf points to itself
with threshold ``+inf``, so prediction is ``depth`` rounds of 1-D gathers.
See ``docs/forest.md`` for the choices and measurements.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import torch
from torch import Tensor

from ._checks import check_finite, check_shape

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
    check_shape(vmf.mean, "vmf.mean", " ".join(["D"] * (vmf.mean.ndim - 1) + ["3"]))
    if vmf.kappa.shape != vmf.mean.shape[:-1]:
        raise ValueError(f"vmf.kappa must have shape {tuple(vmf.mean.shape[:-1])}, got {tuple(vmf.kappa.shape)}")
    if not isinstance(n_samples, int) or n_samples < 1:
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
    # n * H(kappa(R)) for node statistics of any shape; n = 0 gives 0.
    r2 = sx * sx
    r2.addcmul_(sy, sy).addcmul_(sz, sz)
    r2.div_(n.clamp_min(1.0).square())
    return vmf_entropy(_kappa_from_r2(r2, max_kappa)).mul_(n)


@dataclass
class ForestConfig:
    """Hyper-parameters of :class:`VMFForest` (defaults chosen in ``docs/forest.md``)."""

    _target_: str = "sfs_torch.forest.VMFForest"
    n_trees: int = 8
    max_depth: int = 14
    min_samples_leaf: int = 10
    max_features: Union[int, float] = 8
    n_bins: int = 64
    sample_fraction: float = 0.9
    seed: int = 0


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
    ) -> None:
        self.n_trees = n_trees
        self.max_depth = max_depth
        self.min_samples_leaf = min_samples_leaf
        self.max_features = max_features
        self.n_bins = n_bins
        self.sample_fraction = sample_fraction
        self.seed = seed
        self.device = device

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
        }

    def _validate_params(self, n_features: int) -> int:
        def positive_int(name: str, minimum: int) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")

        positive_int("n_trees", 1)
        positive_int("max_depth", 0)
        positive_int("min_samples_leaf", 1)
        positive_int("seed", 0)
        if isinstance(self.n_bins, bool) or not isinstance(self.n_bins, int) or not 2 <= self.n_bins <= 256:
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
        if bool(((normals.norm(dim=1) - 1.0).abs() > 1e-3).any()):
            raise ValueError("normals must be unit vectors (|n| = 1 within 1e-3)")
        m = self._validate_params(X.shape[1])
        device = torch.device(self.device) if self.device is not None else X.device
        X = X.to(device)
        normals = normals.to(device=device, dtype=X.dtype)
        generator = torch.Generator().manual_seed(self.seed)

        edges = _quantile_edges(X, self.n_bins, generator)
        binned = _bin(X, edges)
        tree = _grow(
            binned,
            normals,
            n_trees=self.n_trees,
            max_depth=self.max_depth,
            min_samples_leaf=self.min_samples_leaf,
            max_features=m,
            n_bins=self.n_bins,
            sample_fraction=self.sample_fraction,
            generator=generator,
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
        X, n = X[rows], max_rows
    ranks = (torch.arange(1, n_bins, device=X.device) * n) // n_bins
    return X.T.contiguous().sort(dim=1).values[:, ranks]  # (F, n_bins - 1)


def _bin(X: Tensor, edges: Tensor) -> Tensor:
    # bin = number of edges strictly below x, as (F, N) uint8 (feature-major).
    # Counting edge by edge is about twice as fast as searchsorted on CPU.
    columns = X.T.contiguous()
    binned = torch.zeros(columns.shape, dtype=torch.uint8, device=X.device)
    for k in range(edges.shape[1]):
        binned.add_(columns > edges[:, k : k + 1])
    return binned


def _stats(c: Tensor) -> list[Tensor]:
    # complex (2, ...) holding (count + i n_x, n_y + i n_z) -> strided real views
    # [count, n_x, n_y, n_z], each (...), without copying.
    v = torch.view_as_real(c)
    return [v[0, ..., 0], v[0, ..., 1], v[1, ..., 0], v[1, ..., 1]]


def _grow(
    binned: Tensor,
    normals: Tensor,
    *,
    n_trees: int,
    max_depth: int,
    min_samples_leaf: int,
    max_features: int,
    n_bins: int,
    sample_fraction: float,
    generator: torch.Generator,
) -> dict:
    """Grow all trees level by level on binned features.

    Returns a dict of flat node tensors in level order: ``feature`` (M,), ``bin``
    (M,) (rows with bin > bin go right), ``child`` (M,) (left child, self for leaves),
    ``count`` (M,), ``sum`` (M, 3), and ``depth`` (int, levels grown).
    """
    device, dtype = normals.device, normals.dtype
    n_features, n_rows = binned.shape
    n_in = max(1, round(sample_fraction * n_rows))
    # Random draws are made on the CPU generator so that a seed gives the same forest
    # on every device.
    in_bag = torch.zeros(n_trees, n_rows, dtype=torch.bool)
    for tree in range(n_trees):
        in_bag[tree, torch.randperm(n_rows, generator=generator)[:n_in]] = True
    rows = in_bag.to(device).nonzero()[:, 1]  # ascending within each tree
    # Per (tree, row) pair: its row, its statistics and its node. Pairs stay grouped
    # by node (rows ascending inside), so histogram writes and the reads of the
    # feature-major bins stay local. The four statistics (1, n_x, n_y, n_z) travel as
    # two complex numbers, which halves the scatter-adds.
    offset = rows.to(torch.int32)
    pair_stats = torch.view_as_complex(
        torch.cat([torch.ones_like(normals[:, :1]), normals], dim=1)[rows].view(-1, 2, 2).contiguous()
    )
    pnode = torch.arange(n_trees, device=device).repeat_interleave(n_in)
    flat_bins = binned.reshape(-1)

    count = torch.full((n_trees,), float(n_in), dtype=dtype, device=device)
    vsum = torch.view_as_real(pair_stats.view(n_trees, n_in, 2).sum(1)).reshape(n_trees, 4)[:, 1:]
    features, bins, childs, counts, sums = [], [], [], [], []
    next_id, depth = n_trees, 0
    n_cand = n_bins - 1

    for level in range(max_depth + 1):
        n_level = count.numel()
        feature = torch.zeros(n_level, dtype=torch.long, device=device)
        split_bin = torch.zeros(n_level, dtype=torch.long, device=device)
        child = torch.arange(next_id - n_level, next_id, device=device)  # leaves point to themselves
        counts.append(count)
        sums.append(vsum)
        features.append(feature)
        bins.append(split_bin)
        childs.append(child)
        splittable = count >= 2 * min_samples_leaf
        if level == max_depth or not bool(splittable.any()):
            break
        # Drop the pairs of nodes too small to split; re-number the rest compactly
        # (monotone, so pairs stay grouped by node).
        if not bool(splittable.all()):
            keep = splittable.index_select(0, pnode).nonzero().squeeze(1)
            offset, pair_stats = offset.index_select(0, keep), pair_stats.index_select(0, keep)
            pnode = (splittable.cumsum(0) - 1).index_select(0, pnode.index_select(0, keep))
        cand = splittable.nonzero().squeeze(1)
        n_nodes = cand.numel()
        feats = torch.rand(n_nodes, n_features, generator=generator).argsort(dim=1)[:, :max_features]
        feats = feats.to(device=device, dtype=torch.int32)
        feats_start = (feats * n_rows).T.contiguous()  # where each slot's feature starts in flat_bins

        # One slot (the j-th random feature of every node) at a time keeps the
        # per-pair temporaries small enough to stay in cache.
        node_base = (pnode * (max_features * n_bins)).to(torch.int32)
        sources = pair_stats.T.contiguous()
        hist = torch.zeros(2, n_nodes * max_features * n_bins, dtype=pair_stats.dtype, device=device)
        for j in range(max_features):
            code = flat_bins.index_select(0, feats_start[j].index_select(0, pnode).add_(offset))
            index = (node_base + code).add_(j * n_bins)
            hist[0].index_add_(0, index, sources[0])
            hist[1].index_add_(0, index, sources[1])
        # Score only thresholds that change the partition (the bin is not empty) and
        # leave min_samples_leaf rows on both sides: deep nodes hold fewer rows than
        # bins, so this skips most candidates there.
        nonempty = torch.view_as_real(hist)[0, :, 0].view(n_nodes, max_features, n_bins)[..., :-1] > 0
        cum = hist.view(2, n_nodes, max_features, n_bins).cumsum_(dim=3)
        cum_count = torch.view_as_real(cum)[0, ..., 0]
        n_left = cum_count[..., :-1]
        ok = nonempty & (n_left >= min_samples_leaf) & (n_left <= cum_count[..., -1:] - min_samples_leaf)
        flat_index = ok.view(-1).nonzero().squeeze(1)  # into (nodes, slots, bins - 1)
        row = flat_index // n_cand  # (node, slot)
        flat_cum = cum.view(2, -1)
        left = flat_cum.index_select(1, flat_index + row)
        right = flat_cum.index_select(1, row * n_bins + n_cand) - left
        score = _weighted_entropy(*_stats(left), max_kappa=MAX_KAPPA).add_(_weighted_entropy(*_stats(right), max_kappa=MAX_KAPPA))
        # argmin per node, ties to the lowest candidate index (as a dense argmin would)
        owner = row // max_features
        best = torch.full((n_nodes,), math.inf, dtype=dtype, device=device).scatter_reduce_(0, owner, score, "amin")
        winner = score == best.index_select(0, owner)
        arg = torch.full((n_nodes,), ok.numel(), dtype=torch.long, device=device)
        arg.scatter_reduce_(0, owner[winner], flat_index[winner], "amin")
        node_count, node_sum = count[cand], vsum[cand]
        parent = _weighted_entropy(node_count, *node_sum.unbind(1), max_kappa=MAX_KAPPA)
        # A split must lower the entropy by more than float rounding of the sums.
        tol = 1e-5 * (node_count + parent.abs())
        split = torch.isfinite(best) & (best < parent - tol)
        n_split = int(split.sum())
        if n_split == 0:
            break

        arg = torch.where(split, arg, torch.zeros_like(arg))
        slot, b = (arg // n_cand) % max_features, arg % n_cand
        left_stats = torch.stack(_stats(flat_cum.index_select(1, arg + arg // n_cand)), dim=1)  # (n_nodes, 4)
        total_stats = torch.stack(_stats(flat_cum.index_select(1, (arg // n_cand) * n_bins + n_cand)), dim=1)
        split_nodes = cand[split]
        rank = split.long().cumsum(0) - 1
        best_feature = feats.gather(1, slot[:, None]).squeeze(1)
        feature[split_nodes] = best_feature[split].long()
        split_bin[split_nodes] = b[split]
        child[split_nodes] = next_id + 2 * rank[split]
        child_stats = torch.stack([left_stats[split], (total_stats - left_stats)[split]], dim=1).reshape(-1, 4)
        count, vsum = child_stats[:, 0], child_stats[:, 1:].contiguous()

        # Route pairs to the children, keeping them grouped by child node.
        keep = split.index_select(0, pnode)
        if not bool(keep.all()):
            keep = keep.nonzero().squeeze(1)
            offset, pair_stats, pnode = offset.index_select(0, keep), pair_stats.index_select(0, keep), pnode.index_select(0, keep)
        code = flat_bins.index_select(0, (best_feature * n_rows).index_select(0, pnode).add_(offset))
        go_right = code > b.index_select(0, pnode)
        new = 2 * rank.index_select(0, pnode) + go_right
        per_child = torch.bincount(new, minlength=2 * n_split)
        start = per_child.cumsum(0) - per_child
        base = per_child.view(-1, 2).cumsum(0).view(-1) - per_child  # same-side pairs in earlier parents
        side = go_right.long()
        before = torch.where(go_right, side.cumsum(0) - side, (1 - side).cumsum(0) - (1 - side))
        pos = start.index_select(0, new) + before - base.index_select(0, new)
        offset = torch.empty_like(offset).index_copy_(0, pos, offset)
        pair_stats = torch.empty_like(pair_stats).index_copy_(0, pos, pair_stats)
        pnode = torch.empty_like(new).index_copy_(0, pos, new)
        next_id += 2 * n_split
        depth = level + 1
        logger.debug("level %d: %d of %d nodes split, %d pairs", level, n_split, n_level, pnode.numel())

    return {
        "feature": torch.cat(features),
        "bin": torch.cat(bins),
        "child": torch.cat(childs),
        "count": torch.cat(counts),
        "sum": torch.cat(sums),
        "depth": depth,
    }
