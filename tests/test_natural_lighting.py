import math

import pytest
import torch

from sfs_torch.lighting import natural_lightings, render_sphere
from sfs_torch.natural_lighting import (
    environment_maps,
    environment_to_sh,
    equirect_directions,
    lighting_prior_energy,
    load_lighting_prior,
    normalise_lighting,
)


class TestLightingPrior:
    def test_loads_finite_and_positive_definite(self):
        prior = load_lighting_prior(dtype=torch.float64)
        assert prior.mean.shape == (3, 9) and prior.precision.shape == (27, 27)
        assert bool(torch.isfinite(prior.mean).all()) and bool(torch.isfinite(prior.precision).all())
        assert torch.allclose(prior.precision, prior.precision.T)
        assert float(torch.linalg.eigvalsh(prior.precision).min()) > 0
        # the prior lives on lightings scaled to unit RMS coefficient, with a positive DC term
        assert 0.8 < float(prior.mean.square().mean().sqrt()) <= 1.0
        assert bool((prior.mean[:, 0] > 0).all())

    def test_energy_is_scale_free_and_lowest_near_the_mean(self):
        prior = load_lighting_prior(dtype=torch.float64)
        maps = environment_maps().sh.double()
        assert float(lighting_prior_energy(prior.mean[None], prior)[0]) < float(lighting_prior_energy(maps, prior).min())
        sh = natural_lightings()["campus_sunset"].double()[None]
        assert torch.allclose(lighting_prior_energy(sh, prior), lighting_prior_energy(3.7 * sh, prior))

    def test_natural_lightings_are_likelier_than_unnatural_ones(self):
        prior = load_lighting_prior()
        natural = torch.stack(list(natural_lightings().values()))
        # light from below, blue above and red below: far from any map the prior saw
        unnatural = natural.clone()
        unnatural[:, :, 1] = -unnatural[:, :, 1]
        unnatural[:, 0, 1:] *= 4
        assert float(lighting_prior_energy(natural, prior).median()) < float(lighting_prior_energy(unnatural, prior).min())

    def test_gradcheck(self):
        prior = load_lighting_prior(dtype=torch.float64)
        sh = natural_lightings()["grace_cathedral"].double()[None].requires_grad_(True)
        assert torch.autograd.gradcheck(lambda s: lighting_prior_energy(s, prior), (sh,))

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_zero_lighting_has_a_finite_gradient(self, dtype):
        sh = torch.zeros(1, 3, 9, dtype=dtype, requires_grad=True)
        lighting_prior_energy(sh, load_lighting_prior(dtype=dtype)).sum().backward()
        assert bool(torch.isfinite(sh.grad).all())
        sh.grad = None
        normalise_lighting(sh).sum().backward()
        assert torch.equal(sh.grad, torch.ones_like(sh))

    def test_prior_takes_the_dtype_of_sh(self):
        sh = natural_lightings()["grace_cathedral"][None]
        energy = lighting_prior_energy(sh.double(), load_lighting_prior())
        assert energy.dtype == torch.float64
        torch.testing.assert_close(energy, lighting_prior_energy(sh.double(), load_lighting_prior(dtype=torch.float64)))

    def test_impossible_lightings_get_a_finite_high_energy(self):
        prior = load_lighting_prior()
        sh = natural_lightings()["campus_sunset"][None]
        negative = sh.clone()
        negative[:, :, 0] = -negative[:, :, 0]  # a negative constant term, as an unconstrained fit can give
        energies = lighting_prior_energy(torch.cat([sh, negative, torch.zeros_like(sh)]), prior)
        assert bool(torch.isfinite(energies).all())
        assert float(energies[1]) > 10 * float(energies[0])
        assert torch.allclose(normalise_lighting(sh).square().mean().sqrt(), torch.tensor(1.0))

    def test_normalise_rejects_bad_shape(self):
        with pytest.raises(ValueError, match="sh"):
            normalise_lighting(torch.ones(3, 9))


class TestEnvironmentMaps:
    def test_shipped_maps(self):
        env = environment_maps()
        assert len(env.names) == 8 and env.maps.shape == (8, 32, 64, 3) and env.sh.shape == (8, 3, 9)
        assert bool((env.maps >= 0).all()) and bool(torch.isfinite(env.maps).all())
        # the shipped SH were projected from the full-resolution maps: the 32 x 64 copies agree
        # (the interior's small bright lamps lose most to the area averaging)
        assert torch.allclose(normalise_lighting(environment_to_sh(env.maps)), env.sh, atol=0.06)

    def test_solid_angles_cover_the_sphere(self):
        d, solid_angle = equirect_directions(16, 32)
        assert float(solid_angle.sum()) == pytest.approx(4 * math.pi, rel=1e-2)
        assert torch.allclose(d.norm(dim=-1), torch.ones(16, 32, dtype=torch.float64))
        assert float(d[0, 0, 1]) > 0.99  # row 0 looks up

    def test_uniform_environment_renders_albedo(self):
        sh = environment_to_sh(torch.ones(1, 32, 64, 3), albedo=0.6)
        sphere = render_sphere(sh, 32)[0]
        inside = sphere[0] > 0
        assert torch.allclose(sphere[:, inside], torch.full_like(sphere[:, inside], 0.6), atol=5e-3)

    def test_light_from_above_lights_upward_normals(self):
        maps = torch.zeros(1, 32, 64, 3)
        maps[:, :4] = 1.0  # a bright cap around +y
        sh = environment_to_sh(maps)
        image = render_sphere(sh, 33)[0, 0]
        assert float(image[2, 16]) > 5 * float(image[30, 16])  # the top of the sphere is brighter

    def test_rejects_bad_maps(self):
        with pytest.raises(ValueError, match="maps"):
            environment_to_sh(torch.ones(32, 64, 3))
