import math

import pytest
import torch
import trimesh

from sfs_torch.image_formation import (
    blinn_phong,
    dominant_light,
    estimate_noise_sigma,
    expose,
    poisson_gaussian_noise,
    quantise_srgb,
    sh_radiance,
    shade_environment,
    shadow_visibility,
    sphere_directions,
)
from sfs_torch.io import linear_to_srgb
from sfs_torch.lighting import natural_lightings, render_sh, sh_basis_vectors


def _random_normals(n, seed=0):
    v = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return v / v.norm(dim=1, keepdim=True)


class TestSphereDirections:
    def test_uniform_radiance_shades_to_one(self):
        # (1 / pi) * integral of max(0, n . w) over the sphere is 1 for any normal
        d = sphere_directions(400)
        assert torch.allclose(d.norm(dim=1), torch.ones(400, dtype=torch.float64))
        shading = shade_environment(_random_normals(50), d, torch.ones(400, 3, dtype=torch.float64))
        assert (shading - 1).abs().max() < 0.01

    def test_bad_count(self):
        with pytest.raises(ValueError, match="n must be a positive integer"):
            sphere_directions(0)

    def test_shade_environment_exception(self):
        d, n = sphere_directions(400), _random_normals(5)
        sky = torch.ones(400, 3, dtype=torch.float64)
        with pytest.raises(ValueError, match=r"^directions must have unit length \(within 1e-3\), got lengths from 2 to 2$"):
            shade_environment(n, 2 * d, sky)  # was 4x too bright
        with pytest.raises(ValueError, match=r"^radiance must have shape \(K, 3\), got \(3, 400\)$"):
            shade_environment(n, d, sky.T)
        with pytest.raises(ValueError, match=r"^radiance must have one row per direction, \(400, 3\), got \(399, 3\)$"):
            shade_environment(n, d, sky[:399])
        with pytest.raises(ValueError, match=r"^normals must have shape \(N, 3\), got \(3, 5\)$"):
            shade_environment(n.T, d, sky)
        with pytest.raises(ValueError, match=r"^visibility must have shape \(N, K\) = \(5, 400\) for these normals"):
            shade_environment(n, d, sky, torch.ones(5, 399, dtype=torch.bool))
        with pytest.raises(ValueError, match=r"^radiance contains 3 NaN or infinite values$"):
            shade_environment(n, d, torch.cat([sky[:399], torch.full((1, 3), math.nan, dtype=torch.float64)]))


class TestSHRadiance:
    @pytest.mark.parametrize("name", ["grace_cathedral", "uffizi_gallery", "campus_sunset"])
    def test_non_negative_and_shades_like_render_sh(self, name):
        sh = natural_lightings(0.8)[name].double()
        d = sphere_directions(400)
        radiance = sh_radiance(d, sh)
        assert (radiance >= 0).all()
        n = _random_normals(200)
        expected = render_sh(n.T[None, :, :, None], sh[None])[0, :, :, 0].T
        got = shade_environment(n, d, radiance)
        # the clipped 9-term radiance alone would be up to ~20 % too bright on these probes;
        # what is left is the 9-term model's own error (bands > 2 through the clamped cosine)
        assert (got - expected).abs().max() < 0.03 * expected.max()

    def test_reproduces_the_coefficients(self):
        sh = natural_lightings(1.0)["grace_cathedral"].double()
        d = sphere_directions(400)
        radiance = sh_radiance(d, sh)
        lambert = torch.tensor([1.0, 2 / 3, 2 / 3, 2 / 3, 0.25, 0.25, 0.25, 0.25, 0.25], dtype=torch.float64)
        projected = (4 * math.pi / 400) * (sh_basis_vectors(d).T @ radiance).T * lambert
        assert torch.allclose(projected, sh, atol=1e-3 * float(sh.abs().max()))

    def test_exception(self):
        sh = natural_lightings(0.7)["grace_cathedral"]
        d = sphere_directions(400)
        with pytest.raises(ValueError, match=r"^directions must have unit length \(within 1e-3\), got lengths from 2 to 2$"):
            sh_radiance(2 * d, sh)  # was off by 0.64
        with pytest.raises(ValueError, match=r"^sh contains 27 NaN or infinite values$"):
            sh_radiance(d, torch.full((3, 9), math.nan))
        with pytest.raises(ValueError, match=r"^directions must have shape \(K, 3\), got \(3, 400\)$"):
            sh_radiance(d.T, sh)
        with pytest.raises(ValueError, match=r"^iterations must be an integer >= 0, got 1.5$"):
            sh_radiance(d, sh, iterations=1.5)


def _wall_on_floor():
    floor = trimesh.creation.box(extents=(4.0, 0.1, 4.0))
    floor.apply_translation((0, -0.05, 0))
    wall = trimesh.creation.box(extents=(0.2, 0.5, 4.0))
    wall.apply_translation((0.1, 0.25, 0))
    return trimesh.util.concatenate([floor, wall])


class TestShadowVisibility:
    def test_a_corner_sees_less_sky_and_is_darker(self):
        mesh = _wall_on_floor()
        points = torch.tensor([[-0.05, 0.0, 0.0], [-1.9, 0.0, 0.0]], dtype=torch.float64)  # by the wall, far off
        up = torch.tensor([[0.0, 1.0, 0.0]] * 2, dtype=torch.float64)
        d = sphere_directions(400)
        visible = shadow_visibility(mesh, points, up, d, torch.eye(3))
        above = (d[:, 1] > 0).sum()
        assert visible[1].sum() > 0.85 * above  # far from the wall: nearly the whole hemisphere
        assert visible[0].sum() < 0.65 * above  # in the corner: the wall hides about half
        assert not visible[:, d[:, 1] < 0].any()  # never below the tangent plane
        sky = torch.ones(400, 3, dtype=torch.float64)
        shading = shade_environment(up, d, sky, visible)
        assert shading[0, 0] < 0.8 * shading[1, 0]

    def test_world_and_camera_frames(self):
        # the same scene seen through a rotated camera: normals and directions in that frame
        mesh = _wall_on_floor()
        rot = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)  # world y -> camera z
        points = torch.tensor([[-0.05, 0.0, 0.0]], dtype=torch.float64)
        d = sphere_directions(400)
        world = shadow_visibility(mesh, points, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64), d, torch.eye(3))
        camera = shadow_visibility(mesh, points, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64) @ rot.T,
                                   d @ rot.T, rot)
        assert torch.equal(world, camera)


class TestSpecular:
    def test_dominant_light(self):
        sh = torch.zeros(3, 9, dtype=torch.float64)
        sh[:, 0], sh[:, 3] = 2.0, 1.0  # a dipole towards +x
        direction, colour = dominant_light(sh)
        assert torch.allclose(direction, torch.tensor([1.0, 0, 0], dtype=torch.float64))
        assert torch.allclose(colour, torch.full((3,), 2 * 0.282095 + 0.488603, dtype=torch.float64), atol=1e-6)

    def test_blinn_phong_peak_and_back(self):
        light = torch.tensor([1.0, 0, 1], dtype=torch.float64) / math.sqrt(2)
        view = torch.tensor([0.0, 0, 1], dtype=torch.float64)
        half = (light + view) / (light + view).norm()
        normals = torch.stack([half, torch.tensor([0.0, 0, 1], dtype=torch.float64), -light])
        colour = torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64)
        out = blinn_phong(normals, view, light, colour, 40.0)
        assert torch.allclose(out[0], colour)
        assert torch.allclose(out[1], colour * math.cos(math.pi / 8) ** 40)
        assert (out[2] == 0).all()

    def test_blinn_phong_exception(self):
        normals, view = _random_normals(4), torch.tensor([0.0, 0, 1], dtype=torch.float64)
        light, colour = torch.tensor([0.0, 0, 1], dtype=torch.float64), torch.ones(3, dtype=torch.float64)
        with pytest.raises(ValueError, match=r"^light must have unit length \(within 1e-3\), got lengths from 2 to 2$"):
            blinn_phong(normals, view, 2 * light, colour, 40.0)
        with pytest.raises(ValueError, match=r"^shininess must be a number >= 0, got -1.0$"):
            blinn_phong(normals, view, light, colour, -1.0)  # was NaN
        with pytest.raises(ValueError, match=r"^normals must have shape \(N, 3\), got \(3, 4\)$"):
            blinn_phong(normals.T, view, light, colour, 40.0)
        with pytest.raises(ValueError, match=r"^view must have shape \(N, 3\) = \(4, 3\) or \(3,\), got \(5, 3\)$"):
            blinn_phong(normals, _random_normals(5), light, colour, 40.0)
        with pytest.raises(ValueError, match=r"^colour must have shape \(3\), got \(1, 3\)$"):
            blinn_phong(normals, view, light, colour[None], 40.0)

    def test_no_dipole_no_highlight(self):
        # a lighting without a dipole has no dominant direction: no highlight, not an error
        ambient = torch.zeros(3, 9, dtype=torch.float64)
        ambient[:, 0] = 1.0
        direction, _ = dominant_light(ambient)
        assert not bool(direction.any())
        out = blinn_phong(_random_normals(4), torch.tensor([0.0, 0, 1], dtype=torch.float64), direction,
                          torch.ones(3, dtype=torch.float64), 40.0)
        assert torch.equal(out, torch.zeros(4, 3, dtype=torch.float64))


class TestCameraEffects:
    def test_expose_scales(self):
        image = torch.rand(2, 3, 4, 4)
        gains = torch.tensor([1.1, 1.0, 0.9])
        assert torch.allclose(expose(image, 1.5 * gains), image * 1.5 * gains.view(1, 3, 1, 1))

    def test_expose_exception(self):
        image = torch.rand(2, 3, 4, 4)
        with pytest.raises(TypeError, match=r"^gains must be a torch.Tensor of shape \(3\), got list$"):
            expose(image, [1.0, 2.0, 3.0])
        with pytest.raises(ValueError, match=r"^gains must have shape \(3\), got \(\)$"):
            expose(image, torch.tensor(2.0))
        with pytest.raises(ValueError, match=r"^gains contains 1 NaN or infinite values$"):
            expose(image, torch.tensor([1.0, math.inf, 1.0]))

    @pytest.mark.parametrize("gain, sigma, name, value", [(-0.01, 0.0, "gain", "-0.01"), (0.0, -0.01, "sigma", "-0.01"),
                                                          (math.nan, 0.0, "gain", "nan"), (0.0, "0.1", "sigma", "'0.1'")])
    def test_poisson_gaussian_exception(self, gain, sigma, name, value):
        # a negative gain made the variance, and so the whole image, NaN
        with pytest.raises(ValueError, match=rf"^{name} must be a finite number >= 0, got {value}$"):
            poisson_gaussian_noise(torch.rand(1, 3, 4, 4), gain, sigma, torch.Generator())

    def test_poisson_gaussian_variance(self):
        image = torch.full((1, 3, 200, 200), 0.5, dtype=torch.float64)
        noisy = poisson_gaussian_noise(image, 2e-3, 0.01, torch.Generator().manual_seed(0))
        assert abs(float(noisy.var()) / (2e-3 * 0.5 + 0.01 ** 2) - 1) < 0.05
        assert abs(float(noisy.mean()) - 0.5) < 1e-3

    def test_quantise_srgb_lattice(self):
        x = torch.rand(1000, dtype=torch.float64) * 1.2
        q = quantise_srgb(x, 8)
        codes = linear_to_srgb(q) * 255
        assert torch.allclose(codes, codes.round(), atol=1e-6)
        assert (linear_to_srgb(q) - linear_to_srgb(x.clamp(0, 1))).abs().max() <= 0.5 / 255 + 1e-9

    @pytest.mark.parametrize("bits", [0, -1, 8.0, True, 17, 200])
    def test_quantise_srgb_bits(self, bits):
        # 0 bits made the image NaN, 200 an OverflowError from inside torch
        with pytest.raises(ValueError, match=rf"^bits must be an integer in \[1, 16\], got {bits!r}$"):
            quantise_srgb(torch.rand(10), bits)


class TestNoiseEstimate:
    @pytest.mark.parametrize("sigma", [0.001, 0.005, 0.02])
    def test_recovers_gaussian_noise_on_smooth_shading(self, sigma):
        yy, xx = torch.meshgrid(torch.linspace(-1, 1, 128), torch.linspace(-1, 1, 128), indexing="ij")
        mask = (xx ** 2 + yy ** 2 < 0.8)[None, None]
        clean = (0.4 + 0.2 * xx + 0.1 * yy - 0.1 * xx * xx).expand(1, 3, -1, -1)
        noisy = clean + sigma * torch.randn(clean.shape, generator=torch.Generator().manual_seed(1))
        assert float(estimate_noise_sigma(noisy, mask)[0]) == pytest.approx(sigma, rel=0.1)

    def test_no_interior(self):
        mask = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        mask[..., 8, 4:12] = True  # a line: no pixel two pixels inside
        assert float(estimate_noise_sigma(torch.rand(1, 3, 16, 16), mask)[0]) == 0.0

    def test_bad_mask(self):
        image = torch.rand(2, 3, 16, 16)
        mask = torch.ones(2, 1, 16, 16, dtype=torch.bool)
        with pytest.raises(ValueError, match="image and mask must have the same batch size"):
            estimate_noise_sigma(image, mask[:1])
        with pytest.raises(ValueError, match="image and mask must have the same batch size"):
            estimate_noise_sigma(image, mask[..., :8])
        with pytest.raises(ValueError, match="mask must be boolean or hold only 0 and 1"):
            estimate_noise_sigma(image, torch.full((2, 1, 16, 16), 0.5))
        with pytest.raises(ValueError, match=r"mask must have shape \(B, 1, H, W\), got \(2, 3, 16, 16\)"):
            estimate_noise_sigma(image, mask.expand(-1, 3, -1, -1))
