import math

import numpy as np
import pytest
import torch
import trimesh

import sfs_torch.preview as preview
from sfs_torch.integrability import depth_to_mesh
from sfs_torch.lighting import natural_lightings, render_sh, rotate_sh
from sfs_torch.novel_view import view_rotation
from sfs_torch.preview import (
    GLContext,
    choose_renderer,
    gl_context,
    rasterize_normals,
    render_shaded,
)
from sfs_torch.rendering import render_normals

NO_CONTEXT = GLContext(False, "egl", None, "no OpenGL context on egl: EGLError: no display")
SH = natural_lightings(0.7)["grace_cathedral"]


@pytest.fixture(scope="module")
def gl():
    """The process's OpenGL context; the pyrender checks skip, saying why, where none can be made."""
    context = gl_context()
    if not context.available:
        pytest.skip(f"no offscreen OpenGL context for pyrender here: {context.reason}")
    return context


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=5)


def unit_disk(size, scale=0.9):
    c = (torch.arange(size, dtype=torch.float64) + 0.5 - size / 2) / (scale * size / 2)
    y, x = torch.meshgrid(-c, c, indexing="ij")
    return (x * x + y * y).sqrt()


def angles_deg(a, b, mask):
    return torch.rad2deg(torch.acos((a * b).sum(0)[mask[0]].clamp(-1, 1)))


class TestChooseRenderer:
    def test_embree_needs_no_context(self, monkeypatch):
        monkeypatch.setattr(preview, "gl_context", lambda: pytest.fail("embree must not make a context"))
        choice = choose_renderer("embree")
        assert (choice.name, choice.requested) == ("embree", "embree")

    def test_auto_falls_back_and_says_why(self):
        choice = choose_renderer("auto", NO_CONTEXT)
        assert choice.name == "embree" and choice.requested == "auto"
        assert "ray caster" in choice.reason and "EGLError: no display" in choice.reason

    def test_auto_takes_pyrender_with_a_context(self):
        choice = choose_renderer("AUTO", GLContext(True, "egl", "llvmpipe"))
        assert choice.name == "pyrender" and "egl" in choice.reason and "llvmpipe" in choice.reason

    def test_pyrender_without_a_context_is_one_clear_error(self):
        with pytest.raises(ValueError, match="renderer=pyrender needs an offscreen OpenGL context, but no OpenGL context on egl"):
            choose_renderer("pyrender", NO_CONTEXT)

    @pytest.mark.parametrize("value", ["vulkan", "", None, 3])
    def test_unknown_name(self, value):
        with pytest.raises(ValueError, match=r"renderer must be one of auto, pyrender, embree, got"):
            choose_renderer(value, NO_CONTEXT)


class TestGLContext:
    def test_cached_per_process(self):
        assert gl_context() is gl_context()

    def test_without_pyrender_says_how_to_install(self, monkeypatch):
        monkeypatch.setattr(preview.importlib.util, "find_spec", lambda name, *args: None)
        context = preview._probe()
        assert not context.available and "pip install 'sfs-torch[render]'" in context.reason

    def test_a_forked_child_gets_no_context(self, monkeypatch):
        # the parent's context cannot be used, nor a new one made (Mesa's EGL deadlocks)
        parent = {"pid": -1, "renderer": object(), "context": GLContext(True, "egl", "llvmpipe")}
        monkeypatch.setattr(preview, "_STATE", parent)
        monkeypatch.setattr(preview, "_INHERITED", [])
        context = gl_context()
        assert not context.available and "forked" in context.reason
        assert choose_renderer("auto").name == "embree" and len(preview._INHERITED) == 1

    def test_auto_falls_back_to_the_ray_caster(self, monkeypatch, sphere):
        monkeypatch.setattr(preview, "gl_context", lambda: NO_CONTEXT)
        view = render_shaded(sphere, SH, torch.eye(3), 48)
        ray = render_shaded(sphere, SH, torch.eye(3), 48, renderer="embree")
        assert view.renderer == "embree" and torch.equal(view.image, ray.image)
        with pytest.raises(ValueError, match="needs an offscreen OpenGL context"):
            render_shaded(sphere, SH, torch.eye(3), 48, renderer="pyrender")
        with pytest.raises(ValueError, match="needs an offscreen OpenGL context"):
            rasterize_normals(sphere, torch.eye(3), 48)


class TestRenderShaded:
    def test_embree_is_the_ray_caster_shaded(self, sphere):
        rot = view_rotation(35.0, 20.0)
        view = render_shaded(sphere, SH, rot, 64, renderer="embree", background=0.25)
        ray = render_normals(sphere, rot, 64)
        expected = render_sh(ray.normals[None], rotate_sh(SH.double(), rot).float()[None])[0].clamp(0, 1)
        assert torch.equal(view.mask, ray.mask) and torch.equal(view.normals, ray.normals)
        assert torch.allclose(view.image[:, ray.mask[0]], expected[:, ray.mask[0]], atol=1e-6)
        assert bool((view.image[:, ~ray.mask[0]] == 0.25).all())

    def test_shading_follows_the_light_under_rotation(self, sphere):
        # a sphere looks the same from every side when the light turns with the camera
        rot = view_rotation(60.0, -30.0)
        front = render_shaded(sphere, SH, torch.eye(3), 64, renderer="embree")
        turned = render_shaded(sphere, rotate_sh(SH.double(), rot.T).float(), rot, 64, renderer="embree")
        both = (front.mask & turned.mask)[0]
        assert (front.image - turned.image)[:, both].abs().median() < 1e-3

    def test_exception(self, sphere):
        with pytest.raises(ValueError, match="lighting"):
            render_shaded(sphere, torch.zeros(9), torch.eye(3), 16)
        with pytest.raises(ValueError, match="renderer must be one of"):
            render_shaded(sphere, SH, torch.eye(3), 16, renderer="opengl")
        with pytest.raises(ValueError, match="rotation"):
            render_shaded(sphere, SH, 2 * torch.eye(3), 16, renderer="embree")
        with pytest.raises(ValueError, match="resolution"):
            render_shaded(sphere, SH, torch.eye(3), 0, renderer="embree")

    def test_non_finite_lighting_and_a_scene_are_refused(self, sphere):
        bad = SH.clone()
        bad[0, 0] = float("nan")
        with pytest.raises(ValueError, match="lighting contains 1 NaN or infinite values"):
            render_shaded(sphere, bad, torch.eye(3), 16, renderer="embree")
        with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh, got Scene"):
            render_shaded(trimesh.Scene(sphere), SH, torch.eye(3), 16, renderer="embree")


class TestRasterizeNormals:
    """pyrender against the ray caster and the analytic sphere (figures: docs/rendering.md)."""

    @pytest.mark.parametrize("focal", [None, 300.0], ids=["ortho", "persp"])
    def test_sphere_agrees_with_the_ray_caster(self, gl, sphere, focal):
        rot = view_rotation(35.0, 20.0)
        raster = rasterize_normals(sphere, rot, 256, focal=focal)
        ray = render_normals(sphere, rot, 256, focal=focal)
        assert raster.normals.shape == (3, 256, 256) and raster.mask.dtype == torch.bool
        # measured: 99.82-99.83 % of the pixels, 112-116 of 65536 differ, all on the rim
        assert (raster.mask == ray.mask).float().mean() > 0.995
        both = raster.mask & ray.mask
        angle = angles_deg(raster.normals, ray.normals, both)
        # measured: median 0.17 deg (8-bit normals), 99th percentile 0.35-0.37 deg
        assert angle.median() < 0.3 and angle.quantile(0.99) < 1.0
        assert torch.allclose(raster.normals[:, both[0]].norm(dim=0), torch.ones(1), atol=1e-5)
        assert bool((raster.normals[:, ~raster.mask[0]] == 0).all())

    def test_sphere_mask_is_the_disk(self, gl, sphere):
        raster = rasterize_normals(sphere, torch.eye(3), 256)
        r = unit_disk(256)
        wrong = raster.mask[0] != (r < 1)
        # coverage of 2 of 4 samples: measured ~100 rim pixels, all within 0.3 px of the circle
        assert int(wrong.sum()) < 0.3 * 2 * math.pi * 0.9 * 128
        assert float((r[wrong] - 1).abs().max()) * 0.9 * 128 < 0.5
        assert raster.coverage.min() >= 0 and raster.coverage.max() <= 1
        assert float(raster.coverage[0, 128, 128]) == 1.0 and float(raster.coverage[0, 0, 0]) == 0.0

    def test_back_faces_of_an_open_surface_face_the_camera(self, gl):
        # a hemisphere's depth-map mesh seen from behind and from the side: like the ray
        # caster, every normal is flipped to face the camera (n_z > 0, orthographic)
        c = torch.arange(48, dtype=torch.float64) + 0.5 - 24
        yy, xx = torch.meshgrid(c, c, indexing="ij")
        r2 = (xx**2 + yy**2) / 20.0**2
        mask = (r2 < 1)[None]
        mesh = depth_to_mesh(20.0 * torch.sqrt((1 - r2).clamp_min(0))[None] * mask, mask)
        mesh.apply_translation(-mesh.bounds.mean(0))
        mesh.apply_scale(1.0 / np.linalg.norm(mesh.vertices, axis=1).max())
        for azimuth in (180.0, 80.0):
            rot = view_rotation(azimuth, 10.0)
            raster, ray = rasterize_normals(mesh, rot, 96), render_normals(mesh, rot, 96)
            assert bool((raster.normals[2][raster.mask[0]] >= 0).all())
            assert (raster.mask == ray.mask).float().mean() > 0.99
            assert angles_deg(raster.normals, ray.normals, raster.mask & ray.mask).median() < 0.5

    def test_shading_within_a_tolerance_of_the_ray_caster(self, gl, sphere):
        rot = view_rotation(35.0, 20.0)
        a = render_shaded(sphere, SH, rot, 256, renderer="pyrender")
        b = render_shaded(sphere, SH, rot, 256, renderer="embree")
        assert (a.renderer, b.renderer) == ("pyrender", "embree")
        both = (a.mask & b.mask)[0]
        diff = (a.image - b.image)[:, both].abs()
        # measured: median 2e-4, 99th percentile 1e-3 (an 8-bit PNG step is 4e-3)
        assert diff.median() < 1e-3 and diff.flatten().quantile(0.99) < 5e-3

    def test_auto_takes_pyrender(self, gl, sphere):
        assert render_shaded(sphere, SH, torch.eye(3), 32).renderer == "pyrender"
        assert choose_renderer("auto").name == "pyrender"

    def test_exception(self, gl, sphere):
        with pytest.raises(ValueError, match="rotation"):
            rasterize_normals(sphere, torch.ones(3, 3), 16)
        with pytest.raises(ValueError, match="focal"):
            rasterize_normals(sphere, torch.eye(3), 16, focal=-1.0)
        with pytest.raises(ValueError, match="no faces"):
            rasterize_normals(trimesh.Trimesh(), torch.eye(3), 16)
