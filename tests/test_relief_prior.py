import numpy as np
import pytest
import torch
from scenes import sphere

from sfs_torch.integrability import depth_to_normals
from sfs_torch.metrics import normal_metrics
from sfs_torch.relief_prior import (
    ReliefNet,
    ReliefPrior,
    ReliefTransform,
    apply_relief,
    best_relief,
    compose_relief,
    crop_to_object,
    fit_relief_net,
    load_relief_net,
    predict_relief,
    relief_depth,
    relief_training_views,
    save_relief_net,
)
from sfs_torch.rendering import random_view_rotations, render_normals
from sfs_torch.shapes import blobby_mesh


def transform(*values):
    return ReliefTransform(*(torch.tensor([float(v)]) for v in values))


def blob_views(seed, n=3):
    """True normals and masks of a procedural shape (never in the prior's training set)."""
    mesh = blobby_mesh(seed)
    for rotation in random_view_rotations(n, torch.Generator().manual_seed(seed)):
        view = render_normals(mesh, rotation, 128)
        yield view.normals[None].float(), view.mask[None]


class TestShippedPrior:
    def test_loads_finite(self):
        net = load_relief_net()
        assert isinstance(net, ReliefNet) and not net.training
        assert all(bool(torch.isfinite(p).all()) for p in net.parameters())
        assert net(torch.zeros(2, 4, 64, 64)).shape == (2, 3)

    @pytest.mark.parametrize("seed", [0, 2])
    def test_undoes_a_tilt_of_a_shape_it_never_saw(self, seed):
        net = load_relief_net()
        before, after = [], []
        for normals, mask in blob_views(seed):
            wrong = apply_relief(normals, mask, transform(1.0, 0.4, -0.3))
            corrected = apply_relief(wrong, mask, predict_relief(wrong, mask, net))
            before.append(float(normal_metrics(wrong, normals, mask).median[0]))
            after.append(float(normal_metrics(corrected, normals, mask).median[0]))
        assert np.mean(before) > 14 and np.mean(after) < 0.6 * np.mean(before)

    @pytest.mark.parametrize("symmetry", ["mirror", "quarter turn"])
    def test_a_mirrored_or_turned_field_gets_the_mirrored_or_turned_transform(self, symmetry):
        normals, mask = next(blob_views(0, 1))
        wrong = apply_relief(normals, mask, transform(1.1, 0.3, 0.2))
        if symmetry == "mirror":  # u -> -u
            moved = torch.stack([-wrong[:, 0], wrong[:, 1], wrong[:, 2]], 1).flip(-1)
            moved_mask = mask.flip(-1)
        else:  # counterclockwise on screen: (u, v) -> (-v, u)
            moved = torch.stack([-wrong[:, 1], wrong[:, 0], wrong[:, 2]], 1).rot90(1, (-2, -1))
            moved_mask = mask.rot90(1, (-2, -1))
        net = load_relief_net()
        a, b = predict_relief(wrong, mask, net, passes=1), predict_relief(moved, moved_mask, net, passes=1)
        expected = (-a.tilt_x, a.tilt_y) if symmetry == "mirror" else (-a.tilt_y, a.tilt_x)
        torch.testing.assert_close(b.scale, a.scale, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(b.tilt_x, expected[0], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(b.tilt_y, expected[1], atol=1e-4, rtol=1e-4)

    def test_module_form_and_passes(self):
        normals, mask = next(blob_views(0, 1))
        net = load_relief_net()
        one = predict_relief(normals, mask, net, passes=1)
        two = predict_relief(normals, mask, net, passes=2)
        # the second pass reads the field corrected by the first
        again = predict_relief(apply_relief(normals, mask, one), mask, net, passes=1)
        expected = compose_relief(one, again)
        for field in ("scale", "tilt_x", "tilt_y"):
            torch.testing.assert_close(getattr(two, field), getattr(expected, field))
        module = ReliefPrior(net, passes=2)(normals[0], mask[0])
        torch.testing.assert_close(module.tilt_x, two.tilt_x)

    @pytest.mark.parametrize("bad, message", [
        (dict(passes=0), "passes must be an integer >= 1"),
        (dict(normals=torch.ones(1, 3, 8, 8)), "normals must have unit length .* on the mask"),
        (dict(mask=torch.zeros(1, 1, 8, 8, dtype=torch.bool)), "mask is empty"),
    ])
    def test_refuses_bad_input(self, bad, message):
        normals, mask = sphere(8, radius=3.5)
        kwargs = {**dict(normals=normals[None], mask=mask[None], passes=1), **bad}
        with pytest.raises(ValueError, match=message):
            predict_relief(kwargs["normals"], kwargs["mask"], load_relief_net(), kwargs["passes"])


class TestTransforms:
    def test_composition_is_applying_one_after_the_other(self):
        normals, mask = sphere(32, radius=14.0)
        n, m = normals[None], mask[None]
        first, then = transform(1.3, 0.2, -0.1), transform(0.8, -0.4, 0.3)
        twice = apply_relief(apply_relief(n, m, first), m, then)
        torch.testing.assert_close(apply_relief(n, m, compose_relief(first, then)), twice)

    def test_the_transformed_depth_has_the_transformed_normals(self):
        h = w = 48
        v, u = torch.meshgrid(-torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                              indexing="ij")
        depth = (40 - 0.02 * (u - 24) ** 2 - 0.03 * (v + 24) ** 2)[None, None]
        mask = torch.zeros(1, 1, h, w, dtype=torch.bool)
        mask[..., 6:42, 6:42] = True
        t = transform(1.4, 0.5, -0.3)
        moved = relief_depth(depth, mask, t)
        interior = torch.zeros_like(mask)
        interior[..., 8:40, 8:40] = True
        expected = apply_relief(depth_to_normals(depth, mask), mask, t)
        assert float(normal_metrics(depth_to_normals(moved, mask), expected, interior).mean[0]) < 0.01
        assert bool((moved[~mask] == 0).all())
        # heights keep their mean over the object: the transform turns it about its centroid
        torch.testing.assert_close(moved[mask].mean(), 1.4 * depth[mask].mean())


class TestBestRelief:
    def test_recovers_known_transforms_of_a_batch(self):
        (a, ma), (b, mb) = blob_views(0, 2)
        normals, mask = torch.cat([a, b]), torch.cat([ma, mb])
        applied = ReliefTransform(torch.tensor([0.7, 1.5]), torch.tensor([0.3, -0.5]), torch.tensor([-0.2, 0.1]))
        moved = apply_relief(normals, mask, applied)
        back = apply_relief(moved, mask, best_relief(moved, normals, mask))
        assert float(normal_metrics(moved, normals, mask).median.min()) > 10
        assert float(normal_metrics(back, normals, mask).median.max()) < 0.05
        # the transform found is the inverse of the one applied: scale 1 / s, tilts -t / s
        found = best_relief(moved, normals, mask)
        torch.testing.assert_close(found.scale, 1 / applied.scale, atol=2e-3, rtol=2e-3)
        torch.testing.assert_close(found.tilt_x, -applied.tilt_x / applied.scale, atol=2e-3, rtol=2e-3)

    def test_leaves_a_field_at_its_reference_and_starts_where_asked(self):
        normals, mask = next(blob_views(2, 1))
        same = best_relief(normals, normals, mask)
        torch.testing.assert_close(same.scale, torch.ones(1), atol=1e-4, rtol=0)
        start = transform(2.0, 0.5, 0.5)
        assert float(best_relief(normals, normals, mask, start=start, iterations=1).scale) != 1.0
        converged = best_relief(normals, normals, mask, start=start)
        torch.testing.assert_close(converged.tilt_y, torch.zeros(1), atol=1e-3, rtol=0)

    @pytest.mark.parametrize("bad, message", [
        (dict(iterations=0), "iterations must be an integer >= 1"),
        (dict(start=(1.0, 0.0, 0.0)), "start must be a ReliefTransform of one value per image"),
        (dict(start=ReliefTransform(torch.ones(2), torch.zeros(2), torch.zeros(2))), "start must be a ReliefTransform"),
        (dict(reference=torch.zeros(1, 3, 32, 32)), "normals and reference must have the same batch size"),
        (dict(reference=torch.zeros(1, 3, 64, 64)), "reference must have unit length"),
        (dict(mask=torch.zeros(1, 1, 64, 64, dtype=torch.bool)), "mask"),
    ])
    def test_bad_input_is_one_clear_error(self, bad, message):
        normals, mask = sphere(64, radius=28.0)
        args = {**dict(normals=normals[None], reference=normals[None], mask=mask[None]), **bad}
        with pytest.raises(ValueError, match=message):
            best_relief(args.pop("normals"), args.pop("reference"), args.pop("mask"), **args)


class TestCrop:
    @pytest.mark.parametrize("margin", [1.0, 1.1, 1.25])
    def test_a_sphere_off_centre_fills_the_crop_centred(self, margin):
        normals, mask = sphere(40, radius=19.0)
        big_n = torch.zeros(1, 3, 100, 120)
        big_m = torch.zeros(1, 1, 100, 120, dtype=torch.bool)
        big_n[..., 10:50, 70:110], big_m[..., 10:50, 70:110] = normals, mask
        crop = crop_to_object(big_n, big_m, margin=margin)
        assert crop.shape == (1, 4, 64, 64)
        inside = crop[0, 3].bool()
        # the disc (radius 19 px, 37 px between its outer pixel centres) in a square of
        # 37 * margin + 2 px resampled to 64: a disc of radius 19 * 63 / (37 * margin + 2) px
        assert abs(int(inside.sum()) - np.pi * (19 * 63 / (37 * margin + 2)) ** 2) < 60
        assert torch.equal(inside, inside.flip(-1)) and torch.equal(inside, inside.flip(-2))
        # orientation kept: the right half faces right, the top half up
        assert float(crop[0, 0, 32, 50]) > 0.5 and float(crop[0, 1, 14, 32]) > 0.5
        torch.testing.assert_close(crop[0, :3].norm(dim=0)[inside], torch.ones(int(inside.sum())))

    @pytest.mark.parametrize("margin", [0.9, float("nan"), True])
    def test_a_margin_that_cuts_the_object_is_one_clear_error(self, margin):
        normals, mask = sphere(40, radius=19.0)
        with pytest.raises(ValueError, match="margin must be a finite number >= 1"):
            crop_to_object(normals[None], mask[None], margin=margin)

    @pytest.mark.parametrize("change, message", [
        (lambda n, m: (n[:, :2], m), "normals must have shape"),
        (lambda n, m: (n, m[..., :30]), "same batch size and height/width"),
        (lambda n, m: (n, torch.zeros_like(m)), "mask is empty"),
        (lambda n, m: (n, m.float() * 2), "only 0 and 1"),
    ])
    def test_bad_inputs_are_one_clear_error(self, change, message):
        normals, mask = sphere(40, radius=19.0)
        with pytest.raises(ValueError, match=message):
            crop_to_object(*change(normals[None], mask[None]))

    @pytest.mark.parametrize("size", [1, 2.5, True])
    def test_a_bad_size_is_one_clear_error(self, size):
        normals, mask = sphere(40, radius=19.0)
        with pytest.raises(ValueError, match="size must be an integer >= 2"):
            crop_to_object(normals[None], mask[None], size=size)


class TestTraining:
    def test_seeded_training_is_reproducible_and_learns_to_undo_the_transform(self, tmp_path):
        meshes = [blobby_mesh(s) for s in range(4)]
        views = relief_training_views(meshes, 8, torch.Generator().manual_seed(0), resolution=64, min_pixels=50)
        assert views.shape[1:] == (4, 64, 64) and len(views) == 32
        kwargs = dict(batch_size=16, hidden=16, tilt_std=0.4, log_scale_std=0.0, perturbation=0.0, seed=3)
        short = [fit_relief_net(views, epochs=2, **kwargs) for _ in range(2)]
        assert all(torch.equal(a, b) for a, b in zip(short[0].state_dict().values(), short[1].state_dict().values()))
        net = fit_relief_net(views, epochs=40, **kwargs)
        normals, mask = views[:, :3], views[:, 3:].bool()
        wrong = apply_relief(normals, mask, ReliefTransform(torch.ones(32), torch.full((32,), 0.4), torch.zeros(32)))
        corrected = apply_relief(wrong, mask, predict_relief(wrong, mask, net, passes=1))
        before = normal_metrics(wrong, normals, mask).mean.mean()
        assert float(normal_metrics(corrected, normals, mask).mean.mean()) < 0.7 * float(before)
        # saved and loaded, the network is the same function
        save_relief_net(net, str(tmp_path / "prior.npz"), dict(test=True))
        loaded = load_relief_net(str(tmp_path / "prior.npz"))
        torch.testing.assert_close(loaded(views[:4]), net(views[:4]))

    @pytest.mark.parametrize("content", [None, b"not an npz", "other arrays"])
    def test_load_refuses_a_file_without_weights(self, tmp_path, content):
        path = tmp_path / "prior.npz"
        if content == "other arrays":
            np.savez(path, x=np.zeros(3))
        elif content is not None:
            path.write_bytes(content)
        with pytest.raises(ValueError, match=r"prior.npz' holds no relief prior's weights \(tools/build_relief_prior"):
            load_relief_net(str(path))

    def test_refuses_views_too_small_to_keep(self):
        with pytest.raises(ValueError, match="no view of the 1 meshes covers min_pixels=100000"):
            relief_training_views([blobby_mesh(0)], 2, torch.Generator().manual_seed(0), resolution=64,
                                  min_pixels=100000)

    def test_refuses_too_few_views(self):
        with pytest.raises(ValueError, match="fewer than one batch"):
            fit_relief_net(torch.zeros(3, 4, 64, 64), batch_size=4)
