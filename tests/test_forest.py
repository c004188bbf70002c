import math
import subprocess
import sys
import threading

import numpy as np
import pytest
import torch
from scipy import stats

from sfs_torch import forest as forest_module
from sfs_torch.forest import (
    MAX_KAPPA,
    VMF,
    ForestConfig,
    NotFittedError,
    VMFForest,
    _assemble_levels,
    _bin,
    _child_keys,
    _compact,
    _draw_features,
    _grow,
    _grow_trees,
    _row_streams,
    _sample_rows,
    _mix32,
    _quantile_edges,
    sample_vmf,
    vmf_entropy,
    vmf_fit,
)


def _a3(kappa):
    """Mean resultant length of a vMF on S^2: coth(kappa) - 1/kappa."""
    return 1.0 / math.tanh(kappa) - 1.0 / kappa


def _angle_deg(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1.0, 1.0)))


def _smooth_data(n, n_features=6, noise=0.0, seed=0, dtype=torch.float32):
    """Normals that are a smooth function of the first three features (the rest is clutter)."""
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, n_features, generator=g, dtype=torch.float64)
    azimuth = 2.0 * math.pi * X[:, 0] + 0.5 * X[:, 2]
    polar = 0.1 + 1.2 * X[:, 1]
    normals = torch.stack(
        [polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos()], dim=1
    )
    if noise:
        normals = normals + noise * torch.randn(n, 3, generator=g, dtype=torch.float64)
    normals = torch.nn.functional.normalize(normals, dim=1)
    return X.to(dtype), normals.to(dtype)


def _random_unit(n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=1)


class TestVMFFit:
    @pytest.mark.parametrize("kappa", [5.0, 10.0, 50.0, 100.0, 500.0])
    def test_recovers_scipy_concentration(self, kappa, device):
        mu = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        samples = stats.vonmises_fisher(mu, kappa).rvs(400_000, random_state=1)
        x = torch.from_numpy(samples).to(device)
        fit = vmf_fit(x.sum(0), torch.tensor(float(len(x)), dtype=x.dtype, device=device))
        # Dhillon-Sra is an approximation: its bias on S^2 is 4.9% at kappa 5, < 1% above 50.
        assert abs(float(fit.kappa) / kappa - 1.0) < 0.05
        assert float(_angle_deg(fit.mean, torch.from_numpy(mu).to(device))) < 0.5

    def test_exact_resultant_length(self, dtype):
        kappa = torch.tensor([5.0, 20.0, 100.0, 500.0], dtype=torch.float64)
        r = torch.tensor([_a3(float(k)) for k in kappa], dtype=torch.float64)
        fit = vmf_fit(torch.stack([torch.zeros_like(r), torch.zeros_like(r), r], 1).to(dtype), torch.ones(4, dtype=dtype))
        torch.testing.assert_close(fit.kappa.double(), kappa, rtol=0.05, atol=0)
        # the approximation's known bias: 3R - R^3 over 1 - R^2 at R = A(5)
        assert float(fit.kappa[0]) == pytest.approx(5.2468, rel=1e-3)

    def test_batched_shapes(self, device, dtype):
        s = torch.randn(2, 5, 3, device=device, dtype=dtype)
        fit = vmf_fit(s, torch.full((2, 5), 4.0, device=device, dtype=dtype))
        assert fit.mean.shape == (2, 5, 3) and fit.kappa.shape == (2, 5)
        assert fit.mean.dtype == dtype and fit.kappa.device.type == device.type
        torch.testing.assert_close(fit.mean.norm(dim=-1), torch.ones(2, 5, device=device, dtype=dtype))

    def test_degenerate(self, dtype):
        sums = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 0.0]], dtype=dtype)
        counts = torch.tensor([1.0, 4.0, 3.0, 0.0], dtype=dtype)
        fit = vmf_fit(sums, counts)
        assert torch.isfinite(fit.kappa).all() and torch.isfinite(fit.mean).all()
        assert fit.kappa.tolist() == [MAX_KAPPA, 0.0, MAX_KAPPA, 0.0]
        assert fit.mean[1].tolist() == [0.0, 0.0, 1.0]
        assert torch.isfinite(vmf_entropy(fit.kappa)).all()

    def test_exception(self):
        with pytest.raises(ValueError, match="normal_sum"):
            vmf_fit(torch.zeros(4, 2), torch.ones(4))
        with pytest.raises(ValueError, match="count"):
            vmf_fit(torch.zeros(4, 3), torch.ones(3))


class TestVMFEntropy:
    @pytest.mark.parametrize("kappa", [1e-3, 0.5, 5.0, 50.0, 5000.0])
    def test_vs_scipy(self, kappa, device, dtype):
        ref = stats.vonmises_fisher([0.0, 0.0, 1.0], kappa).entropy()
        got = vmf_entropy(torch.tensor([kappa], device=device, dtype=dtype))
        assert got.dtype == dtype
        assert float(got) == pytest.approx(ref, abs=1e-5 if dtype == torch.float32 else 1e-10)

    def test_limits(self):
        h = vmf_entropy(torch.tensor([0.0, 1e-30, 1e4, 1e30]))
        assert torch.isfinite(h).all()
        assert float(h[0]) == pytest.approx(math.log(4.0 * math.pi), abs=1e-6)
        assert (h.diff() <= 0).all()  # decreasing in kappa


class TestSampleVMF:
    @pytest.mark.parametrize("kappa", [0.0, 2.0, 20.0, 500.0])
    def test_mean_resultant_length(self, kappa, device, dtype):
        g = torch.Generator(device=device).manual_seed(0)
        mean = torch.nn.functional.normalize(torch.tensor([[0.6, -0.2, 0.7]], device=device, dtype=dtype), dim=-1)
        vmf = VMF(mean=mean, kappa=torch.tensor([kappa], device=device, dtype=dtype))
        x = sample_vmf(vmf, 50_000, generator=g)
        assert x.shape == (1, 50_000, 3) and x.dtype == dtype
        torch.testing.assert_close(x.norm(dim=-1), torch.ones(1, 50_000, device=device, dtype=dtype))
        r = x[0].mean(0)
        expected = 0.0 if kappa == 0 else _a3(kappa)
        assert float(r.norm()) == pytest.approx(expected, abs=0.01)
        if kappa > 0:
            assert float(_angle_deg(r / r.norm(), mean[0])) < 2.0

    def test_matches_scipy_distribution(self):
        kappa = 8.0
        mu = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        ours = sample_vmf(VMF(mu, torch.tensor(kappa, dtype=torch.float64)), 20_000, torch.Generator().manual_seed(3))
        ref = stats.vonmises_fisher(mu.numpy(), kappa).rvs(20_000, random_state=3)
        # cosine to the mean, and the azimuth, must have the same laws
        assert stats.ks_2samp(ours[:, 2].numpy(), ref[:, 2]).pvalue > 1e-3
        az = torch.atan2(ours[:, 1], ours[:, 0]).numpy()
        assert stats.ks_2samp(az, np.arctan2(ref[:, 1], ref[:, 0])).pvalue > 1e-3

    def test_reproducible(self):
        vmf = VMF(torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([3.0]))
        a = sample_vmf(vmf, 10, torch.Generator().manual_seed(1))
        b = sample_vmf(vmf, 10, torch.Generator().manual_seed(1))
        assert torch.equal(a, b)

    def test_exception(self):
        with pytest.raises(ValueError, match="kappa"):
            sample_vmf(VMF(torch.zeros(2, 3), torch.zeros(3)), 4)
        with pytest.raises(ValueError, match="n_samples"):
            sample_vmf(VMF(torch.tensor([[0.0, 0.0, 1.0]]), torch.ones(1)), 0)
        with pytest.raises(TypeError, match="vmf must be a VMF"):
            sample_vmf(torch.tensor([[0.0, 0.0, 1.0]]), 4)  # the mean alone: once an AttributeError on .ndim


def _brute_force_root(X, normals, min_samples_leaf, thresholds):
    """Best (score, feature, left mask) over all given thresholds, by direct enumeration."""
    best = (math.inf, None, None)
    for f in range(X.shape[1]):
        for t in thresholds[f]:
            left = X[:, f] <= t
            n_left = int(left.sum())
            if n_left < min_samples_leaf or len(X) - n_left < min_samples_leaf:
                continue
            score = 0.0
            for side in (left, ~left):
                n = torch.tensor(float(side.sum()), dtype=X.dtype)
                score += float(n * vmf_entropy(vmf_fit(normals[side].sum(0), n).kappa))
            if score < best[0]:
                best = (score, f, left)
    return best


def _root_score(forest, X, normals):
    f, t = int(forest.feature_[0]), forest.threshold_[0]
    left = X[:, f] <= t
    score = 0.0
    for side in (left, ~left):
        n = torch.tensor(float(side.sum()), dtype=X.dtype)
        score += float(n * vmf_entropy(vmf_fit(normals[side].sum(0), n).kappa))
    return f, left, score


class TestSplitSearch:
    @pytest.mark.parametrize("seed", range(6))
    def test_all_thresholds_vs_brute_force(self, seed):
        # n_bins >= rows: every distinct value is its own bin, so the histogram search is exhaustive
        g = torch.Generator().manual_seed(seed)
        X = torch.rand(48, 4, generator=g, dtype=torch.float64)
        normals = _random_unit(48, seed + 100)
        normals[X[:, seed % 4] > 0.6] += torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
        normals = torch.nn.functional.normalize(normals, dim=1)
        forest = VMFForest(n_trees=1, max_depth=1, min_samples_leaf=3, max_features=4, n_bins=64, sample_fraction=1.0)
        forest.fit(X, normals)
        score, feature, left = _brute_force_root(X, normals, 3, [X[:, f].unique() for f in range(4)])
        got_feature, got_left, got_score = _root_score(forest, X, normals)
        assert got_feature == feature
        assert torch.equal(got_left, left)
        assert got_score == pytest.approx(score, rel=1e-9)

    @pytest.mark.parametrize("seed", range(3))
    def test_binned_thresholds_vs_brute_force(self, seed):
        # with few bins the candidates are the quantile edges; brute force over the same edges
        g = torch.Generator().manual_seed(seed)
        X = torch.randn(300, 5, generator=g, dtype=torch.float64)
        normals = torch.nn.functional.normalize(
            torch.stack([X[:, 1], X[:, 3].tanh(), torch.full_like(X[:, 0], 1.5)], 1)
            + 0.3 * _random_unit(300, seed + 7),
            dim=1,
        )
        forest = VMFForest(n_trees=1, max_depth=1, min_samples_leaf=5, max_features=5, n_bins=8, sample_fraction=1.0)
        forest.fit(X, normals)
        edges = _quantile_edges(X, 8, torch.Generator().manual_seed(0))
        score, feature, left = _brute_force_root(X, normals, 5, edges)
        got_feature, got_left, got_score = _root_score(forest, X, normals)
        assert (got_feature, got_score) == (feature, pytest.approx(score, rel=1e-9))
        assert torch.equal(got_left, left)

    def test_no_gain_no_split(self):
        # identical normals: no split can lower the entropy
        X = torch.rand(100, 3, generator=torch.Generator().manual_seed(0))
        normals = torch.tensor([[0.0, 0.0, 1.0]]).expand(100, 3)
        forest = VMFForest(n_trees=2, max_depth=5, min_samples_leaf=2, max_features=3).fit(X, normals)
        assert forest.child_.numel() == 2 and forest.depth_ == 0
        assert forest.kappa_.tolist() == [MAX_KAPPA, MAX_KAPPA]


class TestBinning:
    @pytest.mark.parametrize("n_bins", [2, 3, 8, 64, 256])
    def test_matches_counting_edges(self, n_bins, dtype):
        # integer-valued data: many values sit exactly on an edge and many edges repeat
        g = torch.Generator().manual_seed(n_bins)
        X = (4 * torch.randn(3000, 5, generator=g, dtype=torch.float64)).round().to(dtype)
        X[:, 4] = 1.0  # a constant feature: all its edges are equal
        edges = _quantile_edges(X, n_bins, torch.Generator().manual_seed(0))
        expected = (X.T[:, :, None] > edges[:, None, :]).sum(2).to(torch.uint8)  # edges strictly below
        got = _bin(X, edges)
        assert got.dtype == torch.uint8 and got.shape == (5, 3000)
        assert torch.equal(got, expected)
        assert int(got[4].max()) == 0 and int(got.max()) <= n_bins - 1

    def test_extremes(self):
        X = torch.tensor([[-1e30], [0.0], [0.5], [1.0], [1e30]])
        edges = torch.tensor([[0.0, 0.5, 1.0]])
        assert _bin(X, edges)[0].tolist() == [0, 0, 1, 2, 3]


class TestFeatureDraws:
    def test_mix32_matches_full_product(self):
        # the split 16-bit product must equal the exact 32-bit hash (Python ints do not overflow)
        def reference(x):
            x ^= x >> 16
            x = (x * 0x7FEB352D) % 2**32
            x ^= x >> 15
            x = (x * 0x846CA68B) % 2**32
            return x ^ (x >> 16)

        g = torch.Generator().manual_seed(0)
        values = torch.cat([torch.tensor([0, 1, 2**31, 2**32 - 1]), torch.randint(0, 2**32, (1000,), generator=g)])
        got = _mix32(values)
        assert got.tolist() == [reference(int(v)) for v in values]
        assert int(got.min()) >= 0 and int(got.max()) < 2**32
        assert _mix32(12345) == reference(12345)

    def test_golden(self):
        # pinned: the same seed must draw the same features on every device and version
        assert _draw_features(0, torch.tensor([0, 1, 2, 7, 123456789]), 5, 3).tolist() == [
            [0, 3, 4], [3, 0, 2], [1, 0, 4], [2, 1, 3], [1, 3, 4]
        ]
        assert _draw_features(2**40 + 3, torch.tensor([0, 1, 2]), 23, 4).tolist() == [
            [15, 8, 2, 22], [6, 22, 17, 3], [20, 3, 10, 5]
        ]

    def test_distinct_and_seeded(self):
        nodes = torch.arange(5000)
        a = _draw_features(3, nodes, 23, 8)
        assert a.shape == (5000, 8) and a.dtype == torch.int64
        assert (a.sort(1).values.diff(dim=1) > 0).all() and int(a.min()) >= 0 and int(a.max()) < 23
        assert torch.equal(a, _draw_features(3, nodes, 23, 8))
        assert (a != _draw_features(4, nodes, 23, 8)).any(1).float().mean() > 0.9
        assert (a != _draw_features(3 + 2**32, nodes, 23, 8)).any(1).float().mean() > 0.9  # all seed bits count
        assert torch.equal(_draw_features(3, nodes, 23, 23).sort(1).values, torch.arange(23).expand(5000, 23))

    def test_uniform_and_independent(self):
        f = _draw_features(0, torch.arange(100_000), 23, 8)
        for counts in (torch.bincount(f.reshape(-1), minlength=23), torch.bincount(f[:, 0], minlength=23)):
            assert stats.chisquare(counts.double().numpy()).pvalue > 1e-3
        # siblings and parent/child have consecutive ids: their first features are independent
        joint = torch.bincount(f[:-1, 0] * 23 + f[1:, 0], minlength=23 * 23)
        assert stats.chisquare(joint.double().numpy()).pvalue > 1e-3

    def test_device(self, device):
        nodes = torch.arange(1000, device=device) * 7
        got = _draw_features(11, nodes, 23, 8)
        assert got.device.type == device.type
        assert torch.equal(got.cpu(), _draw_features(11, nodes.cpu(), 23, 8))

    def test_child_keys_golden(self):
        # pinned like the draws: a node's key is a hash of its tree's index and its path
        keys = _child_keys(torch.tensor([0, 0, 5, 2**32 - 1]), torch.tensor([0, 1, 1, 0]))
        assert keys.tolist() == [33350994, 83415710, 1483258754, 2767685996]

    def test_child_keys_give_independent_draws(self):
        # the keys of 8 levels of 64 trees: all distinct, and the first feature drawn
        # at a node is independent of its parent's and of its sibling's
        parents, firsts = [torch.arange(64)], []
        for _ in range(7):
            p = parents[-1].repeat_interleave(2)
            parents.append(_child_keys(p, torch.arange(p.numel()) % 2))
        keys = torch.cat(parents)
        assert keys.unique().numel() == keys.numel() == 64 * (2**8 - 1)
        assert int(keys.min()) >= 0 and int(keys.max()) < 2**32
        for level in range(1, 8):
            parent = _draw_features(0, parents[level - 1], 23, 8)[:, 0].repeat_interleave(2)
            child = _draw_features(0, parents[level], 23, 8)[:, 0]
            firsts.append((parent, child, child.view(-1, 2).flip(1).reshape(-1)))
        parent, child, sibling = (torch.cat(x) for x in zip(*firsts))
        for other in (parent, sibling):
            joint = torch.bincount(other * 23 + child, minlength=23 * 23)
            assert stats.chisquare(joint.double().numpy()).pvalue > 1e-3


def _torch_search(pairs, feats, node_pairs, *, n_bins, min_samples_leaf):
    # the torch ops on the compiled search's arguments: the pairs' own bins and statistics
    # as a table of as many rows (feature-major), and pnode from node_pairs
    n_pairs = pairs.count
    stats = pairs.stats[:n_pairs]
    stream = [torch.complex(stats[:, 0], stats[:, 1]), torch.complex(stats[:, 2], stats[:, 3])]
    offset = torch.arange(n_pairs, dtype=torch.int32)
    pnode = torch.repeat_interleave(torch.arange(feats.shape[0], dtype=torch.int32), node_pairs)
    work = forest_module._Workspace(n_pairs, torch.int32, stream[0].dtype, offset.device)
    return forest_module._search_splits(pairs.bins[:n_pairs].T.contiguous().view(-1), feats, offset, pnode, stream,
                                        n_rows=n_pairs, n_bins=n_bins, min_samples_leaf=min_samples_leaf, work=work)


def test_import_does_not_load_numba():
    # the compiled loops load at the first CPU fit (about a second), not at import
    code = "import sys, sfs_torch, sfs_torch.forest, sfs_torch.pipeline; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


class TestGrowInternals:
    def test_compact(self):
        mask = torch.rand(1000, generator=torch.Generator().manual_seed(0)) > 0.7
        assert torch.equal(_compact(mask, int(mask.sum())), mask.nonzero().squeeze(1))
        assert _compact(torch.zeros(5, dtype=torch.bool), 0).numel() == 0

    def test_int64_indices_give_the_same_forest(self, monkeypatch):
        X, normals = _smooth_data(6_000, noise=0.1, seed=4)
        kw = dict(n_trees=3, max_depth=9, min_samples_leaf=4, max_features=3, n_bins=32)
        small = VMFForest(**kw).fit(X, normals)
        monkeypatch.setattr(forest_module, "_INT32_LIMIT", 1)  # every index tensor int64
        wide = VMFForest(**kw).fit(X, normals)
        for name in ("feature_", "threshold_", "child_", "mean_", "kappa_"):
            assert torch.equal(getattr(small, name), getattr(wide, name))

    def test_compiled_search_matches_the_torch_search(self, monkeypatch):
        # the CPU's compiled split search against the torch ops that serve other devices,
        # level by level on the same inputs: same thresholds, same statistics
        X, normals = _smooth_data(8_000, noise=0.1, seed=6)
        compiled = forest_module._search_splits_compiled
        levels = []

        def both(pairs, feats, node_pairs, *, n_bins, min_samples_leaf):
            ours = compiled(pairs, feats, node_pairs, n_bins=n_bins, min_samples_leaf=min_samples_leaf)
            theirs = _torch_search(pairs, feats, node_pairs, n_bins=n_bins, min_samples_leaf=min_samples_leaf)
            levels.append((ours, theirs))
            return theirs  # the whole fit follows the torch ops, so every level is compared

        monkeypatch.setattr(forest_module, "_search_splits_compiled", both)
        VMFForest(n_trees=3, max_depth=10, min_samples_leaf=4, max_features=3, n_bins=32, n_jobs=1).fit(X, normals)
        assert len(levels) >= 20
        for (best, slot, b, left, total), (best_t, slot_t, b_t, left_t, total_t) in levels:
            found = torch.isfinite(best_t)
            assert torch.equal(torch.isfinite(best), found)
            torch.testing.assert_close(best[found], best_t[found], rtol=1e-5, atol=1e-3)
            # other thresholds only where two score within rounding (the scores agree, above)
            same = ((slot == slot_t) & (b == b_t))[found]
            assert int((~same).sum()) <= max(1, same.numel() // 100)
            found &= (slot == slot_t) & (b == b_t)
            # the statistics of nodes that split (the others' are never read)
            torch.testing.assert_close(total[found], total_t[found], rtol=1e-5, atol=1e-3)
            torch.testing.assert_close(left[found], left_t[found], rtol=1e-5, atol=1e-3)
            assert torch.equal(left[found, 0], left_t[found, 0]) and torch.equal(total[found, 0], total_t[found, 0])

    def test_compiled_search_grows_as_accurate_a_forest(self, monkeypatch):
        X, normals = _smooth_data(12_000, noise=0.1, seed=7)
        X_test, normals_test = _smooth_data(4_000, noise=0.0, seed=8)
        kw = dict(n_trees=4, max_depth=12, min_samples_leaf=5, max_features=3, n_bins=32)
        errors = []
        for path in ("compiled", "torch"):
            if path == "torch":
                monkeypatch.setattr(forest_module, "_search_splits_compiled", _torch_search)
            pred = VMFForest(**kw).fit(X, normals).predict(X_test).mean
            errors.append(torch.rad2deg(torch.acos((pred * normals_test).sum(1).clamp(-1, 1))).median())
        assert abs(float(errors[0] - errors[1])) < 0.02

    def test_node_statistics_match_routing(self):
        # every node's vMF must be that of the training rows routed to it: checks the
        # per-level partition of the (tree, row) pairs at every node, not only the leaves
        X, normals = _smooth_data(5_000, noise=0.2, seed=5, dtype=torch.float64)
        forest = VMFForest(n_trees=3, max_depth=8, min_samples_leaf=5, max_features=3, sample_fraction=1.0).fit(X, normals)
        n_nodes = forest.child_.numel()
        total = torch.zeros(n_nodes, 3, dtype=torch.float64)
        count = torch.zeros(n_nodes, dtype=torch.float64)
        node = torch.arange(3).repeat(len(X))  # (row, tree) flat
        rows = torch.arange(len(X)).repeat_interleave(3)
        moving = torch.ones_like(node, dtype=torch.bool)
        for _ in range(forest.depth_ + 1):
            total.index_add_(0, node[moving], normals[rows[moving]])
            count.index_add_(0, node[moving], torch.ones(int(moving.sum()), dtype=torch.float64))
            nxt = forest.child_[node] + (X[rows, forest.feature_[node]] > forest.threshold_[node])
            moving &= nxt != node
            node = nxt
        assert int(count[:3].sum()) == 3 * len(X) and int(count.min()) >= 5
        fit = vmf_fit(total, count)
        torch.testing.assert_close(fit.mean, forest.mean_, rtol=0, atol=1e-9)
        torch.testing.assert_close(fit.kappa, forest.kappa_, rtol=1e-9, atol=1e-9)

    def test_n_jobs_do_not_change_the_forest(self):
        # trees grow in n_jobs threads; the draws are keyed per tree, so the forest is the same bit for bit
        X, normals = _smooth_data(20_000, noise=0.1, seed=1)
        kw = dict(n_trees=5, max_depth=10, min_samples_leaf=4, max_features=3, n_bins=32, seed=2)
        threads = torch.get_num_threads()
        forests = [VMFForest(n_jobs=jobs, **kw).fit(X, normals) for jobs in (1, 2, 5)]
        assert torch.get_num_threads() == threads  # the process's settings are left alone
        assert forests[0].depth_ == 10 and forests[0].child_.numel() > 2000
        for other in forests[1:]:
            for name in ("feature_", "threshold_", "child_", "mean_", "kappa_"):
                assert torch.equal(getattr(forests[0], name), getattr(other, name)), name

    def test_n_jobs_threads(self, monkeypatch):
        # n_jobs = 1 grows every tree in the calling thread, n_jobs = 2 in (at most) two workers
        X, normals = _smooth_data(3_000, seed=0)
        seen = []

        def spy(*args, **kwargs):
            seen.append(threading.current_thread())
            return _grow_trees(*args, **kwargs)

        monkeypatch.setattr(forest_module, "_grow_trees", spy)
        VMFForest(n_trees=4, max_depth=4, n_jobs=1).fit(X, normals)
        assert seen == [threading.current_thread()] * 4
        seen.clear()
        VMFForest(n_trees=4, max_depth=4, n_jobs=2).fit(X, normals)
        assert len(seen) == 4 and 1 <= len(set(seen)) <= 2
        assert all(t.name.startswith("sfs_torch.forest") for t in seen)

    def test_tree_depends_on_its_index_only(self):
        # tree t draws its rows t-th and its features from keys rooted at t: the first
        # 3 trees of a 5-tree forest are the trees of the 3-tree forest
        X, normals = _smooth_data(8_000, noise=0.1, seed=3)
        kw = dict(max_depth=8, min_samples_leaf=4, max_features=3, seed=5)
        three = VMFForest(n_trees=3, **kw).fit(X, normals)
        five = VMFForest(n_trees=5, **kw).fit(X, normals)
        a, b = three.predict_leaves(X[:2000]), five.predict_leaves(X[:2000])
        assert torch.equal(a.mean, b.mean[:, :3]) and torch.equal(a.kappa, b.kappa[:, :3])
        assert not torch.equal(b.mean[:, 3], b.mean[:, 0])

    def test_one_group_gives_the_same_trees(self):
        # on a GPU all trees grow as one group: on the CPU that gives the per-tree forest
        for dtype in (torch.float32, torch.float64):
            X, normals = _smooth_data(10_000, noise=0.1, seed=7, dtype=dtype)
            g = torch.Generator().manual_seed(0)
            binned = _bin(X, _quantile_edges(X, 32, g))
            rows = _sample_rows(len(X), 4, 0.9, g, X.device)
            kw = dict(max_depth=9, min_samples_leaf=4, max_features=3, n_bins=32, seed=0)
            per_tree = _grow(binned, normals, rows, n_jobs=2, **kw)
            stream = _row_streams(normals)
            compiled = dict(rows_table=forest_module._rows_table(binned, stream)) if dtype == torch.float32 else {}
            one = _assemble_levels([_grow_trees(binned, stream, rows, 0, index_dtype=torch.int32, **compiled, **kw)])
            assert per_tree["depth"] == one["depth"] == 9
            for name in ("feature", "bin", "child", "count", "sum"):
                assert torch.equal(per_tree[name], one[name]), name

    def test_threads_do_not_change_the_forest(self):
        X, normals = _smooth_data(20_000, noise=0.1, seed=0)
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            a = VMFForest(n_trees=3, max_depth=10).fit(X, normals)
            torch.set_num_threads(2)
            b = VMFForest(n_trees=3, max_depth=10).fit(X, normals)
        finally:
            torch.set_num_threads(threads)
        for name in ("feature_", "threshold_", "child_", "mean_", "kappa_"):
            assert torch.equal(getattr(a, name), getattr(b, name))


class TestVMFForest:
    def test_smooth_function(self, device):
        X, normals = _smooth_data(30_000, seed=0)
        X_test, normals_test = _smooth_data(5_000, seed=1)
        forest = VMFForest(n_trees=4, max_depth=12, min_samples_leaf=3, max_features=4, n_bins=64, device=device)
        forest.fit(X, normals)
        pred = forest.predict(X_test.to(device))
        err = _angle_deg(pred.mean.cpu(), normals_test)
        assert float(err.median()) < 2.5
        assert float(err.quantile(0.9)) < 6.0
        assert pred.mean.shape == (5_000, 3) and pred.kappa.shape == (5_000,)
        assert (pred.kappa > 0).all() and torch.isfinite(pred.kappa).all()

    def test_noise_lowers_kappa(self):
        X, n_clean = _smooth_data(20_000, seed=0)
        _, n_noisy = _smooth_data(20_000, noise=0.3, seed=0)
        kw = dict(n_trees=3, max_depth=8, min_samples_leaf=5, max_features=3)
        k_clean = VMFForest(**kw).fit(X, n_clean).predict(X[:2000]).kappa.median()
        k_noisy = VMFForest(**kw).fit(X, n_noisy).predict(X[:2000]).kappa.median()
        assert float(k_noisy) < 0.5 * float(k_clean)

    def test_training_data_that_requires_grad_is_read_as_constants(self):
        # hard splits carry no gradient; targets that required grad failed in a numpy() call deep inside
        X, normals = _smooth_data(2_000, seed=0)
        kw = dict(n_trees=2, max_depth=6)
        graph = VMFForest(**kw).fit(X.clone().requires_grad_() * 1, normals.clone().requires_grad_() * 1)
        plain = VMFForest(**kw).fit(X, normals)
        pred, expected = graph.predict(X[:200].clone().requires_grad_()), plain.predict(X[:200])
        assert not pred.mean.requires_grad and torch.equal(pred.mean, expected.mean)
        assert torch.equal(pred.kappa, expected.kappa)

    def test_predict_combines_leaves(self):
        X, normals = _smooth_data(5_000, seed=0)
        forest = VMFForest(n_trees=5, max_depth=6).fit(X, normals)
        leaves, pred = forest.predict_leaves(X[:100]), forest.predict(X[:100])
        assert leaves.mean.shape == (100, 5, 3) and leaves.kappa.shape == (100, 5)
        s = (leaves.kappa[..., None] * leaves.mean).sum(1)
        torch.testing.assert_close(pred.mean, s / s.norm(dim=1, keepdim=True))
        torch.testing.assert_close(pred.kappa, s.norm(dim=1) / 5)
        # leaves hold the in-bag statistics: their means are unit vectors
        torch.testing.assert_close(leaves.mean.norm(dim=-1), torch.ones(100, 5))

    def test_leaf_sizes_and_depth(self):
        # with all rows in the bag, routing the training rows reproduces the leaf counts
        X, normals = _smooth_data(4_000, noise=0.2, seed=2)
        forest = VMFForest(n_trees=3, max_depth=5, min_samples_leaf=20, sample_fraction=1.0).fit(X, normals)
        node = forest._leaf_index(X)
        is_leaf = forest.child_ == torch.arange(forest.child_.numel())
        assert is_leaf[node].all() and forest.depth_ == 5
        per_leaf = torch.bincount(node.reshape(-1), minlength=is_leaf.numel())[is_leaf]
        assert int(per_leaf.min()) >= 20 and int(per_leaf.sum()) == 3 * 4_000

    def test_float64(self):
        X, normals = _smooth_data(3_000, dtype=torch.float64)
        pred = VMFForest(n_trees=2, max_depth=6).fit(X, normals).predict(X)
        assert pred.mean.dtype == torch.float64 and pred.kappa.dtype == torch.float64

    def test_same_seed_same_forest(self):
        X, normals = _smooth_data(8_000, noise=0.1, seed=0)
        a = VMFForest(n_trees=3, max_depth=8, seed=7).fit(X, normals)
        b = VMFForest(n_trees=3, max_depth=8, seed=7).fit(X, normals)
        c = VMFForest(n_trees=3, max_depth=8, seed=8).fit(X, normals)
        for name in ("feature_", "threshold_", "child_", "mean_", "kappa_"):
            assert torch.equal(getattr(a, name), getattr(b, name))
        assert not torch.equal(a.threshold_, c.threshold_) or not torch.equal(a.feature_, c.feature_)

    def test_save_load_bit_exact(self, tmp_path):
        X, normals = _smooth_data(5_000, noise=0.1, seed=0)
        forest = VMFForest(n_trees=3, max_depth=7, max_features=0.5, seed=3).fit(X, normals)
        forest.save(tmp_path / "forest.safetensors")
        loaded = VMFForest.load(tmp_path / "forest.safetensors")
        assert loaded.get_params() == forest.get_params()
        assert loaded.max_features == 0.5 and loaded.depth_ == forest.depth_
        for name in ("feature_", "threshold_", "child_", "mean_", "kappa_"):
            assert torch.equal(getattr(loaded, name), getattr(forest, name))
        a, b = forest.predict(X), loaded.predict(X)
        assert torch.equal(a.mean, b.mean) and torch.equal(a.kappa, b.kappa)

    def test_device(self, device):
        X, normals = _smooth_data(4_000, noise=0.1, seed=0)
        cpu = VMFForest(n_trees=2, max_depth=6).fit(X, normals)
        moved = VMFForest(n_trees=2, max_depth=6).fit(X, normals).to(device)
        assert moved.child_.device.type == device.type
        pred = moved.predict(X.to(device))
        assert pred.mean.device.type == device.type
        torch.testing.assert_close(pred.mean.cpu(), cpu.predict(X).mean)
        trained = VMFForest(n_trees=2, max_depth=6, device=device).fit(X, normals)
        assert trained.child_.device.type == device.type
        # same random draws on every device; sums may differ in the last bits on GPU
        agree = (trained.predict(X).mean.cpu() - cpu.predict(X).mean).norm(dim=1) < 1e-4
        assert float(agree.float().mean()) > 0.99

    def test_params_stored_unchanged(self):
        forest = VMFForest(n_trees=3, max_features=0.3, n_bins=16, device="cpu")
        assert (forest.n_trees, forest.max_features, forest.n_bins, forest.device) == (3, 0.3, 16, "cpu")
        config = ForestConfig()
        assert VMFForest().n_trees == config.n_trees and VMFForest().max_depth == config.max_depth

    def test_instantiate_from_config(self):
        from dataclasses import asdict

        from hydra.utils import instantiate

        forest = instantiate(ForestConfig(n_trees=3, max_depth=5))
        assert isinstance(forest, VMFForest) and (forest.n_trees, forest.max_depth) == (3, 5)
        fields = {k: v for k, v in asdict(ForestConfig()).items() if k != "_target_"}
        assert all(getattr(instantiate(ForestConfig()), k) == v for k, v in fields.items())

    def test_not_fitted(self):
        forest = VMFForest()
        with pytest.raises(NotFittedError, match="fit"):
            forest.predict(torch.rand(3, 4))
        assert issubclass(NotFittedError, ValueError)

    def test_exception(self):
        X, normals = _smooth_data(200)
        with pytest.raises(ValueError, match="X"):
            VMFForest().fit(X[:, 0], normals)
        with pytest.raises(ValueError, match="normals"):
            VMFForest().fit(X, normals[:, :2])
        with pytest.raises(ValueError, match="same number of rows"):
            VMFForest().fit(X, normals[:100])
        bad = X.clone()
        bad[3, 1] = float("nan")
        with pytest.raises(ValueError, match="X contains"):
            VMFForest().fit(bad, normals)
        with pytest.raises(ValueError, match="unit"):
            VMFForest().fit(X, 2 * normals)
        with pytest.raises(ValueError, match="n_bins"):
            VMFForest(n_bins=300).fit(X, normals)
        with pytest.raises(ValueError, match="max_features"):
            VMFForest(max_features=1.5).fit(X, normals)
        for bad_jobs in (0, -1, 1.5, True):
            with pytest.raises(ValueError, match="n_jobs must be None"):
                VMFForest(n_jobs=bad_jobs).fit(X, normals)
        forest = VMFForest(n_trees=2, max_depth=3).fit(X, normals)
        with pytest.raises(ValueError, match="6 features"):
            forest.predict(X[:, :4])
        with pytest.raises(ValueError, match="X contains"):
            forest.predict(bad)
