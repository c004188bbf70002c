"""The forest's split search and routing on the CPU, compiled by Numba (``sfs_torch.forest``).

``best_splits`` runs one loop per active node of a tree level: it accumulates the node's
histogram for each of its drawn features (count and normal sum per bin; each pair is
read once for all features, from the pair's own copy of its bins and statistics, which
``route`` moves along with the pairs, so that every read is sequential), then sweeps
each histogram once, scoring the thresholds that change the partition and leave
``min_leaf`` rows on both sides by ``n_L H(kappa_L) + n_R H(kappa_R)``. It computes what
``forest._search_splits`` computes with torch ops (which serve other devices), with the
histogram of one node in L1 cache and no pass over empty bins. Both functions release
the GIL, so the trees grown in threads run on all cores.

Imported by ``sfs_torch.forest`` at the first CPU fit (compiling takes a few seconds,
cached on disk by Numba afterwards), so that ``import sfs_torch`` does not load Numba.
"""
from __future__ import annotations

import math

import numpy as np
from numba import float32, float64, njit

_LOG_2PI_E = np.float32(math.log(2.0 * math.pi) + 1.0)
# Above this kappa, expm1(-2 kappa) is -1 in float32, and the entropy is log(1 / kappa) + log(2 pi e)
_LARGE_KAPPA = np.float32(9.0)


@njit(nogil=True, cache=True, inline="always")
def _weighted_entropy(n, sx, sy, sz, max_kappa, min_kappa):  # pragma: no cover - compiled
    # n H(kappa(R)) in float32, as forest._weighted_entropy
    nn = max(n, float32(1.0))
    r2 = (sx * sx + sy * sy + sz * sz) / (nn * nn)
    r2 = min(max(r2, float32(0.0)), float32(1.0))
    if r2 < float32(1.0):
        kappa = min(max(math.sqrt(r2) * (float32(3.0) - r2) / (float32(1.0) - r2), min_kappa), max_kappa)
    else:
        kappa = max_kappa
    if kappa > _LARGE_KAPPA:
        h = math.log(float32(1.0) / kappa)
    else:
        m = math.expm1(float32(-2.0) * kappa)
        h = math.log(-m / kappa) + float32(2.0) * kappa * (float32(1.0) + m) / m
    return (h + _LOG_2PI_E) * n


@njit(nogil=True, cache=True)
def best_splits(pair_bins, pair_stats, feats, starts, n_bins, min_leaf, max_kappa, min_kappa,
                best, slot, bin_, left, total):  # pragma: no cover - compiled
    """Best threshold of every active node of a level, written into the output arrays.

    ``pair_bins`` (P, F) uint8 and ``pair_stats`` (P, 4) float32 (1, n_x, n_y, n_z) are
    the (tree, row) pairs' bins and statistics in pair order: node ``k``'s pairs are rows
    ``starts[k]`` to ``starts[k + 1]``; ``feats`` (n, m) each node's features. Outputs
    per node: ``best`` score (``inf`` without a valid threshold), its ``slot`` and
    ``bin_`` (ties to the lowest slot, then bin), the left child's and the node's
    statistics ``left``, ``total`` (n, 4) as (count, n_x, n_y, n_z) (``left`` is 0
    without a threshold).
    """
    m = feats.shape[1]
    hist = np.zeros((m, n_bins, 4), np.float32)  # zero between nodes: each node clears the bins it used
    low = np.zeros(m, np.int64)
    high = np.zeros(m, np.int64)
    dmin = float64(min_leaf)
    for k in range(feats.shape[0]):
        for j in range(m):
            low[j], high[j] = n_bins, -1
        a0 = a1 = a2 = a3 = 0.0  # the node's statistics, in float64 as torch's cumsum
        for p in range(starts[k], starts[k + 1]):
            v0, v1, v2, v3 = pair_stats[p, 0], pair_stats[p, 1], pair_stats[p, 2], pair_stats[p, 3]
            a0 += v0
            a1 += v1
            a2 += v2
            a3 += v3
            for j in range(m):
                b = pair_bins[p, feats[k, j]]
                hist[j, b, 0] += v0
                hist[j, b, 1] += v1
                hist[j, b, 2] += v2
                hist[j, b, 3] += v3
                low[j] = min(low[j], b)
                high[j] = max(high[j], b)
        n0, n1, n2, n3 = float32(a0), float32(a1), float32(a2), float32(a3)
        best_k = np.float32(np.inf)
        best_slot = best_bin = 0
        l0 = l1 = l2 = l3 = float32(0.0)
        for j in range(m):
            # prefix sums in float64, each rounded to float32, as torch's CPU cumsum does;
            # thresholds at or past the last non-empty bin leave the right side empty
            c0 = c1 = c2 = c3 = 0.0
            for b in range(low[j], min(high[j], n_bins - 1)):
                count = hist[j, b, 0]
                c0 += count
                c1 += hist[j, b, 1]
                c2 += hist[j, b, 2]
                c3 += hist[j, b, 3]
                # an empty bin repeats the partition of the one before it (counts are exact)
                if count > 0 and c0 >= dmin and c0 <= a0 - dmin:
                    n_left, x1, x2, x3 = float32(c0), float32(c1), float32(c2), float32(c3)
                    score = (_weighted_entropy(n_left, x1, x2, x3, max_kappa, min_kappa)
                             + _weighted_entropy(n0 - n_left, n1 - x1, n2 - x2, n3 - x3, max_kappa, min_kappa))
                    if score < best_k:
                        best_k, best_slot, best_bin = score, j, b
                        l0, l1, l2, l3 = n_left, x1, x2, x3
            hist[j, low[j] : high[j] + 1] = 0.0
        best[k], slot[k], bin_[k] = best_k, best_slot, best_bin
        left[k, 0], left[k, 1], left[k, 2], left[k, 3] = l0, l1, l2, l3
        total[k, 0], total[k, 1], total[k, 2], total[k, 3] = n0, n1, n2, n3


@njit(nogil=True, cache=True)
def route(pair_bins, pair_stats, starts, feature, split_bin, active, out_bins, out_stats, out_counts):  # pragma: no cover
    """Send the pairs of every split node to its children; keep those of active children.

    Node ``k``'s pairs (rows ``starts[k]`` to ``starts[k + 1]`` of ``pair_bins`` and
    ``pair_stats``) go left when their bin of ``feature[k]`` is at most ``split_bin[k]``;
    ``active`` (2 n,) says which children keep theirs. Copies the kept pairs' bins and
    statistics into ``out_bins``, ``out_stats`` grouped by child (left before right,
    pair order kept inside) and each active child's pair count into ``out_counts``;
    returns the numbers of kept pairs and of active children.
    """
    kept = 0
    n_active = 0
    for k in range(feature.shape[0]):
        f = feature[k]
        for side in range(2):
            if not active[2 * k + side]:
                continue
            first = kept
            for p in range(starts[k], starts[k + 1]):
                if (pair_bins[p, f] > split_bin[k]) == side:
                    out_bins[kept, :] = pair_bins[p, :]
                    out_stats[kept, :] = pair_stats[p, :]
                    kept += 1
            out_counts[n_active] = kept - first
            n_active += 1
    return kept, n_active
