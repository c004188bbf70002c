import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from sfs_torch.camera import rotate_normals_to_camera
from sfs_torch.silhouette import (
    SilhouetteConfig,
    SilhouetteDistances,
    coarse_normals,
    euclidean_distance_transform,
    _edt_squared_torch,
    _lower_envelope,
    check_silhouette_config,
    medial_axis,
    silhouette_distances,
    silhouette_features,
)

RADIUS = 100.0
SIZE = 256


def disk(size: int = SIZE, radius: float = RADIUS, centre=None):
    """Disk mask and the camera-frame (u, v) of every pixel (principal point = centre)."""
    cx, cy = (size / 2, size / 2) if centre is None else centre
    j = np.arange(size) + 0.5 - cx
    i = cy - (np.arange(size) + 0.5)
    u, v = np.meshgrid(j, i)
    return u * u + v * v < radius * radius, u, v


@pytest.fixture(scope="module")
def disk_result():
    mask, u, v = disk()
    m = torch.from_numpy(mask)[None, None]
    return mask, u, v, silhouette_distances(m), coarse_normals(m)


@st.composite
def shapes(draw):
    """Unions of disks and rectangles, minus a few holes; often touching the border."""
    h = draw(st.integers(8, 40))
    w = draw(st.integers(8, 40))
    ii, jj = np.mgrid[:h, :w]
    mask = np.zeros((h, w), bool)

    def blob():
        ci, cj = draw(st.floats(-4, h + 4)), draw(st.floats(-4, w + 4))
        if draw(st.booleans()):
            r = draw(st.floats(1, 15))
            return (ii - ci) ** 2 + (jj - cj) ** 2 < r * r
        a, b = draw(st.floats(1, 20)), draw(st.floats(1, 20))
        return (abs(ii - ci) < a) & (abs(jj - cj) < b)

    for _ in range(draw(st.integers(1, 4))):
        mask |= blob()
    for _ in range(draw(st.integers(0, 2))):
        mask &= ~blob()
    return mask


def angle_diff(a, b):
    return np.abs(np.angle(np.exp(1j * (a - b))))


class TestEuclideanDistanceTransform:
    @settings(max_examples=60, deadline=None)
    @given(shapes())
    def test_equals_scipy(self, mask):
        got = euclidean_distance_transform(torch.from_numpy(mask)[None, None])[0, 0].numpy()
        if mask.all():
            assert np.isinf(got).all()
        else:
            np.testing.assert_allclose(got, ndimage.distance_transform_edt(mask), atol=1e-4)

    @settings(max_examples=40, deadline=None)
    @given(shapes())
    def test_torch_transform_equals_scipy(self, mask):
        # The torch transform serves every non-CPU device; check it on the CPU too.
        if mask.all():
            return
        dist2, rows, cols = _edt_squared_torch(torch.from_numpy(mask)[None])
        np.testing.assert_allclose(dist2[0].sqrt().numpy(), ndimage.distance_transform_edt(mask), atol=1e-4)
        r = torch.arange(mask.shape[0])[:, None]
        c = torch.arange(mask.shape[1])[None, :]
        # the feature transform points at a background pixel at exactly that distance
        assert not mask[rows[0].numpy(), cols[0].numpy()].any()
        assert torch.equal(((rows[0] - r) ** 2 + (cols[0] - c) ** 2).float(), dist2[0])

    def test_batch_equals_single(self, device):
        rng = np.random.default_rng(0)
        masks = ndimage.binary_opening(rng.random((2, 1, 30, 45)) < 0.8, np.ones((1, 1, 3, 3)))
        m = torch.from_numpy(masks).to(device)
        batched = euclidean_distance_transform(m)
        assert batched.shape == (2, 1, 30, 45) and batched.device.type == device.type
        for b in range(2):
            single = euclidean_distance_transform(m[b])  # (1, H, W): unbatched
            assert single.shape == (1, 30, 45)
            torch.testing.assert_close(batched[b], single)
            np.testing.assert_allclose(single[0].cpu().numpy(), ndimage.distance_transform_edt(masks[b, 0]), atol=1e-4)

    def test_border_is_not_background(self):
        m = torch.zeros(1, 1, 5, 9, dtype=torch.bool)
        m[..., :, :4] = True  # cut by the top, bottom and left border
        d = euclidean_distance_transform(m)[0, 0]
        torch.testing.assert_close(d[2], torch.tensor([4.0, 3, 2, 1, 0, 0, 0, 0, 0]))

    def test_empty_and_numeric_mask(self):
        torch.testing.assert_close(euclidean_distance_transform(torch.zeros(6, 7)), torch.zeros(6, 7))
        m = torch.zeros(1, 1, 5, 5)
        m[..., 2, 2] = 1.0
        assert float(euclidean_distance_transform(m)[0, 0, 2, 2]) == 1.0

    def test_large_distance_exact(self):
        mask, _, _ = disk(300, 140.0)
        got = euclidean_distance_transform(torch.from_numpy(mask))
        np.testing.assert_allclose(got.numpy(), ndimage.distance_transform_edt(mask), atol=1e-4)

    def test_exception(self):
        with pytest.raises(ValueError, match="mask"):
            euclidean_distance_transform(torch.zeros(2, 3, 5, 5, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask"):
            euclidean_distance_transform(torch.full((1, 1, 5, 5), 2.0))
        with pytest.raises(TypeError, match="mask"):
            euclidean_distance_transform(np.zeros((5, 5), bool))


class TestTorchTransform:
    """``_edt_squared_torch`` (every non-CPU device) on edge cases, against SciPy."""

    @staticmethod
    def _check(mask: np.ndarray, device="cpu"):
        dist2, rows, cols = _edt_squared_torch(torch.from_numpy(mask).to(device))
        dist2, rows, cols = dist2.cpu(), rows.cpu(), cols.cpu()
        for b, m in enumerate(mask):
            if m.all():
                assert torch.isinf(dist2[b]).all()
                continue
            ref = np.rint(ndimage.distance_transform_edt(m) ** 2)
            np.testing.assert_array_equal(dist2[b].numpy(), ref)
            r = torch.arange(m.shape[0])[:, None]
            c = torch.arange(m.shape[1])[None, :]
            assert not m[rows[b].numpy(), cols[b].numpy()].any()
            assert torch.equal(((rows[b] - r) ** 2 + (cols[b] - c) ** 2).float(), dist2[b])
        return dist2

    def test_empty_mask(self, device):
        assert not self._check(np.zeros((1, 7, 9), bool), device).any()

    def test_full_mask(self, device):
        # no background at all: inf everywhere, also next to an ordinary element
        mask = np.ones((2, 6, 5), bool)
        mask[1, 2, 3] = False
        dist2 = self._check(mask, device)
        assert torch.isinf(dist2[0]).all() and torch.isfinite(dist2[1]).all()

    def test_one_pixel(self, device):
        one_fg = np.zeros((1, 5, 8), bool)
        one_fg[0, 2, 3] = True
        assert float(self._check(one_fg, device).max()) == 1.0
        one_bg = ~one_fg  # every distance measured to a single background pixel
        dist2 = self._check(one_bg, device)
        assert float(dist2[0, 4, 7]) == 2.0 * 2.0 + 4.0 * 4.0

    def test_single_row_and_column(self, device):
        for shape in ((1, 1, 9), (1, 9, 1), (1, 1, 1)):
            mask = np.ones(shape, bool)
            mask.flat[len(mask.flat) // 2] = False
            self._check(mask, device)

    def test_border_touching(self, device):
        mask = np.zeros((3, 30, 41), bool)
        mask[0, :, :20] = True  # cut by three borders
        mask[1, 5:, 10:] = True  # a corner
        mask[2] = True
        mask[2, 0, 0] = False  # one background pixel in a corner: distances up to the far corner
        self._check(mask, device)

    def test_large(self, device):
        mask, _, _ = disk(300, 145.0)  # distances near 145, near the sizes the pipeline uses
        self._check(mask[None], device)


class TestLowerEnvelope:
    @staticmethod
    def _brute(f):
        n = f.shape[1]
        j = torch.arange(n, dtype=torch.float64)
        return (f.double()[:, None, :] + (j[:, None] - j[None, :]) ** 2).min(2)

    @pytest.mark.parametrize("max_site", [30 * 30, 1 << 40], ids=["int32", "int64"])
    def test_equals_brute_force(self, max_site):
        g = torch.Generator().manual_seed(0)
        for _ in range(100):
            n = int(torch.randint(1, 50, (1,), generator=g))
            f = torch.randint(0, 31, (4, n), generator=g).float() ** 2
            f[torch.rand(4, n, generator=g) < float(torch.rand(1, generator=g))] = math.inf
            f[0] = math.inf  # a row without sites
            value, arg = _lower_envelope(f, max_site=max_site)
            ref, ref_arg = self._brute(f)
            assert torch.equal(value.double(), ref)
            finite = torch.isfinite(ref)
            # the leftmost argmin (ties go to the smaller column)
            assert torch.equal(arg[finite], ref_arg[finite])
            assert bool(torch.isinf(value[0]).all())


class TestCheckSilhouetteConfig:
    @pytest.mark.parametrize("options, message", [
        ({"prune_distance": -1.0}, r"prune_distance must be a finite number >= 0, got -1.0"),
        ({"gradient_sigma": math.nan}, r"gradient_sigma must be a finite number >= 0, got nan"),
        ({"prune_angle": 181.0}, r"prune_angle must be in \[0, 180\] degrees, got 181.0"),
        ({"depth_layer_ratio": 1.0}, r"depth_layer_ratio must be > 1 \(inf for none\), got 1.0"),
    ])
    @pytest.mark.parametrize("prefix", ["", "silhouette."])
    def test_exception_names_the_key(self, options, message, prefix):
        with pytest.raises(ValueError, match=f"^{re.escape(prefix)}{message}$"):
            check_silhouette_config(SilhouetteConfig(**options), prefix=prefix)

    def test_valid(self):
        # the defaults, no pruning or smoothing at all, and the plain distance to the axis
        unpruned = SilhouetteConfig(prune_distance=0.0, prune_angle=0.0, prune_depth_ratio=0.0, gradient_sigma=0.0)
        for cfg in (SilhouetteConfig(), unpruned, SilhouetteConfig(depth_layer_ratio=math.inf)):
            check_silhouette_config(cfg, prefix="silhouette.")

    def test_the_functions_check_their_config(self):
        mask, _, _ = disk(32, 10.0)
        m = torch.from_numpy(mask)[None, None]
        bad = SilhouetteConfig(prune_angle=-5.0)
        for function in (medial_axis, silhouette_distances, silhouette_features, coarse_normals):
            with pytest.raises(ValueError, match=r"^config\.prune_angle must be a finite number >= 0"):
                function(m, config=bad)


class TestMedialAxis:
    def test_disk_centre(self, disk_result):
        mask, u, v, dist, _ = disk_result
        axis = dist.medial[0, 0].numpy()
        assert axis.any()
        assert np.sqrt(u[axis] ** 2 + v[axis] ** 2).max() < 1.0

    def test_rectangle(self):
        m = torch.zeros(1, 1, 40, 100, dtype=torch.bool)
        m[..., 10:31, 10:91] = True  # 21 rows: the centre row is row 20
        axis = medial_axis(m)[0, 0]
        assert bool(axis[20, 25:76].all())  # the long central segment
        assert not bool(axis[~m[0, 0]].any())
        # corner branches (90 degree object angle) run along the diagonals; their shallow
        # ends are pruned
        rows, cols = torch.nonzero(axis[:, :20], as_tuple=True)
        assert len(rows) >= 4
        assert bool((((rows - 10) - (cols - 10)).abs() <= 1).logical_or(((rows - 30) + (cols - 10)).abs() <= 1).all())
        assert int(rows.min()) > 12

    def test_noise_robust(self):
        """Contour noise barely moves d_rel with pruning; unpruned it would."""
        rng = np.random.default_rng(3)
        mask, u, v = disk(160, 60.0)
        noisy = mask.copy()
        rim = np.argwhere(np.abs(np.sqrt(u * u + v * v) - 60) < 1.0)
        for i, j in rim[rng.random(len(rim)) < 0.15]:
            noisy[i - 1 : i + 2, j - 1 : j + 2] = rng.random() < 0.5
        both = mask & noisy & (np.sqrt(u * u + v * v) < 55)
        clean = silhouette_distances(torch.from_numpy(mask)[None, None]).d_rel[0, 0].numpy()

        def change(config):
            d = silhouette_distances(torch.from_numpy(noisy)[None, None], config).d_rel[0, 0].numpy()
            return np.median(np.abs(d - clean)[both])

        assert change(SilhouetteConfig()) < 0.03
        unpruned = SilhouetteConfig(prune_distance=1.0, prune_angle=0.0, prune_depth_ratio=0.0)
        assert change(unpruned) > 0.2
        assert change(SilhouetteConfig(depth_layer_ratio=math.inf)) > 0.03

    def test_transposed_mask(self):
        m = torch.zeros(1, 1, 40, 100, dtype=torch.bool)
        m[..., 10:31, 10:91] = True
        m[..., 5:12, 30:40] = True
        torch.testing.assert_close(medial_axis(m.transpose(-1, -2)), medial_axis(m).transpose(-1, -2))

    def test_exception(self):
        with pytest.raises(ValueError, match="empty"):
            medial_axis(torch.zeros(1, 1, 5, 5, dtype=torch.bool))
        with pytest.raises(ValueError, match="whole image"):
            medial_axis(torch.ones(1, 1, 5, 5, dtype=torch.bool))


class TestSilhouetteDistances:
    def test_disk_analytic(self, disk_result):
        mask, u, v, dist, _ = disk_result
        assert isinstance(dist, SilhouetteDistances)
        r = np.sqrt(u * u + v * v)[mask]
        d_rel = dist.d_rel[0, 0].numpy()[mask]
        np.testing.assert_allclose(d_rel, 1 - r / RADIUS, atol=0.012)
        np.testing.assert_allclose(dist.d_boundary[0, 0].numpy()[mask], RADIUS - r, atol=0.75)
        np.testing.assert_allclose(dist.d_medial[0, 0].numpy()[mask], r, atol=1.0)
        for field in (dist.d_boundary, dist.d_medial, dist.d_rel, dist.beta):
            assert float(field[0, 0][~torch.from_numpy(mask)].abs().max()) == 0.0

    def test_beta_points_outward(self, disk_result):
        mask, u, v, dist, _ = disk_result
        err = np.degrees(angle_diff(dist.beta[0, 0].numpy(), np.arctan2(v, u)))[mask]
        assert np.median(err) < 1.0
        assert np.percentile(err, 99) < 10.0
        # the y-up convention: the top of the disk points up, not down
        top = (slice(None), slice(None), SIZE // 2 - 90, SIZE // 2)
        assert abs(float(dist.beta[top]) - math.pi / 2) < 0.05

    def test_components_holes_border(self):
        m = torch.zeros(1, 1, 60, 80, dtype=torch.bool)
        m[..., 0:25, 0:30] = True  # touches the border
        m[..., 30:58, 40:78] = True
        m[..., 40:48, 50:60] = False  # a hole
        m[..., 5:8, 60:63] = True  # tiny component
        dist = silhouette_distances(m)
        inside = m[0, 0]
        d_rel = dist.d_rel[0, 0]
        assert bool(torch.isfinite(d_rel).all() and torch.isfinite(dist.beta).all())
        assert float(d_rel[inside].min()) > 0 and float(d_rel[inside].max()) == 1.0
        assert bool((d_rel[dist.medial[0, 0]] == 1).all())
        # the border is no contour: along the cut the contour lies below / to the right
        assert float(dist.d_boundary[0, 0, 0, 5]) > 20

    def test_transposed_mask(self):
        m = torch.zeros(1, 1, 40, 100, dtype=torch.bool)
        m[..., 10:31, 10:91] = True
        m[..., 5:12, 30:40] = True
        transposed, dist = silhouette_distances(m.transpose(-1, -2)), silhouette_distances(m)
        for field in ("d_boundary", "d_medial", "d_rel", "medial"):
            torch.testing.assert_close(getattr(transposed, field), getattr(dist, field).transpose(-1, -2))
        # beta is not compared: transposing flips its axes, and on the medial axis it
        # comes from a nearest contour pixel whose ties resolve by scan order

    def test_dtype_device(self, device):
        m = torch.zeros(2, 1, 20, 30, dtype=torch.bool, device=device)
        m[0, 0, 3:15, 4:20] = True
        m[1, 0, 5:18, 2:28] = True
        dist = silhouette_distances(m)
        assert dist.d_rel.device.type == device.type and dist.d_rel.dtype == torch.float32
        assert dist.medial.dtype == torch.bool


class TestSilhouetteFeatures:
    def test_values(self, disk_result):
        mask, _, _, dist, _ = disk_result
        f = silhouette_features(torch.from_numpy(mask)[None, None])
        assert f.shape == (1, 3, SIZE, SIZE)
        inside = torch.from_numpy(mask)
        assert float(f[0][:, ~inside].abs().max()) == 0.0
        torch.testing.assert_close(f[0, 0], dist.d_rel[0, 0])
        torch.testing.assert_close(f[0, 1][inside] ** 2 + f[0, 2][inside] ** 2, torch.ones(int(inside.sum())))

    def test_cardinality(self, device):
        m = torch.zeros(2, 1, 24, 32, dtype=torch.bool, device=device)
        m[0, 0, 2:20, 3:15] = True
        yy, xx = torch.meshgrid(torch.arange(24), torch.arange(32), indexing="ij")
        m[1, 0] = ((yy - 12) ** 2 + (xx - 20) ** 2 < 80).to(device)
        batched = silhouette_features(m)
        for b in range(2):
            torch.testing.assert_close(batched[b], silhouette_features(m[b]))  # (1, H, W)
            torch.testing.assert_close(batched[b], silhouette_features(m[b, 0]))  # (H, W)

    def test_transposed_mask(self):
        m = torch.zeros(1, 1, 24, 32, dtype=torch.bool)
        m[0, 0, 2:20, 3:15] = True
        t = m.transpose(-1, -2)
        torch.testing.assert_close(silhouette_features(t), silhouette_features(t.contiguous()))

    def test_exception(self):
        with pytest.raises(ValueError, match="mask"):
            silhouette_features(torch.zeros(1, 2, 5, 5, dtype=torch.bool))
        with pytest.raises(ValueError, match="mask"):
            silhouette_features(torch.rand(1, 1, 5, 5))
        with pytest.raises(ValueError, match="empty"):
            silhouette_features(torch.zeros(2, 1, 5, 5, dtype=torch.bool))


class TestCoarseNormals:
    def test_sphere(self, disk_result):
        mask, u, v, _, normals = disk_result
        n = normals[0].numpy()
        gt = np.stack([u / RADIUS, v / RADIUS, np.sqrt(np.clip(1 - (u * u + v * v) / RADIUS**2, 0, 1))])
        err = np.degrees(np.arccos(np.clip((n * gt).sum(0), -1, 1)))[mask]
        assert np.median(err) < 1.0
        np.testing.assert_allclose(np.linalg.norm(n, axis=0)[mask], 1.0, atol=1e-5)
        assert (n[2][mask] >= 0).all()
        assert np.abs(n[:, ~mask]).max() == 0.0

    def test_perspective(self, device):
        mask, _, _ = disk(64, 20.0, centre=(40.0, 30.0))
        m = torch.from_numpy(mask)[None, None].to(device)
        ortho = coarse_normals(m)
        persp = coarse_normals(m, focal=80.0, principal_point=(30.0, 34.0))
        torch.testing.assert_close(persp, rotate_normals_to_camera(ortho, 80.0, (30.0, 34.0)))
        assert not torch.allclose(persp, ortho)

    def test_transposed_mask(self):
        mask, _, _ = disk(40, 12.0, centre=(15.0, 22.0))
        t = torch.from_numpy(mask)[None, None].transpose(-1, -2)
        torch.testing.assert_close(coarse_normals(t), coarse_normals(t.contiguous()))

    def test_unbatched(self):
        mask, _, _ = disk(40, 12.0)
        m = torch.from_numpy(mask)
        torch.testing.assert_close(coarse_normals(m), coarse_normals(m[None, None])[0])
