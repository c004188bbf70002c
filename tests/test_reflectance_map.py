import pytest
import torch
from scenes import sphere

from sfs_torch.camera import centroid_rotation
from sfs_torch.lighting import fit_sh, natural_lightings, render_sh, render_sphere, rotate_sh
from sfs_torch.metrics import lmse
from sfs_torch.reflectance_map import (
    LightingEstimator,
    LightingRefit,
    ReflectanceMapConfig,
    estimate_lighting,
    hemisphere_directions,
    refit_lighting,
    sphere_mapping,
)


def sphere_image(size=128, radius=50.0, centre=(0.0, 0.0)):
    normals, mask = sphere(size, radius, centre)
    return normals[None], mask[None]


class TestHemisphereDirections:
    def test_unit_and_visible(self):
        d = hemisphere_directions(300)
        assert torch.allclose(d.norm(dim=1), torch.ones(300), atol=1e-6)
        assert bool((d[:, 2] > 0).all())
        # nearly uniform: the mean direction of a uniform hemisphere is (0, 0, 1/2)
        assert torch.allclose(d.mean(0), torch.tensor([0.0, 0.0, 0.5]), atol=0.01)


class TestSphereMapping:
    def test_disk_maps_to_sphere_normals(self):
        normals, mask = sphere_image(160, 70.0)
        mapped = sphere_mapping(mask, "sphere")
        cos = (mapped * normals).sum(1)[mask[:, 0]]
        assert torch.rad2deg(torch.acos(cos.clamp(-1, 1))).median() < 1.0

    def test_exception(self):
        _, mask = sphere_image(32, 10.0)
        with pytest.raises(ValueError, match="profile"):
            sphere_mapping(mask, "cube")


class TestEstimateLighting:
    @pytest.mark.parametrize("name", ["grace_cathedral", "campus_sunset", "uffizi_gallery"])
    def test_sphere_recovers_lighting(self, name):
        normals, mask = sphere_image()
        sh = natural_lightings(0.7)[name][None]
        image = (render_sh(normals, sh) * mask).clamp(0, 1)
        est = estimate_lighting(image, mask)
        assert float(lmse(est, sh)[0]) < 1e-4

    def test_sphere_profile_beats_linear_on_a_sphere(self):
        normals, mask = sphere_image()
        sh = natural_lightings(0.7)["galileos_tomb"][None]
        image = (render_sh(normals, sh) * mask).clamp(0, 1)
        exact = lmse(estimate_lighting(image, mask), sh)
        linear = lmse(estimate_lighting(image, mask, config=ReflectanceMapConfig(profile="linear")), sh)
        assert float(exact[0]) < 0.1 * float(linear[0])

    def test_batch_equals_single(self):
        normals, mask = sphere_image(64, 25.0)
        lights = natural_lightings(0.7)
        sh = torch.stack([lights["grace_cathedral"], lights["eucalyptus_grove"]])
        images = (render_sh(normals.expand(2, -1, -1, -1), sh) * mask).clamp(0, 1)
        both = estimate_lighting(images, mask.expand(2, -1, -1, -1))
        one = estimate_lighting(images[1:], mask)
        assert torch.allclose(both[1], one[0], atol=1e-5)

    def test_perspective_rotates_by_the_centroid(self):
        normals, mask = sphere_image(96, 20.0, centre=(25.0, 10.0))
        sh = natural_lightings(0.7)["st_peters_basilica"][None]
        image = (render_sh(normals, sh) * mask).clamp(0, 1)
        ortho = estimate_lighting(image, mask)
        persp = estimate_lighting(image, mask, focal=80.0)
        expected = rotate_sh(ortho, centroid_rotation(mask, 80.0))
        assert torch.allclose(persp, expected, atol=1e-5)

    def test_exception(self):
        normals, mask = sphere_image(32, 10.0)
        with pytest.raises(ValueError, match="image"):
            estimate_lighting(torch.zeros(1, 2, 32, 32), mask)
        with pytest.raises(ValueError, match="mask"):
            estimate_lighting(torch.zeros(1, 3, 32, 32), torch.zeros(1, 1, 32, 32, dtype=torch.bool))
        bad = torch.zeros(1, 3, 32, 32)
        bad[0, 0, 16, 16] = float("inf")
        with pytest.raises(ValueError, match="image contains"):
            estimate_lighting(bad, mask)

    @pytest.mark.parametrize("config, error, match", [
        (ReflectanceMapConfig(knn_fraction=0.0, min_k=0), ValueError, r"config\.min_k must be an integer >= 1, got 0"),
        (ReflectanceMapConfig(n_directions=4), ValueError, r"config\.n_directions must be an integer >= 9, got 4"),
        (ReflectanceMapConfig(max_pixels=0), ValueError, r"config\.max_pixels must be an integer >= 1, got 0"),
        ({"n_direction": 10}, ValueError, "config does not fit ReflectanceMapConfig"),
        ("sphere", TypeError, "config must be a ReflectanceMapConfig, a mapping or None, got str"),
    ])
    def test_config_is_checked(self, config, error, match):
        _, mask = sphere_image(32, 10.0)
        with pytest.raises(error, match=match):
            estimate_lighting(torch.zeros(1, 3, 32, 32), mask, config=config)

    def test_mapping_config_equals_dataclass(self):
        normals, mask = sphere_image(32, 10.0)
        image = (render_sh(normals, natural_lightings(0.7)["grace_cathedral"][None]) * mask).clamp(0, 1)
        options = {"profile": "linear", "n_directions": 40}
        assert torch.equal(estimate_lighting(image, mask, config=options),
                           estimate_lighting(image, mask, config=ReflectanceMapConfig(**options)))


class TestRefitLighting:
    def test_true_normals_recover_lighting_despite_clipping(self):
        normals, mask = sphere_image(64, 25.0)
        sh = natural_lightings(4.0)["grace_cathedral"][None]  # bright enough to clip at 1
        shading = render_sh(normals, sh)
        image = (shading * mask).clamp(0, 1)
        clipped = mask & ((shading <= 0) | (shading >= 1)).any(1, keepdim=True)
        assert 0.05 < float(clipped.sum() / mask.sum()) < 0.95
        assert torch.allclose(refit_lighting(image, mask, normals), sh, atol=1e-4)

    def test_all_pixels_clipped_falls_back_to_the_mask(self):
        normals, mask = sphere_image(32, 12.0)
        image = torch.ones(1, 3, 32, 32) * mask
        sh = refit_lighting(image, mask, normals)
        # a constant white image is fitted by a constant (ambient-only) lighting
        assert torch.allclose(render_sh(normals, sh)[mask.expand(-1, 3, -1, -1)], torch.ones(1), atol=1e-4)

    def test_saturated_image_and_wrong_normals_give_a_valid_lighting(self):
        # most of the object saturated and normals tilted away: an unconstrained fit to
        # the few unclipped pixels shades parts of the hemisphere negative (-1.25 here)
        normals, mask = sphere_image(64, 26.0)
        image = (8 * render_sh(normals, natural_lightings(0.8)["campus_sunset"][None])).clamp(0, 1) * mask
        wrong = torch.nn.functional.normalize(normals + torch.tensor([0.8, 0.0, 0.0]).view(1, 3, 1, 1), dim=1) * mask
        unclipped = mask & ((image > 0) & (image < 1)).all(1, keepdim=True)
        assert float(render_sphere(fit_sh(wrong, image, unclipped), 64).min()) < -1.0
        sh = refit_lighting(image, mask, wrong)
        sphere_render = render_sphere(sh, 64)
        assert float(sphere_render.min()) > -0.005 * float(sphere_render.max())

    def test_exception(self):
        normals, mask = sphere_image(32, 12.0)
        with pytest.raises(ValueError, match="mask"):
            refit_lighting(torch.zeros(1, 3, 32, 32), torch.zeros_like(mask), normals)

    def test_swapped_or_non_unit_normals(self):
        normals, mask = sphere_image(32, 12.0)
        image = (render_sh(normals, natural_lightings(0.7)["grace_cathedral"][None]) * mask).clamp(0, 1)
        with pytest.raises(ValueError, match=r"normals must have unit length \(within 1e-3\) on the mask"):
            refit_lighting(normals, mask, image)  # image and normals swapped
        with pytest.raises(ValueError, match=r"normals must have unit length.*got lengths from 1\.1 to 1\.1"):
            refit_lighting(image, mask, 1.1 * normals)
        refit_lighting(image, mask, normals)  # only the mask's pixels count: zero normals outside it are fine

    def test_errors_name_image_and_normals(self):
        normals, mask = sphere_image(32, 12.0)
        image = (render_sh(normals, natural_lightings(0.7)["grace_cathedral"][None]) * mask).clamp(0, 1)
        bad = image.clone()
        bad[0, 0, 16, 16] = float("nan")
        with pytest.raises(ValueError, match="image contains 1 NaN"):
            refit_lighting(bad, mask, normals)
        with pytest.raises(ValueError, match="image and normals must have the same batch size"):
            refit_lighting(image, mask, normals[..., :16])


def lit_spheres(batch, size=32, radius=12.0, dtype=torch.float32):
    """``batch`` spheres under different natural lightings: normals, mask, lighting, image."""
    normals, mask = sphere_image(size, radius)
    lights = natural_lightings(0.7)
    sh = torch.stack([lights[name] for name in sorted(lights)[:batch]]).to(dtype)
    normals, mask = normals.to(dtype).expand(batch, -1, -1, -1), mask.expand(batch, -1, -1, -1)
    image = (render_sh(normals, sh) * mask).clamp(0, 1)
    return normals, mask, sh, image


# small settings keep the k-NN and the fits cheap
FEW_DIRECTIONS = ReflectanceMapConfig(n_directions=40)


class TestLightingEstimator:
    def test_smoke(self, device, dtype):
        _, mask, sh, image = lit_spheres(1, 64, 26.0, dtype)
        module = LightingEstimator()
        out = module(image.to(device), mask.to(device))
        assert out.shape == (1, 3, 9) and out.dtype == dtype and out.device.type == device.type
        assert float(lmse(out.cpu().float(), sh.float())[0]) < 1e-3
        assert module.config == ReflectanceMapConfig() and module.focal is None
        assert list(module.buffers()) == []

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        _, mask, _, image = lit_spheres(batch)
        module = LightingEstimator(FEW_DIRECTIONS)
        out = module(image.to(device), mask.to(device))
        assert out.shape == (batch, 3, 9)
        for b in range(batch):  # objects are estimated one at a time
            torch.testing.assert_close(out[b : b + 1], module(image[b : b + 1].to(device), mask[b : b + 1].to(device)))

    def test_exception(self):
        _, mask, _, image = lit_spheres(1)
        with pytest.raises(ValueError, match="profile"):
            LightingEstimator(ReflectanceMapConfig(profile="cube"))
        with pytest.raises(ValueError, match="config"):
            LightingEstimator({"n_direction": 10})
        with pytest.raises(TypeError, match="config"):
            LightingEstimator("sphere")
        with pytest.raises(ValueError, match="focal"):
            LightingEstimator(focal=-1.0)
        with pytest.raises(ValueError, match="image"):
            LightingEstimator()(image[:, :2], mask)
        with pytest.raises(ValueError, match="mask"):
            LightingEstimator()(image, torch.zeros_like(mask))

    def test_gradcheck(self):
        # Differentiable in the image: the k nearest pixels of each hemisphere direction
        # (Eq. 9) are chosen by the mask's silhouette mapping alone, so the k-NN selection
        # is a constant of the image; what remains (means, least squares, mean/std
        # matching) is smooth. The mask (bool) has no gradient.
        _, mask, _, image = lit_spheres(1, 16, 6.0, torch.float64)
        g = torch.Generator().manual_seed(0)
        image = ((image + 0.01 * torch.rand(image.shape, generator=g, dtype=torch.float64)) * mask).requires_grad_()
        module = LightingEstimator(ReflectanceMapConfig(n_directions=20), focal=30.0)
        assert torch.autograd.gradcheck(lambda x: module(x, mask), (image,), fast_mode=True)

    def test_module(self):
        _, mask, _, image = lit_spheres(2)
        mask = mask.roll(3, -1)  # off centre: the perspective rotation is not the identity
        image = image.roll(3, -1)
        options = {"profile": "linear", "n_directions": 40, "match_statistics": False}
        module = LightingEstimator(options, focal=40.0, principal_point=(15.0, 17.0))
        assert module.config == ReflectanceMapConfig(**options)
        expected = estimate_lighting(
            image, mask, focal=40.0, principal_point=(15.0, 17.0), config=ReflectanceMapConfig(**options)
        )
        torch.testing.assert_close(module(image, mask), expected)

    @pytest.mark.slow
    @pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace the builtin")
    def test_dynamo(self):
        # ~20 s: the per-object loop, the SciPy distance transform and the k-NN chunks
        # break the graph many times
        _, mask, _, image = lit_spheres(2)
        module = LightingEstimator(FEW_DIRECTIONS)
        compiled = torch.compile(module, backend="eager")
        torch.testing.assert_close(compiled(image, mask), module(image, mask))


class TestLightingRefit:
    def test_smoke(self, device, dtype):
        normals, mask, sh, image = lit_spheres(1, dtype=dtype)
        module = LightingRefit()
        out = module(image.to(device), mask.to(device), normals.to(device))
        assert out.shape == (1, 3, 9) and out.dtype == dtype and out.device.type == device.type
        torch.testing.assert_close(out.cpu(), sh, atol=1e-3, rtol=0)
        assert module.valid and "valid=True" in repr(module)

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch, device):
        normals, mask, sh, image = lit_spheres(batch)
        out = LightingRefit()(image.to(device), mask.to(device), normals.to(device))
        assert out.shape == (batch, 3, 9)
        torch.testing.assert_close(out.cpu(), sh, atol=1e-3, rtol=0)

    def test_exception(self):
        normals, mask, _, image = lit_spheres(1)
        with pytest.raises(ValueError, match="mask"):
            LightingRefit()(image, torch.zeros_like(mask), normals)
        with pytest.raises(ValueError, match="normals"):
            LightingRefit()(image, mask, normals[:, :2])
        with pytest.raises(ValueError, match="image"):
            LightingRefit()(image[:, :2], mask, normals)

    def test_gradcheck(self):
        normals, mask, _, image = lit_spheres(1, 12, 5.0, torch.float64)
        g = torch.Generator().manual_seed(1)
        # unclipped pixels, a lighting valid on the hemisphere: the non-negativity
        # constraint stays inactive and the fit is plain least squares
        noise = 0.01 * torch.rand(image.shape, generator=g, dtype=torch.float64)
        image = ((0.9 * image + noise) * mask).requires_grad_()
        normals = normals.clone().requires_grad_()
        module = LightingRefit()
        assert torch.autograd.gradcheck(lambda x, n: module(x, mask, n), (image, normals), fast_mode=True)

    @pytest.mark.parametrize("valid", [True, False])
    def test_module(self, valid):
        normals, mask, _, image = lit_spheres(2)
        wrong = torch.nn.functional.normalize(normals + torch.tensor([0.8, 0.0, 0.0]).view(1, 3, 1, 1), dim=1) * mask
        expected = refit_lighting(image, mask, wrong, valid=valid)
        torch.testing.assert_close(LightingRefit(valid)(image, mask, wrong), expected)

    @pytest.mark.slow
    def test_dynamo(self):
        # ~5 s: the clipping test and the validity constraint break the graph
        normals, mask, _, image = lit_spheres(2)
        compiled = torch.compile(LightingRefit(), backend="eager")
        torch.testing.assert_close(compiled(image, mask, normals), refit_lighting(image, mask, normals))
