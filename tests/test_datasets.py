from dataclasses import replace

import pytest
import torch
import trimesh

from sfs_torch.datasets import (
    DEGRADATIONS,
    FormationConfig,
    evaluation_lightings,
    form_image,
    scene_lightings,
    scene_shapes,
    synthetic_scenes,
    validation_lightings,
    view_visibility,
)
from sfs_torch.geometry_db import DatabaseConfig, database_split, evaluation_shapes
from sfs_torch.lighting import render_sh
from sfs_torch.natural_lighting import normalise_lighting
from sfs_torch.rendering import render_normals
from sfs_torch.shapes import Shape, normalize_mesh

LIGHT = evaluation_lightings(1)


def _shapes():
    sphere = normalize_mesh(trimesh.creation.icosphere(subdivisions=4))
    # a cup: a concave inside that cast shadows darken
    cup = trimesh.creation.annulus(r_min=0.6, r_max=1.0, height=1.2)
    bottom = trimesh.creation.cylinder(radius=1.0, height=0.2)
    bottom.apply_translation((0, 0, -0.5))
    return [Shape("sphere", sphere), Shape("cup", normalize_mesh(trimesh.util.concatenate([cup, bottom])))]


def _scenes(formation, shapes=None, **kwargs):
    return list(synthetic_scenes(shapes or _shapes(), LIGHT, resolution=48, formation=formation, **kwargs))


class TestFormationConfig:
    @pytest.mark.parametrize("field, value", [("specular", -0.1), ("noise", float("nan")), ("directions", 0),
                                              ("bits", 0), ("exposure_stops", "1"),
                                              ("exposure_stops", float("inf")), ("shot_noise", True),
                                              ("directions", True), ("bits", True)])
    def test_bad_values(self, field, value):
        with pytest.raises(ValueError, match=f"FormationConfig.{field}"):
            FormationConfig(**{field: value})

    def test_all_combines_every_degradation(self):
        combined = DEGRADATIONS["all"]
        for name, single in DEGRADATIONS.items():
            for field in FormationConfig.__dataclass_fields__:
                if getattr(single, field) != getattr(DEGRADATIONS["exact"], field) and name != "all":
                    assert getattr(combined, field) == getattr(single, field), (name, field)


class TestSyntheticScenes:
    def test_exact_is_the_paper_setting(self):
        for scene in _scenes(DEGRADATIONS["exact"]):
            expected = (render_sh(scene.normals, scene.source_lighting).clamp(0, 1) * scene.mask)
            m = scene.mask.expand_as(scene.image)
            assert (scene.image - expected)[m].std() == pytest.approx(0.001, rel=0.1)
            assert torch.equal(scene.lighting, scene.source_lighting)

    def test_same_views_for_every_formation(self):
        a, b = _scenes(DEGRADATIONS["exact"]), _scenes(DEGRADATIONS["all"])
        assert [s.name for s in a] == [s.name for s in b]
        for x, y in zip(a, b):
            assert torch.equal(x.normals, y.normals) and torch.equal(x.mask, y.mask)
        again = _scenes(DEGRADATIONS["all"])
        assert all(torch.equal(x.image, y.image) for x, y in zip(b, again))
        alone = _scenes(DEGRADATIONS["all"], shapes=_shapes()[1:])  # without the sphere
        assert torch.equal(alone[0].image, b[1].image)

    def test_shadows_darken_only_the_concave_shape(self):
        exact, shadowed = _scenes(replace(DEGRADATIONS["exact"], noise=0.0)), _scenes(DEGRADATIONS["shadows"])
        assert float(shadowed[0].image.sum() / exact[0].image.sum()) == pytest.approx(1.0, abs=0.03)  # convex
        # looking down into the cup: its floor sees the sky through the opening only
        cup = _shapes()[1].mesh
        view = render_normals(cup, torch.eye(3, dtype=torch.float64), 48)
        config = replace(DEGRADATIONS["shadows"], noise=0.0)
        visibility = view_visibility(view, cup, torch.eye(3), config)
        sh = LIGHT[0][1][None]
        args = (view.normals[None], view.mask[None], sh)
        plain = form_image(*args, replace(config, shadows=False), torch.Generator())
        dark = form_image(*args, config, torch.Generator(), visibility=visibility)
        floor = (slice(None), slice(None), slice(22, 26), slice(22, 26))
        assert float(dark[floor].sum()) < 0.6 * float(plain[floor].sum())
        assert float(dark.sum()) < float(plain.sum())

    def test_exposure_moves_the_known_lighting_not_the_normals(self):
        exact, exposed = _scenes(DEGRADATIONS["exact"]), _scenes(DEGRADATIONS["exposure"])
        for s, t in zip(exact, exposed):
            gain = t.image.sum((2, 3)) / s.image.sum((2, 3))  # per channel
            assert not torch.allclose(gain, torch.ones_like(gain), atol=0.02)
            assert torch.allclose(t.lighting / s.lighting, gain[..., None].expand(-1, -1, 9), rtol=0.02)
            assert torch.allclose(normalise_lighting(t.source_lighting), normalise_lighting(s.source_lighting))

    def test_sensor_is_8_bit_srgb(self):
        from sfs_torch.io import linear_to_srgb

        for scene in _scenes(DEGRADATIONS["sensor"]):
            codes = linear_to_srgb(scene.image) * 255
            assert torch.allclose(codes, codes.round(), atol=1e-3)

    def test_specular_highlight_brightens_the_sphere(self):
        exact, shiny = _scenes(DEGRADATIONS["exact"]), _scenes(DEGRADATIONS["specular"])
        lift = shiny[0].image - exact[0].image
        assert float(lift.max()) > 0.05 and float(lift.min()) > -0.01

    def test_lights_per_shape(self):
        lights = validation_lightings(4)
        scenes = list(synthetic_scenes(_shapes(), lights, resolution=32, lights_per_shape=2))
        assert [s.lighting_name for s in scenes] == [name for name, _ in lights]

    @pytest.mark.parametrize("lights, per_shape, match", [
        (2, 3, r"lights_per_shape must be an integer in \[1, 2\] \(the number of lightings\), got 3"),
        (2, 0, r"lights_per_shape must be an integer in \[1, 2\] .*, got 0"),
        (0, 1, "lightings must hold at least one"),
        (0, None, "lightings must hold at least one"),
    ])
    def test_bad_lights_per_shape(self, lights, per_shape, match):
        # 3 of 2 lightings gave one shape a lighting twice: duplicate scene names
        with pytest.raises(ValueError, match=match):
            synthetic_scenes(_shapes(), evaluation_lightings(2)[:lights], resolution=32, lights_per_shape=per_shape)

    def test_form_image_checks_the_mask(self):
        view = render_normals(_shapes()[0].mesh, torch.eye(3), 16)
        normals, mask, sh = view.normals[None], view.mask[None], LIGHT[0][1][None]
        with pytest.raises(ValueError, match="mask must be boolean or hold only 0 and 1"):
            form_image(normals, mask * 0.5, sh, FormationConfig(), torch.Generator())
        with pytest.raises(ValueError, match=r"normals and mask must have the same .*\(1, 3, 16, 16\) and \(1, 1, 8, 8\)"):
            form_image(normals, mask[..., :8, :8], sh, FormationConfig(), torch.Generator())


class TestSides:
    def test_validation_lightings_are_not_rh(self):
        names = [name for name, _ in validation_lightings(8)]
        assert not set(names) & {name for name, _ in evaluation_lightings(7)}
        assert len(set(n.rsplit("_", 1)[0] for n in names)) == 8

    @pytest.mark.parametrize("exposure", [None, 0.15])
    def test_validation_exposure_sets_the_lit_spheres_95th_percentile(self, exposure):
        from sfs_torch.lighting import render_sphere

        for _, sh in validation_lightings(3, seed=1, exposure=exposure):
            sphere = render_sphere(sh[None], 64)[0]
            assert float(torch.quantile(sphere[sphere > 0], 0.95)) == pytest.approx(exposure or 0.9, rel=1e-4)

    @pytest.mark.parametrize("exposure", [0.0, -1.0, float("inf")])
    def test_bad_exposure(self, exposure):
        with pytest.raises(ValueError, match="exposure must be a number > 0"):
            validation_lightings(2, exposure=exposure)

    def test_scene_lightings_by_side(self):
        # the tuning sides share the Poly Haven maps (seed and exposure passed on); the test side is the probes
        def same(a, b):
            return [n for n, _ in a] == [n for n, _ in b] and all(torch.equal(x, y) for (_, x), (_, y) in zip(a, b))

        assert same(scene_lightings(2, "test"), evaluation_lightings(2))
        for side in ("validation", "spare"):
            assert same(scene_lightings(3, side, seed=2, exposure=0.2), validation_lightings(3, seed=2, exposure=0.2))

    @pytest.mark.parametrize("options, message", [
        (dict(side="train"), "side must be one of 'test', 'validation', 'spare', got 'train'"),
        (dict(side="test", exposure=0.2), r"seed and exposure are for the tuning sides \(validation, spare\)"),
        (dict(side="test", seed=1), r"seed and exposure are for the tuning sides \(validation, spare\)"),
    ])
    def test_bad_scene_lightings(self, options, message):
        with pytest.raises(ValueError, match=message):
            scene_lightings(2, **options)

    def test_test_and_validation_shapes_are_disjoint(self):
        cfg = DatabaseConfig(collection="blobby", n_shapes=3, n_views=2, resolution=48, samples_per_view=40,
                             n_eval_shapes=4, seed=0)
        every = [s.name for s in evaluation_shapes(cfg)]
        test = [s.name for s in scene_shapes(2, "test", cfg)]
        validation = [s.name for s in scene_shapes(2, "validation", cfg)]
        assert test == every[0::2] and validation == every[1::2]
        # None: the whole half (sfs-torch-eval's dataset.shapes=null)
        assert [s.name for s in scene_shapes(None, "validation", cfg)] == every[1::2]

    def test_spare_shapes_are_neither_trained_on_nor_held_out(self):
        cfg = DatabaseConfig(collection="blobby", n_shapes=3, n_views=2, resolution=48, samples_per_view=40,
                             n_eval_shapes=4, seed=0)
        split = database_split(cfg)
        spare = [s.name for s in scene_shapes(5, "spare", cfg)]
        assert len(set(spare)) == 5
        assert not set(spare) & (set(split.train) | set(split.evaluation))
        # the next shapes of the same draw: a longer pool starts with a shorter one
        assert set(spare) < {s.name for s in scene_shapes(9, "spare", cfg)}
        assert set(spare) == set(database_split(replace(cfg, n_shapes=8)).train) - set(split.train)

    @pytest.mark.parametrize("make, n, match", [
        (validation_lightings, -2, "n must be an integer >= 0, got -2"),
        (validation_lightings, 2.5, "n must be an integer >= 0, got 2.5"),
        (evaluation_lightings, 2.5, r"n must be an integer in \[1, 7\], got 2.5"),
        (scene_shapes, 2.5, r"n must be an integer in \[0, \d+\] on the test side, got 2.5"),
    ])
    def test_bad_n(self, make, n, match):
        with pytest.raises(ValueError, match=match):
            make(n)

    def test_bad_side(self):
        with pytest.raises(ValueError, match="side must be one of 'test', 'validation', 'spare', got 'train'"):
            scene_shapes(1, "train")

    def test_too_many_spare_shapes(self):
        cfg = DatabaseConfig(collection="blobby", n_shapes=3, n_eval_shapes=4)
        with pytest.raises(ValueError, match=r"n must be an integer in \[0, \d+\] on the spare side, got 100000"):
            scene_shapes(100_000, "spare", cfg)
