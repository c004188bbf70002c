
import pytest
import torch
import trimesh

from sfs_torch.integrability import depth_to_mesh
from sfs_torch.lighting import natural_lightings, render_sh
from sfs_torch.novel_view import render_novel_view, view_rotation


def hemisphere_depth(size=64, radius=28.0):
    c = torch.arange(size, dtype=torch.float64) + 0.5 - size / 2
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    r2 = (xx**2 + yy**2) / radius**2
    mask = r2 < 1
    depth = radius * torch.sqrt((1 - r2).clamp_min(0)) * mask
    return depth[None], mask[None]


class TestViewRotation:
    def test_is_rotation_and_turns_the_view(self):
        rot = view_rotation(90.0, 0.0)
        assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
        # after a quarter turn the original right (+x) points towards the new camera (+z)
        assert torch.allclose(rot @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=1e-12)


class TestRenderNovelView:
    def test_frontal_view_of_a_hemisphere_matches_sh_shading(self):
        depth, mask = hemisphere_depth()
        mesh = depth_to_mesh(depth, mask)
        sh = natural_lightings(0.6)["grace_cathedral"]
        image = render_novel_view(mesh, sh, azimuth_deg=0.0, elevation_deg=0.0, resolution=64, background=0.0)
        # the frontal view of a unit hemisphere is a disk shaded like a sphere
        c = (torch.arange(64, dtype=torch.float32) + 0.5) / 32 - 1
        y, x = torch.meshgrid(-c, c, indexing="ij")
        r2 = x * x + y * y
        inner = r2 < 0.6**2  # away from the tessellated rim
        # render_normals frames the unit sphere at 0.9 of the half-size
        xs, ys = x / 0.9, y / 0.9
        rs = xs * xs + ys * ys
        ns = torch.stack([xs, ys, torch.sqrt((1 - rs).clamp_min(0))])[None]
        expected = render_sh(ns, sh[None])[0].clamp(0, 1)
        assert (image - expected)[:, inner].abs().median() < 0.01

    def test_exception(self):
        depth, mask = hemisphere_depth(16, 6.0)
        with pytest.raises(ValueError, match="lighting"):
            render_novel_view(depth_to_mesh(depth, mask), torch.zeros(9))

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_lighting(self, bad):
        depth, mask = hemisphere_depth(16, 6.0)
        sh = natural_lightings(0.6)["grace_cathedral"].clone()
        sh[1, 4] = bad
        with pytest.raises(ValueError, match="lighting contains 1 NaN or infinite values"):
            render_novel_view(depth_to_mesh(depth, mask), sh, resolution=16, renderer="embree")

    def test_a_scene_is_refused(self):
        depth, mask = hemisphere_depth(16, 6.0)
        scene = trimesh.Scene(depth_to_mesh(depth, mask))  # what trimesh.load returns for a .glb
        sh = natural_lightings(0.6)["grace_cathedral"]
        with pytest.raises(TypeError, match=r"mesh must be a trimesh.Trimesh, got Scene \(for a trimesh.Scene, pass "
                                            r"scene.to_mesh\(\)"):
            render_novel_view(scene, sh, resolution=16, renderer="embree")
        assert render_novel_view(scene.to_mesh(), sh, resolution=16, renderer="embree").shape == (3, 16, 16)
