import hashlib
import os
import time

import numpy as np
import pytest
import torch
from scenes import sphere, with_highlight

import sfs_torch
from sfs_torch.lighting import natural_lightings, render_sh
from sfs_torch.metrics import lmse, normal_metrics
from sfs_torch import pipeline
from sfs_torch.camera import centroid_rotation
from sfs_torch.integrability import depth_to_normals
from sfs_torch.pipeline import PipelineConfig, resolve_config, training_set
from sfs_torch.reflectance_map import refit_lighting
from sfs_torch.refine import RefineConfig, photometric_residual, refine_shape_and_lighting, rim_pixels
from sfs_torch.relief_prior import (ReliefNet, apply_relief, load_relief_net, predict_relief, relief_depth,
                                    save_relief_net)
from sfs_torch.silhouette import coarse_normals

# A small database and forest keep these end-to-end tests to seconds; the accuracy of
# the default configuration is measured in benchmarks/end_to_end.py.
TINY = {
    "database": {"collection": "blobby", "n_shapes": 12, "n_views": 4, "resolution": 64, "samples_per_view": 150, "n_eval_shapes": 2},
    "forest": {"n_trees": 8, "max_depth": 12},
}


def _recording_integrators(monkeypatch) -> list:
    """Every :class:`~sfs_torch.integrability.Integrator` the pipeline runs from now on, in order."""
    from sfs_torch import integrability

    built = []

    class Recording(integrability.Integrator):
        def forward(self, normals, mask, weights=None):
            built.append(self)
            return super().forward(normals, mask, weights)

    monkeypatch.setattr(integrability, "Integrator", Recording)
    return built


@pytest.fixture(scope="module")
def scene():
    normals, mask = sphere()
    sh = natural_lightings(0.7)["grace_cathedral"]
    image = (render_sh(normals[None], sh[None])[0] * mask).clamp(0, 1)
    return normals, mask, sh, image


class TestEstimate:
    def test_sphere_known_and_unknown_lighting(self, scene):
        normals, mask, sh, image = scene
        est = sfs_torch.estimate(image, mask, config=TINY, progress=False)
        assert est.normals.shape == (3, 64, 64) and est.confidence.shape == (1, 64, 64)
        assert float(lmse(est.lighting[None], sh[None])[0]) < 1e-3
        assert float(normal_metrics(est.normals, normals, mask).median) < 5.0
        known = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        assert torch.equal(known.lighting, sh)
        assert float(normal_metrics(known.normals, normals, mask).median) < 5.0

    def test_outputs_are_unit_inside_and_zero_outside(self, scene):
        _, mask, sh, image = scene
        est = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        norms = est.normals.norm(dim=0)
        assert torch.allclose(norms[mask[0]], torch.ones(int(mask.sum())), atol=1e-5)
        assert float(est.normals[:, ~mask[0]].abs().max()) == 0.0
        assert bool((est.confidence[mask] > 0).all()) and float(est.confidence[~mask].abs().max()) == 0.0

    def test_batch_equals_single(self, scene):
        _, mask, sh, image = scene
        flipped = image.flip(-1)
        images, masks = torch.stack([image, flipped]), torch.stack([mask, mask.flip(-1)])
        # up to the photometric refinement the images of a batch are computed exactly as alone
        forest = dict(TINY, refine={"when": "known"})
        batch = sfs_torch.estimate(images, masks, config=forest, progress=False)
        one = sfs_torch.estimate(flipped, mask.flip(-1), config=forest, progress=False)
        assert torch.allclose(batch.normals[1], one.normals, atol=1e-5)
        assert torch.allclose(batch.lighting[1], one.lighting, atol=1e-5)
        # the refinement optimises each image alone too, but 150 L-BFGS steps along a nearly
        # flat valley carry rounding-level differences of its start to a few 0.1 deg (median
        # 0.18, max 0.22-0.76 deg in two environments)
        batch = sfs_torch.estimate(images, masks, config=TINY, progress=False)
        one = sfs_torch.estimate(flipped, mask.flip(-1), config=TINY, progress=False)
        cos = (batch.normals[1] * one.normals).sum(0)[mask.flip(-1)[0]].clamp(-1, 1)
        difference = torch.rad2deg(torch.acos(cos))
        assert float(difference.median()) < 0.5 and float(difference.max()) < 2.0

    def test_numpy_input(self, scene):
        _, mask, sh, image = scene
        est = sfs_torch.estimate(image.permute(1, 2, 0).numpy(), mask[0].numpy(), lighting=sh, config=TINY, progress=False)
        ref = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        assert torch.allclose(est.normals, ref.normals)

    def test_perspective(self, scene):
        _, mask, sh, image = scene
        # the rotation rule of the forest's normals, before any refinement or prior check
        forest_only = dict(TINY, refine={"when": "never"}, keep_prior=False)
        est = sfs_torch.estimate(image, mask, focal=60.0, lighting=sh, config=forest_only, progress=False)
        norms = est.normals.norm(dim=0)[mask[0]]
        assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)
        # centred object: the centroid rotation is the identity, the per-pixel one is not
        ortho = sfs_torch.estimate(image, mask, lighting=sh, config=forest_only, progress=False)
        assert torch.allclose(est.normals, ortho.normals, atol=1e-6)
        per_pixel = dict(forest_only, normal_rotation="pixel")
        tilted = sfs_torch.estimate(image, mask, focal=60.0, lighting=sh, config=per_pixel, progress=False)
        assert not torch.allclose(tilted.normals, ortho.normals, atol=1e-3)

    @pytest.mark.filterwarnings("ignore:the object touches the image border")
    def test_perspective_sphere_known_lighting(self):
        import trimesh

        from sfs_torch.rendering import render_normals

        view = render_normals(trimesh.creation.icosphere(subdivisions=5), torch.eye(3), 64, focal=50.0)
        normals, mask = view.normals, view.mask
        # off-centre crop: the perspective rotation is far from the identity there
        normals, mask = normals[:, 8:, 8:], mask[:, 8:, 8:]
        sh = natural_lightings(0.7)["grace_cathedral"]
        image = (render_sh(normals[None], sh[None])[0] * mask).clamp(0, 1)
        errors = {}
        for rule in ("centroid", "pixel"):
            config = dict(TINY, normal_rotation=rule, keep_prior=False)
            est = sfs_torch.estimate(
                image, mask, focal=50.0, principal_point=(24.0, 24.0), lighting=sh, config=config, progress=False
            )
            errors[rule] = float(normal_metrics(est.normals, normals, mask).median)
        # the colour cue is learnt in the centroid's frame: rotating by it stays consistent
        assert errors["centroid"] < 5.0 and errors["centroid"] < errors["pixel"]

    @pytest.mark.parametrize("method", ["l2", "l1"])
    def test_integration_gives_depth(self, scene, method):
        normals, mask, sh, image = scene
        est = sfs_torch.estimate(image, mask, lighting=sh, integrate=method, config=TINY, progress=False)
        assert est.depth.shape == (1, 64, 64)
        # a sphere's centre is nearer the viewer than its rim
        assert float(est.depth[0, 32, 32]) > float(est.depth[0, 32, 8]) + 5
        assert float(normal_metrics(est.normals, normals, mask).median) < 8.0

    def test_config_ablation(self, scene):
        normals, mask, sh, image = scene
        rgb_only = dict(TINY, features={"rgb": True, "silhouette": False, "texton": False})
        est = sfs_torch.estimate(image, mask, lighting=sh, config=rgb_only, progress=False)
        assert float(normal_metrics(est.normals, normals, mask).median) < 30.0

    def test_exceptions(self, scene):
        _, mask, sh, image = scene
        with pytest.raises(ValueError, match="image"):
            sfs_torch.estimate(image[:2], mask, config=TINY)
        with pytest.raises(ValueError, match="same batch size and height/width"):
            sfs_torch.estimate(image, mask[:, :32], config=TINY)
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            sfs_torch.estimate(image + 2, mask, config=TINY)
        nan = image.clone()
        nan[0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="image contains 1 NaN"):
            sfs_torch.estimate(nan, mask, config=TINY)
        with pytest.raises(ValueError, match="mask is empty"):
            sfs_torch.estimate(image, torch.zeros_like(mask), config=TINY)
        with pytest.raises(ValueError, match="whole image"):
            sfs_torch.estimate(image, torch.ones_like(mask), config=TINY)
        with pytest.raises(ValueError, match="integrate"):
            sfs_torch.estimate(image, mask, integrate="l3", config=TINY)
        with pytest.raises(ValueError, match="lighting"):
            sfs_torch.estimate(image, mask, lighting=torch.zeros(3, 4), config=TINY)
        with pytest.raises(ValueError, match="focal"):
            sfs_torch.estimate(image, mask, focal=-5.0, config=TINY)
        with pytest.raises(ValueError, match="no feature"):
            sfs_torch.estimate(image, mask, lighting=sh, config=dict(TINY, features={"rgb": False, "silhouette": False, "texton": False}))


class TestTrainingSet:
    def test_centre_colour_is_the_shaded_centre_normal(self):
        from sfs_torch.geometry_db import DatabaseConfig, load_database
        from sfs_torch.pipeline import FeatureConfig
        from sfs_torch.texton import TextonConfig

        db = load_database(DatabaseConfig(**TINY["database"]), progress=False)
        sh = natural_lightings(0.5)["uffizi_gallery"]
        data = training_set(db, sh, FeatureConfig(), TextonConfig(), noise_sigma=0.0, seed=0)
        shaded = render_sh(data.normals[:, :, None, None], sh[None].expand(len(data.normals), -1, -1))[:, :, 0, 0]
        assert torch.allclose(data.features[:, :3], shaded.clamp(0, 1), atol=1e-6)
        assert torch.equal(data.features[:, 3:6], db.silhouette)
        assert data.features.shape[1] == 3 + 3 + 17


    def test_brightness_jitter_scales_whole_patches(self):
        from sfs_torch.geometry_db import DatabaseConfig, load_database
        from sfs_torch.pipeline import FeatureConfig
        from sfs_torch.texton import TextonConfig

        db = load_database(DatabaseConfig(**TINY["database"]), progress=False)
        sh = natural_lightings(0.3)["uffizi_gallery"]
        plain = training_set(db, sh, FeatureConfig(texton=False), TextonConfig(), noise_sigma=0.0, seed=0)
        jittered = training_set(
            db, sh, FeatureConfig(texton=False), TextonConfig(), noise_sigma=0.0, seed=0, brightness_jitter=0.3
        )
        ratio = jittered.features[:, :3] / plain.features[:, :3]
        unclipped = (jittered.features[:, :3] < 1).all(1) & (plain.features[:, :3] > 1e-3).all(1)
        # one gain per patch, shared by the three channels, log-normal with std 0.3
        assert torch.allclose(ratio[unclipped], ratio[unclipped][:, :1].expand(-1, 3), rtol=1e-4)
        assert abs(float(ratio[unclipped][:, 0].log().std()) - 0.3) < 0.03


class TestJitterOnlyForEstimatedLighting:
    def test_given_lighting_ignores_jitter(self, scene):
        _, mask, sh, image = scene
        a = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        b = sfs_torch.estimate(image, mask, lighting=sh, config=dict(TINY, training={"brightness_jitter": 0.0, "colour_jitter": 0.0}), progress=False)
        assert torch.equal(a.normals, b.normals)


class TestLightingRefinement:
    # the refit rounds alone: on this sphere the prior check would replace their result, and
    # the photometric refinement would refine it further
    ROUNDS = dict(TINY, keep_prior=False, refine={"when": "known"})

    def test_refined_lighting_is_fitted_to_the_unrefined_normals(self, scene):
        _, mask, _, image = scene
        plain = sfs_torch.estimate(image, mask, config=dict(self.ROUNDS, refine_rounds=0), progress=False)
        refined = sfs_torch.estimate(image, mask, config=self.ROUNDS, progress=False)
        expected = refit_lighting(image[None], mask[None], plain.normals[None])[0]
        assert torch.allclose(refined.lighting, expected, atol=1e-5)
        assert not torch.allclose(refined.lighting, plain.lighting, atol=1e-3)

    def test_a_refit_that_explains_the_image_worse_is_dropped(self, scene, monkeypatch):
        _, mask, _, image = scene
        plain = sfs_torch.estimate(image, mask, config=dict(self.ROUNDS, refine_rounds=0), progress=False)
        # a refit gone wrong: three times too bright
        monkeypatch.setattr("sfs_torch.pipeline.refit_lighting", lambda im, m, n, valid: 3 * refit_lighting(im, m, n))
        guarded = sfs_torch.estimate(image, mask, config=self.ROUNDS, progress=False)
        assert torch.equal(guarded.lighting, plain.lighting)
        assert torch.equal(guarded.normals, plain.normals) and torch.equal(guarded.confidence, plain.confidence)

    def test_given_lighting_is_not_refined(self, scene):
        _, mask, sh, image = scene
        config = dict(TINY, refine_rounds=2)
        est = sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)
        assert torch.equal(est.lighting, sh)

    def test_negative_rounds_are_rejected(self, scene):
        _, mask, _, image = scene
        with pytest.raises(ValueError, match="refine_rounds"):
            sfs_torch.estimate(image, mask, config=dict(TINY, refine_rounds=-1), progress=False)


class TestKeepPrior:
    def test_a_sphere_keeps_its_silhouette_prior(self, scene):
        # Eq. 10 is exact for a sphere: its coarse normals with their own lighting explain the
        # image better than any forest, and the call returns them
        normals, mask, sh, image = scene
        forest = dict(TINY, refine={"when": "known"})  # the check itself, before the photometric refinement
        on = sfs_torch.estimate(image, mask, config=dict(forest, keep_prior=True), progress=False)
        off = sfs_torch.estimate(image, mask, config=dict(forest, keep_prior=False), progress=False)
        error_on = float(normal_metrics(on.normals[None], normals[None], mask[None]).median[0])
        error_off = float(normal_metrics(off.normals[None], normals[None], mask[None]).median[0])
        assert error_on < 1.5 < error_off
        assert torch.allclose(on.normals, coarse_normals(mask[None])[0], atol=1e-6)
        refit = refit_lighting(image[None], mask[None], coarse_normals(mask[None]))[0]
        assert torch.allclose(on.lighting, refit, atol=1e-5)
        kappa = on.confidence[mask]
        assert torch.allclose(kappa, kappa[0].expand_as(kappa))  # no per-pixel confidence for the prior

    def test_a_kept_prior_is_not_refined(self, scene):
        # the default refines an estimated lighting jointly with a surface; a kept prior is
        # Eq. 10's exact answer for a sphere, which that refinement would only move away
        normals, mask, sh, image = scene
        kept = sfs_torch.estimate(image, mask, config=TINY, progress=False)
        moved = sfs_torch.estimate(image, mask, config=dict(TINY, refine={"skip_prior": False}), progress=False)
        coarse = coarse_normals(mask[None])[0]
        assert torch.allclose(kept.normals, coarse, atol=1e-6)
        assert torch.allclose(kept.lighting, refit_lighting(image[None], mask[None], coarse[None])[0], atol=1e-5)
        assert not torch.allclose(moved.normals, coarse, atol=1e-3)
        # its depth is still given: the L2 integration of those normals
        interior = mask & ~rim_pixels(mask[None])[0]
        of_depth = depth_to_normals(kept.depth[None], mask[None])[0]
        assert float(normal_metrics(of_depth[None], coarse[None], interior[None]).median[0]) < 1.0

    def test_a_glossy_sphere_is_checked_with_the_highlight_rule_after_the_refinement(self, monkeypatch):
        # a specular highlight: the refined surface bends to explain it, so under a plain
        # residual it fits better than Eq. 10's exact sphere and is returned. With the rule
        # (prior_check_highlight) the check gets the option, and where it says so the call
        # returns the prior. What the rule decides is tested on controlled fields in
        # test_refine: on this 64 px sphere and the tests' small forest the decision is a
        # coin toss (measured: the prior's score 0.01383 against the refined surface's
        # 0.01384 on an Intel Xeon, the refined surface lower on an AMD EPYC), see
        # docs/robustness.md
        normals, mask = sphere()
        sh = natural_lightings(0.8)["uffizi_gallery"]
        image, _ = with_highlight(render_sh(normals[None], sh[None])[0] * mask, normals, mask, sh)
        # the check before the refinement off, so the forest's surface is refined and checked
        monkeypatch.setattr(pipeline, "_better_prior", lambda *a, **k: None)
        coarse = coarse_normals(mask[None])[0]
        coarse_error = float(normal_metrics(coarse[None], normals[None], mask[None]).median[0])
        plain = sfs_torch.estimate(image, mask, config=dict(TINY, prior_check_highlight=None), progress=False)
        assert float(normal_metrics(plain.normals[None], normals[None], mask[None]).median[0]) > coarse_error + 2.0

        highlights = []

        def prior_wins(*args):
            highlights.append(args[-1].prior_check_highlight)
            return torch.ones_like(args[3])

        monkeypatch.setattr(pipeline, "_prior_explains_better", prior_wins)
        est = sfs_torch.estimate(image, mask, config=TINY, progress=False)
        assert highlights == [PipelineConfig.prior_check_highlight]
        assert torch.allclose(est.normals, coarse, atol=1e-6)
        assert torch.allclose(est.lighting, refit_lighting(image[None], mask[None], coarse[None])[0], atol=1e-5)

    def test_a_batch_refines_only_the_items_without_a_kept_prior(self, scene, monkeypatch):
        normals, mask, sh, image = scene
        checked = []

        def first_only(*args, **kwargs):
            checked.append(None)
            return better_prior(*args, **kwargs) if len(checked) == 1 else None

        better_prior = pipeline._better_prior
        monkeypatch.setattr(pipeline, "_better_prior", first_only)
        # and no return to the prior after the refinement, which would also take the second sphere back
        monkeypatch.setattr(pipeline, "_prior_explains_better", lambda image, *a: torch.zeros(len(image), dtype=torch.bool))
        # without the pixel refinement, whose normals are no longer the surface's
        config = dict(TINY, pixel_refinement=False)
        both = sfs_torch.estimate(torch.stack([image, image]), torch.stack([mask, mask]), config=config, progress=False)
        monkeypatch.undo()
        forest = sfs_torch.estimate(image, mask, config=dict(config, keep_prior=False), progress=False)
        assert torch.allclose(both.normals[0], coarse_normals(mask[None])[0], atol=1e-6)
        assert float(normal_metrics(both.normals[1:], forest.normals[None], mask[None]).median[0]) < 0.5
        assert float(lmse(both.lighting[1:], forest.lighting[None])[0]) < 1e-5
        interior = (mask & ~rim_pixels(mask[None])[0])[None]
        for depth, expected in zip(both.depth, (coarse_normals(mask[None])[0], both.normals[1])):
            of_depth = depth_to_normals(depth[None], mask[None])
            assert float(normal_metrics(of_depth, expected[None], interior).median[0]) < 1.0

    def test_a_refined_surface_worse_than_the_prior_is_replaced_by_it(self, scene, monkeypatch):
        # the prior check before the refinement missed the prior (patched away here), and the
        # refinement returned a bent surface: under their own best smooth shadings Eq. 10's
        # normals explain the image better, and the call returns them
        normals, mask, sh, image = scene
        coarse = coarse_normals(mask[None])
        monkeypatch.setattr(pipeline, "_better_prior", lambda *a, **k: None)
        refine = pipeline._refine

        def bent(image, mask, normals, sh, confidence, skip, *args):
            depth, out, light = refine(image, mask, normals, sh, confidence, skip, *args)
            if skip is not None and bool(skip.all()):  # the prior's integration
                return depth, out, light
            c = torch.linspace(-1, 1, mask.shape[-1])
            wave = torch.stack([0.3 * torch.sin(4 * c)[:, None].expand(-1, len(c)), torch.zeros(len(c), len(c)),
                                torch.zeros(len(c), len(c))])
            return depth, torch.nn.functional.normalize(coarse + wave, dim=1) * mask, light

        monkeypatch.setattr(pipeline, "_refine", bent)
        # without the final round, which would start again from a forest and undo the bend, and
        # without the pixel refinement, which would smooth it
        config = dict(TINY, final_round=False, pixel_refinement=False)
        est = sfs_torch.estimate(image, mask, config=config, progress=False)
        assert torch.allclose(est.normals, coarse[0], atol=1e-6)
        assert torch.allclose(est.lighting, refit_lighting(image[None], mask[None], coarse)[0], atol=1e-5)
        kappa = est.confidence[mask]
        assert torch.allclose(kappa, kappa[0].expand_as(kappa))
        interior = (mask & ~rim_pixels(mask[None])[0])[None]
        assert float(normal_metrics(depth_to_normals(est.depth[None], mask[None]), coarse, interior).median[0]) < 1.0
        # without keep_prior the bent surface stays
        off = sfs_torch.estimate(image, mask, config=dict(config, keep_prior=False), progress=False)
        assert float(normal_metrics(off.normals[None], coarse, mask[None]).median[0]) > 5.0

    def test_a_given_lighting_is_kept_with_the_prior(self, scene):
        normals, mask, sh, image = scene
        est = sfs_torch.estimate(image, mask, lighting=sh, progress=False,
                                 config=dict(TINY, keep_prior=True, refine={"when": "never"}))
        assert torch.equal(est.lighting, sh)


@pytest.fixture(scope="module")
def ellipsoid():
    """An ellipsoid's normals, mask and exact image, each with a batch axis: Eq. 10 is off on it."""
    c = torch.arange(64, dtype=torch.float32) + 0.5 - 32
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    x, y = xx / 26.0, -yy / 16.0
    r2 = x * x + y * y
    mask = (r2 < 1)[None]
    truth = torch.nn.functional.normalize(torch.stack([20 * x / 26, 20 * y / 16, torch.sqrt((1 - r2).clamp_min(0))]),
                                          dim=0) * mask
    sh = natural_lightings(0.7)["grace_cathedral"]
    image = (render_sh(truth[None], sh[None])[0] * mask).clamp(0, 1)
    return truth[None], mask[None], image[None]


class TestPriorCheckTie:
    """The near-tie rule of the prior check after the refinement (``prior_check_tie``), on
    an ellipsoid whose Eq. 10 prior is off. The refined surface lies between the prior and
    the truth; the prior's own refinement is replaced by a stand-in that returns a set field."""

    FOCAL = 300.0

    def _check(self, monkeypatch, ellipsoid, towards_truth, prior_refined_to_truth, focal=FOCAL, **config):
        truth, mask, image = ellipsoid
        coarse = coarse_normals(mask, focal=focal)
        refined = torch.nn.functional.normalize(coarse + towards_truth * (truth - coarse), dim=1) * mask
        calls = []

        def prior_refinement(image, mask, normals, sh, confidence, skip, *args):
            calls.append((normals.clone(), confidence.clone(), skip))
            return None, truth if prior_refined_to_truth else normals, sh

        monkeypatch.setattr(pipeline, "_refine", prior_refinement)
        cfg = resolve_config(config)
        back = pipeline._prior_explains_better(image, mask, refined, torch.ones(1, dtype=torch.bool), focal, None, cfg)
        return bool(back[0]), calls, coarse

    def test_a_near_tie_goes_to_the_prior_when_its_refinement_explains_the_image_better(self, monkeypatch, ellipsoid):
        # a fifth of the way to the truth: 0.74x the prior's residual, so no plain win for the prior
        back, calls, coarse = self._check(monkeypatch, ellipsoid, 0.2, True)
        assert back
        (start, confidence, skip), = calls
        torch.testing.assert_close(start, coarse)  # the prior refined from Eq. 10's normals
        mask = ellipsoid[1]
        torch.testing.assert_close(confidence, mask.float())  # with a uniform confidence
        assert skip is None  # refined, none skipped

    def test_a_near_tie_stays_refined_when_the_prior_refines_no_better(self, monkeypatch, ellipsoid):
        back, calls, _ = self._check(monkeypatch, ellipsoid, 0.2, False)
        assert not back and len(calls) == 1

    @pytest.mark.parametrize("case", ["clear win", "rule off", "orthographic"])
    def test_no_second_refinement_outside_a_perspective_near_tie(self, monkeypatch, ellipsoid, case):
        # 0.7 of the way: 0.08x the prior's residual, a clear win for the refined surface
        kwargs = {"clear win": dict(towards_truth=0.7), "rule off": dict(towards_truth=0.2, prior_check_tie=None),
                  "orthographic": dict(towards_truth=0.2, focal=None)}[case]
        back, calls, _ = self._check(monkeypatch, ellipsoid, prior_refined_to_truth=True, **kwargs)
        assert not back and calls == []


# the refined surface as it is (and its normals, not refined per pixel after it)
NO_RELIEF = {"relief_scale": 1.0, "relief_slope_power": 0, "relief_prior_passes": 0, "pixel_refinement": False}
DEEPER = {"relief_scale": 1.5, "relief_slope_power": 0, "relief_prior_passes": 0}
# the relief stage's own surface: without the refinements after it (TestReliefRefinements, TestPixelRefinement)
RELIEF_STAGE = dict(TINY, keep_prior=False, relief_refinements=0, pixel_refinement=False)


class TestFinalRound:
    def test_it_refines_an_unjittered_forest_trained_for_the_refined_lighting(self, scene, monkeypatch):
        # keep_prior=false: the sphere's prior would be kept, and a kept prior is not refined
        normals, mask, sh, image = scene
        rounds, refinements = [], []
        forest_rounds, refine = pipeline._forest_rounds, pipeline.refine_shape_and_lighting

        def recording_rounds(image, mask, rows, sh, db, cfg, *args, **kwargs):
            rounds.append((sh.clone(), cfg.training.brightness_jitter, cfg.training.colour_jitter, cfg.refine_rounds))
            return forest_rounds(image, mask, rows, sh, db, cfg, *args, **kwargs)

        def recording_refine(*args, **kwargs):
            refinements.append(refine(*args, **kwargs))
            return refinements[-1]

        monkeypatch.setattr(pipeline, "_forest_rounds", recording_rounds)
        monkeypatch.setattr(pipeline, "refine_shape_and_lighting", recording_refine)
        est = sfs_torch.estimate(image, mask, config=dict(TINY, keep_prior=False, **NO_RELIEF), progress=False)
        assert len(rounds) == 2 and len(refinements) == 2
        (_, jitter, colour, refits), (last_sh, *final) = rounds
        assert jitter == 0.3 and colour == 0.05 and refits == 1  # the call's own forests
        assert final == [0.0, 0.0, 0]  # unjittered, as for a given lighting, no refit round
        torch.testing.assert_close(last_sh, refit_lighting(image[None], mask[None], refinements[0].normals)[0])
        torch.testing.assert_close(est.normals, refinements[1].normals[0])
        torch.testing.assert_close(est.lighting, refinements[1].lighting[0])
        torch.testing.assert_close(est.depth, refinements[1].depth[0])
        assert "final round" in est.timings
        rounds.clear()
        sfs_torch.estimate(image, mask, config=dict(TINY, keep_prior=False, final_round_jitter=0.5, **NO_RELIEF),
                           progress=False)
        assert [r[1:] for r in rounds] == [(0.3, 0.05, 1), (0.5 * 0.3, 0.5 * 0.05, 0)]  # that fraction of the jitter
        rounds.clear(), refinements.clear()
        off = sfs_torch.estimate(image, mask, config=dict(TINY, keep_prior=False, final_round=False, **NO_RELIEF),
                                 progress=False)
        assert len(rounds) == 1 and len(refinements) == 1
        torch.testing.assert_close(off.normals, refinements[0].normals[0])


def _judged_perspective_relief(monkeypatch, refined: torch.Tensor, before: torch.Tensor) -> list:
    """Make the perspective relief stage read these photometric residuals, ``(B,)`` each, of
    its refined surfaces and of the surfaces before it; returns the record of its calls."""
    stage, residual, calls = pipeline._perspective_relief, pipeline.photometric_residual, []

    def in_stage(*args):
        calls.append("stage")
        return stage(*args)

    def judged(normals, *args):  # the stage asks for its refined surfaces' residuals, then for those before
        if calls not in (["stage"], ["stage", "refined"]):
            return residual(normals, *args)
        calls.append("before" if "refined" in calls else "refined")
        return before if calls[-1] == "before" else refined

    monkeypatch.setattr(pipeline, "_perspective_relief", in_stage)
    monkeypatch.setattr(pipeline, "photometric_residual", judged)
    return calls


class TestReliefScale:
    def test_an_estimated_orthographic_surface_is_deepened_and_its_lighting_refitted(self, scene):
        _, mask, _, image = scene
        config = RELIEF_STAGE
        flat = sfs_torch.estimate(image, mask, config=dict(config, **NO_RELIEF), progress=False)
        deep = sfs_torch.estimate(image, mask, config=dict(config, **DEEPER), progress=False)
        torch.testing.assert_close(deep.depth, 1.5 * flat.depth)
        n = flat.normals
        expected = torch.nn.functional.normalize(torch.stack([1.5 * n[0], 1.5 * n[1], n[2]]), dim=0) * mask
        torch.testing.assert_close(deep.normals, expected)
        torch.testing.assert_close(deep.lighting, refit_lighting(image[None], mask[None], expected[None])[0])
        # the surface of a scaled depth has the scaled normals: the outputs stay one surface
        interior = (mask & ~rim_pixels(mask[None])[0])[None]
        from_depth = depth_to_normals(deep.depth[None], mask[None])
        assert float(normal_metrics(from_depth, deep.normals[None], interior).median[0]) < 1.0
        assert "relief scale and prior" in deep.timings and "relief scale and prior" not in flat.timings

    def test_the_scale_grows_with_the_surfaces_own_median_slope(self, scene):
        _, mask, _, image = scene
        config = RELIEF_STAGE
        flat = sfs_torch.estimate(image, mask, config=dict(config, **NO_RELIEF), progress=False)
        deep = sfs_torch.estimate(image, mask, config=dict(config, relief_scale=1.2, relief_slope_power=0.5,
                                                           relief_prior_passes=0), progress=False)
        n = flat.normals[:, mask[0]]
        slope = float((n[:2].norm(dim=0) / n[2]).median())
        assert 0.2 < slope < 2.0  # a rim pixel's n_z near 0 does not move the median
        factor = 1.2 * (slope / 0.8) ** 0.5
        torch.testing.assert_close(deep.depth, factor * flat.depth)
        n = flat.normals
        expected = torch.nn.functional.normalize(torch.stack([factor * n[0], factor * n[1], n[2]]), dim=0) * mask
        torch.testing.assert_close(deep.normals, expected)
        # a steeper surface of the same image is deepened more: its own slope sets the factor
        steep = sfs_torch.estimate(image, mask, config=dict(config, relief_scale=1.2, relief_slope_power=1.0,
                                                            relief_prior_passes=0), progress=False)
        assert (float(steep.depth.abs().max()) > float(deep.depth.abs().max())) == (slope > 0.8)

    # by default the prior alone corrects the surface as refined, with no scale before it
    @pytest.mark.parametrize("start, overrides", [(DEEPER, dict(DEEPER, relief_prior_passes=2)), (NO_RELIEF, {})],
                             ids=["after a scale", "the default"])
    def test_the_learnt_prior_corrects_the_surface_by_its_transform(self, scene, start, overrides):
        _, mask, _, image = scene
        config = RELIEF_STAGE
        scaled = sfs_torch.estimate(image, mask, config=dict(config, **start), progress=False)
        corrected = sfs_torch.estimate(image, mask, config=dict(config, **overrides), progress=False)
        learnt = predict_relief(scaled.normals, mask, load_relief_net(), passes=2)
        expected = apply_relief(scaled.normals[None], mask[None], learnt)
        torch.testing.assert_close(corrected.normals, expected[0])
        torch.testing.assert_close(corrected.depth, relief_depth(scaled.depth[None], mask[None], learnt)[0])
        torch.testing.assert_close(corrected.lighting, refit_lighting(image[None], mask[None], expected)[0])
        assert float(normal_metrics(corrected.normals[None], scaled.normals[None], mask[None]).median[0]) > 0.1

    def test_other_weights_replace_the_shipped_prior(self, scene, tmp_path):
        _, mask, _, image = scene
        config = RELIEF_STAGE
        identity = tmp_path / "identity.npz"  # an untrained network returns the identity transform
        save_relief_net(ReliefNet(), str(identity), {})
        scaled = sfs_torch.estimate(image, mask, config=dict(config, **DEEPER), progress=False)
        other = sfs_torch.estimate(image, mask, progress=False, config=dict(
            config, **dict(DEEPER, relief_prior_passes=2, relief_prior_weights=str(identity))))
        torch.testing.assert_close(other.normals, scaled.normals)
        torch.testing.assert_close(other.depth, scaled.depth)

    @pytest.mark.parametrize("explains_better", [True, False], ids=["kept", "refused"])
    def test_a_perspective_surface_is_corrected_in_its_centroids_frame_and_refined(self, scene, monkeypatch,
                                                                                   explains_better):
        _, mask, _, image = scene
        camera = {"focal": 60.0, "principal_point": (12.0, 20.0)}  # the object well off the optical axis
        config = RELIEF_STAGE
        before = sfs_torch.estimate(image, mask, config=dict(config, **NO_RELIEF), progress=False, **camera)
        refinements = []
        refine = pipeline.refine_shape_and_lighting

        def recording_refine(*args, **kwargs):
            refinements.append((args, refine(*args, **kwargs)))
            return refinements[-1][1]

        monkeypatch.setattr(pipeline, "refine_shape_and_lighting", recording_refine)
        calls = _judged_perspective_relief(monkeypatch, torch.tensor([0.0 if explains_better else 1.0]),
                                           torch.tensor([0.5]))
        after = sfs_torch.estimate(image, mask, config=config, progress=False, **camera)
        assert len(refinements) == 3 and calls == ["stage", "refined", "before"]  # the last is the stage's
        (_, _, start_normals, start_sh), last = refinements[-1]
        rotation = centroid_rotation(mask, **camera)
        assert float(torch.linalg.matrix_norm(rotation - torch.eye(3))) > 0.3
        local = torch.einsum("ji,jhw->ihw", rotation, before.normals)  # the centroid's frame
        learnt = predict_relief(local, mask, load_relief_net(), passes=2)
        turned = torch.einsum("ij,bjhw->bihw", rotation, apply_relief(local[None], mask[None], learnt))
        torch.testing.assert_close(start_normals, turned)
        torch.testing.assert_close(start_sh, refit_lighting(image[None], mask[None], turned))
        assert float(normal_metrics(last.normals, before.normals[None], mask[None]).median[0]) > 0.1
        kept = (last.normals[0], last.depth[0], last.lighting[0]) if explains_better else (
            before.normals, before.depth, before.lighting)
        for got, expected in zip((after.normals, after.depth, after.lighting), kept):
            torch.testing.assert_close(got, expected)

    def test_each_perspective_image_of_a_batch_keeps_or_refuses_its_own_correction(self, scene, monkeypatch):
        _, mask, _, image = scene
        images, masks = torch.stack([image, image.flip(-1)]), torch.stack([mask, mask.flip(-1)])
        config = RELIEF_STAGE
        before = sfs_torch.estimate(images, masks, focal=60.0, config=dict(config, **NO_RELIEF), progress=False)
        calls = _judged_perspective_relief(monkeypatch, torch.tensor([0.0, 1.0]), torch.tensor([0.5, 0.5]))
        after = sfs_torch.estimate(images, masks, focal=60.0, config=config, progress=False)
        assert calls == ["stage", "refined", "before"]
        assert float(normal_metrics(after.normals[:1], before.normals[:1], masks[:1]).median[0]) > 0.1  # kept
        for got, expected in zip((after.normals, after.depth, after.lighting), (before.normals, before.depth,
                                                                                 before.lighting)):
            torch.testing.assert_close(got[1], expected[1])  # refused: the surface before the stage

    @pytest.mark.parametrize("case", ["known lighting", "kept prior"])
    def test_left_alone(self, scene, case):
        _, mask, sh, image = scene
        kwargs = {"known lighting": {"lighting": sh}, "kept prior": {}}[case]
        # the sphere's silhouette prior is kept (TestKeepPrior), so nothing is deepened
        config = dict(TINY, keep_prior=case == "kept prior")
        flat = sfs_torch.estimate(image, mask, config=dict(config, **NO_RELIEF), progress=False, **kwargs)
        deep = sfs_torch.estimate(image, mask, config=dict(config, **dict(DEEPER, relief_prior_passes=2)),
                                  progress=False, **kwargs)
        assert torch.equal(deep.normals, flat.normals) and torch.equal(deep.lighting, flat.lighting)


class TestReliefRounds:
    def test_each_round_starts_from_the_last_corrected_surface_and_the_surfaces_are_averaged(self, scene, monkeypatch):
        _, mask, _, image = scene
        config = RELIEF_STAGE
        one = sfs_torch.estimate(image, mask, config=config, progress=False)  # one round by default
        corrected, starts = [], []
        scaled_relief, final_round = pipeline._scaled_relief, pipeline._final_round

        def recording_relief(*args):
            corrected.append(scaled_relief(*args))
            return corrected[-1]

        def recording_final(image, mask, normals, *args):
            starts.append(normals.clone())
            return final_round(image, mask, normals, *args)

        monkeypatch.setattr(pipeline, "_scaled_relief", recording_relief)
        monkeypatch.setattr(pipeline, "_final_round", recording_final)
        two = sfs_torch.estimate(image, mask, config=dict(config, relief_rounds=2), progress=False)
        assert len(corrected) == 2 and len(starts) == 2
        (first_depth, first, _), (second_depth, second, _) = corrected
        torch.testing.assert_close(first[0], one.normals)  # the first round is the one-round estimate
        torch.testing.assert_close(starts[1], first)  # the second starts from its corrected surface
        assert float(normal_metrics(second, first, mask[None]).median[0]) > 0.1
        torch.testing.assert_close(two.depth, (first_depth[0] + second_depth[0]) / 2)
        slopes = (first[:, :2] / first[:, 2:] + second[:, :2] / second[:, 2:]) / 2
        expected = torch.nn.functional.normalize(torch.cat([slopes, torch.ones_like(slopes[:, :1])], 1), dim=1)
        expected = torch.where(mask, expected, 0.0)  # 0 / 0 off the object
        torch.testing.assert_close(two.normals, expected[0])
        torch.testing.assert_close(two.lighting, refit_lighting(image[None], mask[None], expected)[0])
        torch.testing.assert_close(two.confidence, one.confidence)
        # the mean of the slopes is the mean surface's: depth and normals stay one surface
        interior = (mask & ~rim_pixels(mask[None])[0])[None]
        from_depth = depth_to_normals(two.depth[None], mask[None])
        assert float(normal_metrics(from_depth, two.normals[None], interior).median[0]) < 1.0
        assert "relief rounds" in two.timings and "relief rounds" not in one.timings


class TestReliefRefinements:
    @pytest.mark.parametrize("prior_after", [False, True])
    def test_the_refinement_starts_from_the_corrected_surface_in_image_sides(self, scene, monkeypatch, prior_after):
        _, mask, _, image = scene
        config = dict(TINY, keep_prior=False, pixel_refinement=False)
        without = sfs_torch.estimate(image, mask, config=RELIEF_STAGE, progress=False)
        corrected, refinements = [], []
        scaled_relief, refine = pipeline._scaled_relief, pipeline._refine

        def recording_relief(*args):
            corrected.append(scaled_relief(*args))
            return corrected[-1]

        def recording_refine(image, mask, normals, sh, confidence, skip, cfg, *args):
            start = (normals.clone(), sh.clone(), confidence.clone(), cfg.refine.height_unit)
            result = refine(image, mask, normals, sh, confidence, skip, cfg, *args)
            refinements.append((*start, result))
            return result

        monkeypatch.setattr(pipeline, "_scaled_relief", recording_relief)
        monkeypatch.setattr(pipeline, "_refine", recording_refine)
        once = sfs_torch.estimate(image, mask, config=dict(config, relief_refinement_prior=prior_after),
                                  progress=False)  # once by default
        # the joint refinement, the final round's, the one after the prior (and the prior again after it)
        assert len(corrected) == 1 + prior_after and len(refinements) == 3
        _, first, first_sh = corrected[0]
        torch.testing.assert_close(first[0], without.normals)  # the prior's surface of relief_refinements=0
        start, start_sh, confidence, _, result = refinements[2]
        assert [r[3] for r in refinements] == [1.0, 1.0, 64.0]  # the last one's height in image sides (64 px)
        torch.testing.assert_close(start, first)  # refined from it, pulled towards it
        torch.testing.assert_close(start_sh, first_sh)
        torch.testing.assert_close(confidence[0], once.confidence)
        # the refined surface is the estimate, or the prior corrects it again
        last = corrected[1] if prior_after else result
        for returned, expected in zip((once.depth, once.normals, once.lighting), last):
            torch.testing.assert_close(returned, expected[0])
        assert float(normal_metrics(once.normals[None], without.normals[None], mask[None]).median[0]) > 0.1
        assert "refinement after the relief prior" in once.timings
        assert "refinement after the relief prior" not in without.timings

    def test_not_run_on_images_the_prior_check_returns_to_the_prior(self, scene, monkeypatch):
        _, mask, _, image = scene
        checked = []

        def prior_always_better(image, mask, normals, among, *args):
            checked.append(normals.clone())
            return among.clone()

        monkeypatch.setattr(pipeline, "_better_prior", lambda *args, **kwargs: None)  # the first check keeps none
        monkeypatch.setattr(pipeline, "_prior_explains_better", prior_always_better)
        est = sfs_torch.estimate(image, mask, config=TINY, progress=False)
        without = sfs_torch.estimate(image, mask, config=RELIEF_STAGE, progress=False)
        # the check weighed the prior against the surface as the prior corrected it, and kept the prior
        torch.testing.assert_close(checked[0][0], without.normals)
        torch.testing.assert_close(est.normals, coarse_normals(mask[None])[0] * mask)
        assert "relief scale and prior" in est.timings and "refinement after the relief prior" not in est.timings


class TestPixelRefinement:
    def test_the_estimate_is_refined_per_pixel_under_its_own_lighting(self, scene):
        # keep_prior=false: the sphere's prior would be kept, and a kept prior is not refined
        _, mask, _, image = scene
        config = dict(TINY, keep_prior=False)
        off = sfs_torch.estimate(image, mask, config=dict(config, pixel_refinement=False), progress=False)
        on = sfs_torch.estimate(image, mask, config=config, progress=False)  # on by default
        expected = refine_shape_and_lighting(image[None], mask[None], off.normals[None], off.lighting[None],
                                             confidence=off.confidence[None], config=RefineConfig(model="pixel"))
        torch.testing.assert_close(on.normals, expected.normals[0])
        assert torch.equal(on.lighting, off.lighting) and torch.equal(on.depth, off.depth)
        assert torch.equal(on.confidence, off.confidence)
        # it fits the image under the estimate's lighting closer than the surface does
        residual = [float(photometric_residual(e.normals[None], e.lighting[None], image[None], mask[None])[0])
                    for e in (on, off)]
        assert residual[0] < 0.8 * residual[1]
        assert "pixel refinement" in on.timings and "pixel refinement" not in off.timings

    def test_an_image_at_its_silhouette_prior_stays_there(self, scene):
        _, mask, _, image = scene
        est = sfs_torch.estimate(image, mask, config=TINY, progress=False)  # the sphere keeps its prior
        torch.testing.assert_close(est.normals, coarse_normals(mask[None])[0] * mask)
        assert "pixel refinement" not in est.timings

    def test_a_given_lighting_is_refined_once(self, scene):
        _, mask, sh, image = scene
        on, off = (sfs_torch.estimate(image, mask, lighting=sh, config=dict(TINY, pixel_refinement=flag),
                                      progress=False) for flag in (True, False))
        assert torch.equal(on.normals, off.normals) and "pixel refinement" not in on.timings


@pytest.mark.parametrize("option, stage", [({"relief_rounds": 2}, "relief rounds"),
                                           ({"relief_refinements": 1}, "refinement after the relief prior")])
@pytest.mark.parametrize("case", ["known lighting", "perspective"])
def test_relief_options_leave_alone_what_the_relief_stage_does_not_run_on(scene, case, option, stage):
    _, mask, sh, image = scene
    kwargs = {"known lighting": {"lighting": sh}, "perspective": {"focal": 300.0}}[case]
    config = RELIEF_STAGE
    without = sfs_torch.estimate(image, mask, config=config, progress=False, **kwargs)
    with_option = sfs_torch.estimate(image, mask, config=dict(config, **option), progress=False, **kwargs)
    assert torch.equal(with_option.normals, without.normals) and stage not in with_option.timings


class TestForestCache:
    def test_keeps_the_most_recently_used(self, scene, tmp_path, monkeypatch):
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        _, mask, sh, image = scene
        config = dict(TINY, training={"max_cached_forests": 2})
        forests = tmp_path / "forests"
        first = sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)
        (first_file,) = forests.glob("*.safetensors")
        sfs_torch.estimate(image, mask, lighting=sh * 0.9, config=config, progress=False)
        # backdate both, as if they were written long ago (some file systems keep 1 s mtimes)
        for age, path in enumerate(forests.glob("*.safetensors")):
            os.utime(path, (time.time() - 100 - age, time.time() - 100 - age))
        again = sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)  # reuses, marks it used
        assert torch.equal(again.normals, first.normals)
        sfs_torch.estimate(image, mask, lighting=sh * 0.8, config=config, progress=False)
        kept = set(forests.glob("*.safetensors"))
        assert len(kept) == 2 and first_file in kept

    def test_evicts_checksums_with_their_forests(self, scene, tmp_path, monkeypatch):
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        _, mask, sh, image = scene
        config = dict(TINY, training={"max_cached_forests": 1})
        for scale in (1.0, 0.9):
            sfs_torch.estimate(image, mask, lighting=sh * scale, config=config, progress=False)
        forests = tmp_path / "forests"
        assert len(list(forests.glob("*.safetensors"))) == 1 and len(list(forests.glob("*.sha256"))) == 1

    def test_corrupt_forest_is_retrained_not_trusted(self, scene, tmp_path, monkeypatch, caplog):
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        _, mask, sh, image = scene
        first = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        (path,) = (tmp_path / "forests").glob("*.safetensors")
        data = bytearray(path.read_bytes())
        middle = len(data) // 2
        data[middle : middle + 4096] = os.urandom(4096)  # random bytes, size unchanged
        path.write_bytes(bytes(data))
        with caplog.at_level("WARNING", logger="sfs_torch.forest_cache"):
            again = sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        assert "checksum mismatch" in caplog.text
        assert torch.equal(again.normals, first.normals)  # retrained: the same forest as before
        assert path.with_suffix(".sha256").read_text() == hashlib.sha256(path.read_bytes()).hexdigest()
        caplog.clear()
        with caplog.at_level("WARNING", logger="sfs_torch.forest_cache"):
            sfs_torch.estimate(image, mask, lighting=sh, config=TINY, progress=False)
        assert "unusable" not in caplog.text  # the replacement verifies

    def test_bound_must_be_positive(self, scene):
        _, mask, sh, image = scene
        with pytest.raises(ValueError, match="max_cached_forests"):
            sfs_torch.estimate(image, mask, lighting=sh, config=dict(TINY, training={"max_cached_forests": 0}), progress=False)

    @pytest.mark.parametrize("policy, given, estimated", [("given", 1, 0), ("always", 1, 2), ("never", 0, 0)])
    def test_policy(self, scene, tmp_path, monkeypatch, policy, given, estimated):
        # an estimated lighting is new for nearly every image: its forests are not kept by default
        monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path))
        _, mask, sh, image = scene
        config = dict(TINY, training={"cache_forests": policy}, refine_rounds=1)
        forests = tmp_path / "forests"
        sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)
        assert len(list(forests.glob("*.safetensors"))) == given
        sfs_torch.estimate(image, mask, config=config, progress=False)
        assert len(list(forests.glob("*.safetensors"))) == given + estimated

    def test_unknown_policy_fails_before_training(self, scene, monkeypatch):
        _, mask, sh, image = scene
        monkeypatch.setattr(pipeline, "load_database", lambda *a, **k: pytest.fail("validated too late"))
        with pytest.raises(ValueError, match="training.cache_forests must be one of"):
            sfs_torch.estimate(image, mask, lighting=sh, config=dict(TINY, training={"cache_forests": True}),
                               progress=False)


class TestConfig:
    def test_partial_dict_merges_onto_defaults(self):
        cfg = resolve_config({"forest": {"n_trees": 3}})
        assert isinstance(cfg, PipelineConfig) and cfg.forest.n_trees == 3
        assert cfg.database == PipelineConfig().database

    def test_unknown_key_is_rejected(self):
        with pytest.raises(ValueError, match="n_treez"):
            resolve_config({"forest": {"n_treez": 3}})


# every option is checked when the config is resolved, before the lighting estimate and the
# database: each bad value's message names its key
BAD_CONFIGS = [
    ({"refine_rounds": -1}, r"^refine_rounds must be an integer >= 0, got -1"),
    ({"normal_rotation": "pxl"}, r"^normal_rotation must be one of \('centroid', 'pixel'\), got 'pxl'"),
    ({"conv_samples_per_tree": 0}, r"^conv_samples_per_tree must be an integer >= 1"),
    ({"prior_check_highlight": 0.0}, r"^prior_check_highlight must be a number > 0 or null, got 0.0"),
    ({"prior_check_highlight": float("nan")}, r"^prior_check_highlight must be a number > 0 or null, got nan"),
    ({"prior_check_tie": 0.0}, r"^prior_check_tie must be a number in \(0, 1\] or null, got 0.0"),
    ({"prior_check_tie": 1.5}, r"^prior_check_tie must be a number in \(0, 1\] or null, got 1.5"),
    ({"relief_scale": 0.0}, r"^relief_scale must be a number > 0, got 0.0"),
    ({"relief_scale": "deep"}, r"'deep' .*could not be converted to Float\s+full_key: relief_scale"),
    ({"relief_slope_power": float("inf")}, r"^relief_slope_power must be a number, got inf"),
    ({"final_round_jitter": -0.5}, r"^final_round_jitter must be a number >= 0, got -0.5"),
    ({"relief_prior_passes": -1}, r"^relief_prior_passes must be an integer >= 0, got -1"),
    ({"relief_refinements": -1}, r"^relief_refinements must be an integer >= 0, got -1"),
    ({"relief_refinement_unit": 0.0}, r"^relief_refinement_unit must be a number > 0, got 0.0"),
    ({"relief_rounds": 0}, r"^relief_rounds must be an integer >= 1, got 0"),
    ({"relief_prior_weights": "no/such/prior.npz"},
     r"^relief_prior_weights must be null \(the shipped prior\) or the path .*got 'no/such/prior.npz': no such file"),
    ({"integrate": {"method": "l3"}}, r"^integrate.method must be one of .*got 'l3'"),
    ({"integrate": {"tol": 0.0}}, r"^integrate.tol must be > 0"),
    # the solver's options are checked with integrate.method="none" (the default) too
    ({"integrate": {"max_iter": 0}}, r"^integrate.max_iter must be an integer >= 1, got 0"),
    # the old spelling of "no integration" says the new one
    ({"integrate": {"method": None}}, r"integrate.method=None is now integrate.method='none' \(integrate=none\)"),
    ({"forest": {"n_trees": 0}}, r"^forest.n_trees must be an int >= 1, got 0"),
    ({"forest": {"max_features": 0}}, r"^forest.max_features must be >= 1"),
    ({"forest": {"_target_": "sfs_torch.forest.NoSuchForest"}}, r"^forest._target_='sfs_torch.forest.NoSuchForest' could not"),
    ({"database": {"n_shapes": 0}}, r"^database.n_shapes must be a positive integer"),
    ({"silhouette": {"depth_layer_ratio": 1.0}}, r"^silhouette.depth_layer_ratio must be > 1"),
    ({"silhouette": {"prune_angle": 30.0}}, r"^silhouette.prune_angle=30.0 needs features.silhouette=false"),
    ({"texton": {"kernel_size": 4}}, r"^texton.kernel_size must be a positive odd integer"),
    ({"texton": {"kernel_size": 7}}, r"^texton.kernel_size \(7\) must equal database.patch_size \(5\)"),
    ({"reflectance_map": {"profile": "cube"}}, r"^reflectance_map.profile must be one of"),
    ({"features": {"rgb": False, "silhouette": False, "texton": False}}, r"^features enables no feature"),
    ({"training": {"noise_sigma": -0.1}}, r"^training.noise_sigma must be"),
    ({"camera": {"focal": -3.0}}, r"^camera.focal must be a positive focal length"),
    ({"camera": {"focal": 100.0, "principal_point": [1.0]}}, r"^camera.principal_point must be two finite numbers"),
    ({"refine": {"when": "sometimes"}}, r"^refine.when must be one of"),
    ({"refine_rounds": 1.5}, r"full_key: refine_rounds"),
    # a key that moved out of a stage's config says where it went
    ({"reflectance_map": {"refine_rounds": 0}}, r"reflectance_map.refine_rounds is now refine_rounds"),
    ({"reflectance_map": {"keep_prior": False}}, r"reflectance_map.keep_prior is now keep_prior"),
    ({"reflectance_map": {"valid_refit": False}}, r"reflectance_map.valid_refit is now valid_refit"),
    ({"camera": {"normal_rotation": "pixel"}}, r"camera.normal_rotation is now normal_rotation"),
    ({"training": {"conv_samples_per_tree": 2}}, r"training.conv_samples_per_tree is now conv_samples_per_tree"),
]


class TestConfigCheckedAtEntry:
    @pytest.fixture()
    def no_work(self, monkeypatch):
        def never(*args, **kwargs):
            raise AssertionError("work started before the config was checked")

        for name in ("load_database", "estimate_lighting", "pixel_features", "_trained_forest"):
            monkeypatch.setattr(pipeline, name, never)

    @pytest.mark.parametrize("config, match", BAD_CONFIGS, ids=[str(c) for c, _ in BAD_CONFIGS])
    def test_estimate(self, scene, no_work, config, match):
        _, mask, _, image = scene
        with pytest.raises(ValueError, match=match):
            sfs_torch.estimate(image, mask, config={**TINY, **config}, progress=False)

    def test_relief_prior_weights_that_hold_no_network(self, scene, no_work, tmp_path):
        _, mask, _, image = scene
        junk = tmp_path / "junk.npz"
        np.savez(junk, weights=np.zeros(3))
        with pytest.raises(ValueError, match=r"^relief_prior_weights: '.*junk.npz' holds no relief prior's weights"):
            sfs_torch.estimate(image, mask, config={**TINY, "relief_prior_weights": str(junk)}, progress=False)

    @pytest.mark.parametrize("integrate", ["l3", "None", ""])
    def test_estimate_integrate_argument(self, scene, no_work, integrate):
        _, mask, _, image = scene
        with pytest.raises(ValueError, match=rf"^integrate must be one of \('none', 'l2', 'l1', 'conv'\).*got '{integrate}'"):
            sfs_torch.estimate(image, mask, integrate=integrate, config=TINY, progress=False)

    @pytest.mark.parametrize("config, match", BAD_CONFIGS[:6], ids=[str(c) for c, _ in BAD_CONFIGS[:6]])
    def test_model(self, config, match):
        from sfs_torch.model import ShapeFromShading

        with pytest.raises(ValueError, match=match):
            ShapeFromShading({**TINY, **config})

    def test_good_values_pass(self):
        cfg = resolve_config({"refine_rounds": 0, "normal_rotation": "pixel", "conv_samples_per_tree": 3,
                              "integrate": {"method": "conv"}, "silhouette": {"prune_angle": 30.0},
                              "features": {"silhouette": False}, "camera": {"focal": 500.0, "principal_point": [1, 2]}})
        assert (cfg.refine_rounds, cfg.normal_rotation, cfg.conv_samples_per_tree) == (0, "pixel", 3)
        assert cfg.integrate.method == "conv" and cfg.silhouette.prune_angle == 30.0


class TestStagesBuiltFromTheirConfigs:
    """The forest and the integrator are ``hydra.utils.instantiate`` of ``forest`` and ``integrate``
    (their ``_target_``), and the silhouette group reaches every silhouette computation."""

    def test_forest_target(self, scene, monkeypatch):
        from sfs_torch import forest as forest_module

        built = []

        class Recording(forest_module.VMFForest):
            def fit(self, X, normals):
                built.append(self)
                return super().fit(X, normals)

        monkeypatch.setattr(forest_module, "RecordingForest", Recording, raising=False)
        _, mask, sh, image = scene
        config = {**TINY, "forest": {**TINY["forest"], "_target_": "sfs_torch.forest.RecordingForest", "n_bins": 32},
                  "training": {"cache_forests": "never"}, "refine": {"when": "never"}}
        sfs_torch.estimate(image, mask, lighting=sh, config=config, progress=False)
        assert len(built) == 1 and (built[0].n_trees, built[0].n_bins) == (8, 32)

    def test_integrate_options_reach_the_integrator(self, scene, monkeypatch):
        built = _recording_integrators(monkeypatch)
        _, mask, sh, image = scene
        config = {**TINY, "integrate": {"method": "l1", "l1_iter": 2, "max_iter": 50}, "refine": {"when": "never"}}
        est = sfs_torch.estimate(image, mask, lighting=sh, focal=80.0, config=config, progress=False)
        assert est.depth is not None and len(built) == 1
        assert (built[0].method, built[0].l1_iter, built[0].max_iter, built[0].focal) == ("l1", 2, 50, 80.0)

    @pytest.mark.parametrize("config_method, argument, integrates", [("l2", "none", False), ("none", "l1", True)])
    def test_integrate_argument_overrides_the_config(self, scene, monkeypatch, config_method, argument, integrates):
        built = _recording_integrators(monkeypatch)
        _, mask, sh, image = scene
        config = {**TINY, "integrate": {"method": config_method, "max_iter": 40}, "refine": {"when": "never"}}
        est = sfs_torch.estimate(image, mask, lighting=sh, integrate=argument, config=config, progress=False)
        assert (est.depth is not None) == integrates and len(built) == integrates
        if integrates:  # the call's method, the config's solver options
            assert (built[0].method, built[0].max_iter) == (argument, 40)

    def test_silhouette_options_reach_every_silhouette_computation(self, scene, monkeypatch):
        import sfs_torch.refine as refine_module
        from sfs_torch.silhouette import SilhouetteConfig

        seen = []

        def recording(module, name, position):
            original = getattr(module, name)

            def wrapper(*args, **kwargs):
                seen.append((name, kwargs.get("silhouette", kwargs.get("config", args[position] if len(args) > position else None))))
                return original(*args, **kwargs)

            monkeypatch.setattr(module, name, wrapper)

        recording(pipeline, "estimate_lighting", 99)
        recording(pipeline, "coarse_normals", 3)
        recording(refine_module, "coarse_normals", 3)
        _, mask, _, image = scene
        options = SilhouetteConfig(gradient_sigma=0.5, prune_angle=45.0)
        config = {**TINY, "silhouette": {"gradient_sigma": 0.5, "prune_angle": 45.0},
                  "features": {"silhouette": False}, "refine": {"when": "always", "iterations": 2}}
        sfs_torch.estimate(image, mask, config=config, progress=False)
        assert {name for name, _ in seen} == {"estimate_lighting", "coarse_normals"}
        assert all(value == options for _, value in seen) and len(seen) >= 3


class TestInputValidation:
    """Odd input gets one clear error naming the argument, or runs with a warning."""

    @pytest.fixture()
    def sphere_scene(self):
        normals, mask = sphere()
        sh = natural_lightings(0.7)["grace_cathedral"]
        image = (render_sh(normals[None], sh[None])[0] * mask).clamp(0, 1)
        return image, mask, sh

    @pytest.fixture()
    def no_database(self, monkeypatch):
        monkeypatch.setattr("sfs_torch.pipeline.load_database", lambda *a, **k: pytest.fail("database loaded"))

    @pytest.mark.parametrize("focal", ["abc", -3.0, float("nan"), float("inf")])
    def test_bad_focal(self, sphere_scene, no_database, focal):
        image, mask, _ = sphere_scene
        with pytest.raises(ValueError, match="focal must be a positive focal length"):
            sfs_torch.estimate(image, mask, focal=focal, config=TINY, progress=False)

    @pytest.mark.parametrize("point", [(float("nan"), float("nan")), (3.0,), "centre", (1.0, 2.0, 3.0)])
    def test_bad_principal_point(self, sphere_scene, no_database, point):
        image, mask, _ = sphere_scene
        with pytest.raises(ValueError, match="principal_point must be two finite numbers"):
            sfs_torch.estimate(image, mask, focal=100.0, principal_point=point, config=TINY, progress=False)

    def test_principal_point_without_focal_warns(self, sphere_scene):
        image, mask, sh = sphere_scene
        with pytest.warns(UserWarning, match="principal_point is ignored"):
            sfs_torch.estimate(image, mask, principal_point=(30.0, 30.0), lighting=sh, config=TINY, progress=False)

    def test_far_principal_point_warns(self, sphere_scene):
        image, mask, sh = sphere_scene
        with pytest.warns(UserWarning, match="far outside"):
            sfs_torch.estimate(image, mask, focal=100.0, principal_point=(5000.0, 30.0), lighting=sh, config=TINY,
                               progress=False)

    def test_lighting_that_is_not_coefficients(self, sphere_scene, no_database):
        image, mask, _ = sphere_scene
        with pytest.raises(TypeError, match="lighting must be SH coefficients"):
            sfs_torch.estimate(image, mask, lighting="foo", config=TINY, progress=False)

    def test_impossible_lightings(self, sphere_scene, no_database):
        image, mask, sh = sphere_scene
        with pytest.raises(ValueError, match="renders no light"):
            sfs_torch.estimate(image, mask, lighting=torch.zeros(3, 9), config=TINY, progress=False)
        with pytest.raises(ValueError, match="renders no light"):
            sfs_torch.estimate(image, mask, lighting=-sh, config=TINY, progress=False)
        strong = sh.clone()
        strong[:, 3] = 4 * strong[:, 0]  # a dipole far stronger than the constant term: negative on one side
        with pytest.raises(ValueError, match="strongly negative"):
            sfs_torch.estimate(image, mask, lighting=strong, config=TINY, progress=False)

    def test_too_bright_lighting_warns(self, sphere_scene):
        image, mask, sh = sphere_scene
        with pytest.warns(UserWarning, match="is its scale"):
            sfs_torch.estimate(image * 0.1, mask, lighting=sh, config=TINY, progress=False)

    def test_bad_forest_option_fails_before_any_work(self, sphere_scene, no_database):
        image, mask, _ = sphere_scene
        with pytest.raises(ValueError, match="forest.n_trees"):
            sfs_torch.estimate(image, mask, config={**TINY, "forest": {"n_trees": 0}}, progress=False)

    def test_one_pixel_object(self):
        mask = torch.zeros(1, 32, 32, dtype=torch.bool)
        mask[0, 16, 16] = True
        image = torch.full((3, 32, 32), 0.5) * mask
        with pytest.warns(UserWarning, match="only 1 pixels"):
            est = sfs_torch.estimate(image, mask, config=TINY, progress=False)
        assert bool(torch.isfinite(est.lighting).all()) and bool(torch.isfinite(est.normals).all())
        assert torch.allclose(est.normals[:, mask[0]].norm(dim=0), torch.ones(1), atol=1e-5)

    def test_border_and_constant_images_warn(self, sphere_scene):
        image, mask, sh = sphere_scene
        shifted_mask = torch.roll(mask, 40, dims=-1)  # the sphere cut by the right border
        with pytest.warns(UserWarning, match="touches the image border"):
            sfs_torch.estimate(torch.roll(image, 40, dims=-1), shifted_mask, lighting=sh, config=TINY, progress=False)
        with pytest.warns(UserWarning, match="constant on the object"):
            sfs_torch.estimate(torch.full_like(image, 0.4) * mask, mask, lighting=sh, config=TINY, progress=False)


    @pytest.mark.parametrize("given", [False, True], ids=["estimated", "given"])
    def test_inputs_that_require_grad_are_read_as_constants(self, sphere_scene, given):
        # an upstream network's output requires grad; the call is not differentiable (the
        # forest's splits), and its refinement once failed in L-BFGS's second backward
        image, mask, sh = sphere_scene
        lighting = sh.clone().requires_grad_() if given else None
        config = {**TINY, "final_round": False, "refine": {"iterations": 5}}
        est = sfs_torch.estimate(image.clone().requires_grad_(), mask, lighting=lighting, config=config, progress=False)
        plain = sfs_torch.estimate(image, mask, lighting=None if lighting is None else sh, config=config,
                                   progress=False)
        assert not est.normals.requires_grad and not est.lighting.requires_grad
        assert torch.equal(est.normals, plain.normals) and torch.equal(est.lighting, plain.lighting)

class TestSaturatedImage:
    """docs/robustness.md: half of the object's pixels saturated at 1 (the lighting scaled up
    until its median pixel clips), default settings against ``refine_rounds=0``, both before the
    photometric refinement (``refine=known``); then the whole default, refinement included, once
    per case: its jointly refined lighting must stay valid too.

    The cases take the method's paths: the silhouette prior kept (the sphere; blobby/9360 under
    Grace for some seeds), the refit round kept (blobby/4046 under Uffizi), and the refit round
    dropped by the guard (a tilted capsule under Eucalyptus Grove), where the default used to
    return the unconstrained silhouette estimate, shading 9 % of its peak negative. Errors are
    averaged over six training seeds and the four cases: with one seed, blobby/4046's median
    moved by 0.5 deg from seed to seed, and with three the mean of medians moved by 0.3 deg
    when the forest's near-tied splits went the other way (compiled CPU search).
    """

    SEEDS = (0, 1, 2, 3, 4, 5)

    @staticmethod
    def saturated(normals, mask, sh):
        shading = render_sh(normals[None], sh[None])[0]
        scale = 1 / float(torch.quantile(shading.amax(0)[mask[0]], 0.5))
        return (scale * shading * mask).clamp(0, 1)

    @staticmethod
    def view(shape):
        import trimesh

        from sfs_torch.geometry_db import DatabaseConfig, evaluation_shapes
        from sfs_torch.rendering import render_normals
        from sfs_torch.shapes import normalize_mesh

        if shape == "sphere":
            return sphere()
        if shape == "capsule":
            mesh = normalize_mesh(trimesh.creation.capsule(1.5, 0.5))
            tilt = torch.tensor(trimesh.transformations.rotation_matrix(0.9, [1, 0.3, 0])[:3, :3], dtype=torch.float32)
        else:
            (mesh,) = [s.mesh for s in evaluation_shapes(DatabaseConfig(**TINY["database"])) if s.name == shape]
            tilt = torch.eye(3)
        view = render_normals(mesh, tilt, 64)
        return view.normals, view.mask

    CASES = (("sphere", "grace_cathedral"), ("blobby/9360", "grace_cathedral"), ("blobby/4046", "uffizi_gallery"),
             ("capsule", "eucalyptus_grove"))

    @pytest.mark.filterwarnings("ignore:.*saturated")
    def test_default_is_no_worse_than_no_refit_and_its_lighting_is_valid(self):
        from sfs_torch.lighting import render_sphere

        errors = {"default": [], "no refit": []}
        for shape, light in self.CASES:
            normals, mask = self.view(shape)
            image = self.saturated(normals, mask, natural_lightings(0.7)[light])
            saturated = float((image[:, mask[0]] >= 1).any(0).float().mean())
            assert 0.45 < saturated < 0.55
            refined = sfs_torch.estimate(image, mask, config=TINY, progress=False)
            rendered = render_sphere(refined.lighting, 64)
            assert float(rendered.min()) >= -0.01 * float(rendered.max()), (shape, "refined")
            for label, extra in (("default", {"refine": {"when": "known"}}),
                                 ("no refit", {"refine_rounds": 0, "refine": {"when": "known"}})):
                # over three seeds: one tiny forest's luck on one 64 px image moves the median by ~0.5 deg
                for seed in self.SEEDS:
                    config = dict(TINY, **extra, training={**TINY.get("training", {}), "seed": seed})
                    est = sfs_torch.estimate(image, mask, config=config, progress=False)
                    metrics = normal_metrics(est.normals[None], normals[None], mask[None])
                    errors[label].append((float(metrics.median[0]), float(metrics.mean[0])))
                    rendered = render_sphere(est.lighting, 64)
                    # exactly >= 0 on the 400 directions the fits are constrained on, rings <= 1 % between
                    assert float(rendered.min()) >= -0.01 * float(rendered.max()), (shape, label)
        # the claim is on average over the cases (docs/robustness.md): on blobby/9360 the default
        # keeps the forest's pair after the refit for some seeds, which the prior beats there
        (median, mean), (median_r0, mean_r0) = (
            tuple(sum(column) / len(column) for column in zip(*errors[label])) for label in ("default", "no refit"))
        # the compiled forest's near-tied splits differ between processors: on one the mean
        # came 0.10 deg above refine_rounds=0 (7.50 vs 7.40), on another 0.0
        assert median <= median_r0 + 0.3 and mean <= mean_r0 + 0.2, errors
