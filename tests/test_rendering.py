import math

import pytest
import torch
import trimesh

from sfs_torch.camera import pixel_grid
from sfs_torch.rendering import NormalRender, camera_distance, random_view_rotations, render_normals
from sfs_torch.shapes import normalize_mesh

RES = 256
SCALE = 0.9
FOCAL = 300.0


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=5)


@pytest.fixture(scope="module")
def torus():
    return trimesh.creation.torus(major_radius=0.65, minor_radius=0.35, major_sections=256, minor_sections=128)


def _angles(a, b):
    return torch.rad2deg(torch.acos((a.double() * b.double()).sum(0).clamp(-1, 1)))


def _rays(focal, distance):
    """Camera-frame ray origins and unit directions per pixel, (3, R, R) each."""
    uv = pixel_grid(RES, RES, dtype=torch.float64)
    if focal is None:
        pix = SCALE * RES / 2
        origin = torch.cat([uv / pix, torch.full((1, RES, RES), distance, dtype=torch.float64)])
        direction = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)[:, None, None].expand(3, RES, RES)
    else:
        origin = torch.tensor([0.0, 0.0, distance], dtype=torch.float64)[:, None, None].expand(3, RES, RES)
        direction = torch.cat([uv, torch.full((1, RES, RES), -focal, dtype=torch.float64)])
        direction = direction / direction.norm(dim=0)
    return origin, direction


def _analytic_sphere(focal, distance):
    """Exact unit-sphere hit normals, mask, depth and the ray's distance from the rim."""
    origin, direction = _rays(focal, distance)
    b = (origin * direction).sum(0)
    c = (origin * origin).sum(0) - 1
    disc = b * b - c
    t = -b - disc.clamp_min(0).sqrt()
    point = origin + t * direction
    # closest approach of the ray to the centre, minus the radius
    miss = (c + 1 - b * b).clamp_min(0).sqrt() - 1
    return point, disc > 0, distance - point[2], miss


@pytest.mark.parametrize("focal", [None, FOCAL], ids=["ortho", "persp"])
class TestRenderNormalsSphere:
    def test_normals_depth(self, sphere, focal):
        distance = 3.0 if focal is None else camera_distance(RES, focal, SCALE)
        r = render_normals(sphere, torch.eye(3), RES, focal=focal, scale=SCALE)
        normal, inside, depth, _ = _analytic_sphere(focal, distance)
        both = r.mask[0] & inside
        err = _angles(r.normals, normal)[both]
        assert err.median() < 0.1
        # facet sagitta of a subdivision-5 icosphere is ~2e-4: depth error is of that order
        assert (r.depth[0].double() - depth)[both].abs().median() < 5e-4

    def test_mask_matches_disk(self, sphere, focal):
        distance = 3.0 if focal is None else camera_distance(RES, focal, SCALE)
        r = render_normals(sphere, torch.eye(3), RES, focal=focal, scale=SCALE)
        _, inside, _, miss = _analytic_sphere(focal, distance)
        # the inscribed polyhedron's outline is <= 1e-3 radii inside the circle: only pixel
        # centres that close to the rim may differ
        differ = r.mask[0] != inside
        assert differ.sum() <= 16
        assert (miss[differ].abs() < 1.5e-3).all()
        assert r.mask.sum() == pytest.approx(float(inside.sum()), abs=16)

    def test_outside_zero_inside_unit(self, sphere, focal):
        r = render_normals(sphere, torch.eye(3), 64, focal=focal)
        inside = r.mask[0]
        assert (r.normals[:, ~inside] == 0).all() and (r.depth[:, ~inside] == 0).all()
        assert torch.allclose(r.normals[:, inside].norm(dim=0), torch.ones(()), atol=1e-6)
        assert r.normals.dtype == torch.float32 and r.mask.dtype == torch.bool
        assert isinstance(r, NormalRender)


@pytest.mark.parametrize("focal", [None, FOCAL], ids=["ortho", "persp"])
class TestRenderNormalsTorus:
    def test_rotated_torus(self, torus, focal):
        gen = torch.Generator().manual_seed(3)
        rot = random_view_rotations(1, gen)[0]
        distance = 3.0 if focal is None else camera_distance(RES, focal, SCALE)
        r = render_normals(torus, rot, RES, focal=focal, scale=SCALE)
        # surface point from the rendered depth, back to the world frame
        origin, direction = _rays(focal, distance)
        t = r.depth[0].double() / -direction[2]
        point = torch.einsum("ij,ihw->jhw", rot, origin + t * direction)
        # analytic torus normal at that point: away from the nearest core-circle point
        ring = point[:2] / point[:2].norm(dim=0).clamp_min(1e-12) * 0.65
        normal = point - torch.cat([ring, torch.zeros_like(ring[:1])])
        normal = torch.einsum("ij,jhw->ihw", rot, normal / normal.norm(dim=0))
        m = r.mask[0]
        err = _angles(r.normals, normal)[m]
        assert m.sum() > 0.2 * RES * RES
        assert err.median() < 0.1
        # depth is consistent: every hit lies inside the torus' bounding sphere (radius 1)
        assert (point.norm(dim=0)[m] < 1.0 + 1e-3).all()


class TestRenderNormals:
    def test_inverted_winding_faces_camera(self, sphere):
        inverted = trimesh.Trimesh(sphere.vertices, sphere.faces[:, ::-1], process=False)
        a = render_normals(sphere, torch.eye(3), 48)
        b = render_normals(inverted, torch.eye(3), 48)
        assert torch.equal(a.mask, b.mask)
        assert torch.allclose(a.normals, b.normals, atol=1e-6)
        assert (b.normals[2][b.mask[0]] >= 0).all()

    def test_rotation_moves_view(self):
        box = normalize_mesh(trimesh.creation.box(extents=[1.0, 2.0, 1.0]))  # flat faces
        rot = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # world y -> camera z
        r = render_normals(box, rot, 32)
        centre = r.normals[:, 14, 13]
        assert torch.allclose(centre, torch.tensor([0.0, 0.0, 1.0]), atol=1e-6)
        # a numpy rotation gives the same image
        assert torch.equal(render_normals(box, rot.numpy(), 32).normals, r.normals)

    def test_scale_frames_unit_sphere(self, sphere):
        r = render_normals(sphere, torch.eye(3), 100, scale=0.5)
        row = r.mask[0, 50]
        assert int(row.sum()) == pytest.approx(50, abs=1)

    def test_exception(self, sphere):
        with pytest.raises(ValueError, match="rotation"):
            render_normals(sphere, torch.eye(3) * 2, 16)
        with pytest.raises(ValueError, match="rotation"):
            render_normals(sphere, torch.eye(4), 16)
        with pytest.raises(ValueError, match="rotation"):
            render_normals(sphere, -torch.eye(3), 16)
        with pytest.raises(ValueError, match="resolution"):
            render_normals(sphere, torch.eye(3), 0)
        with pytest.raises(ValueError, match="focal"):
            render_normals(sphere, torch.eye(3), 16, focal=-1.0)
        with pytest.raises(ValueError, match="scale"):
            render_normals(sphere, torch.eye(3), 16, scale=0.0)

    def test_scene_refused(self, sphere):
        # a .glb loads as a Scene, which has no ray intersector
        with pytest.raises(TypeError, match=r"got Scene \(for a trimesh.Scene, pass scene.to_mesh\(\)"):
            render_normals(trimesh.Scene(sphere), torch.eye(3), 16)

    @pytest.mark.parametrize("kwargs, match", [
        (dict(focal=math.inf), "focal must be a positive focal length in pixels, got inf"),
        (dict(scale=math.inf), "scale must be a finite positive number, got inf"),
        (dict(distance=0.5), r"distance must be a finite number > 1 \(outside the unit sphere\), got 0.5"),
        (dict(distance=1.0), r"distance must be a finite number > 1 \(outside the unit sphere\), got 1.0"),
        (dict(distance=math.inf), "distance must be a finite number > 1 .*, got inf"),
        (dict(focal=50.0, distance=0.5), "distance must be a finite number > 1 .*, got 0.5"),
    ])
    def test_bad_camera(self, sphere, kwargs, match):
        with pytest.raises(ValueError, match=match):
            render_normals(sphere, torch.eye(3), 16, **kwargs)


class TestCameraDistance:
    def test_outline_radius(self):
        d = camera_distance(200, 400.0, 0.8)
        # tangent cone of the unit sphere: half-angle asin(1/d) -> 80 px at f = 400
        assert 400.0 * math.tan(math.asin(1 / d)) == pytest.approx(80.0)


class TestRandomViewRotations:
    def test_rotations(self):
        rot = random_view_rotations(500, torch.Generator().manual_seed(0))
        assert rot.shape == (500, 3, 3)
        eye = torch.eye(3, dtype=rot.dtype).expand(500, 3, 3)
        assert torch.allclose(rot @ rot.transpose(1, 2), eye, atol=1e-12)
        assert torch.allclose(torch.linalg.det(rot), torch.ones(500, dtype=rot.dtype))

    def test_uniform_view_directions(self):
        rot = random_view_rotations(20000, torch.Generator().manual_seed(1))
        view = rot[:, 2]  # world direction of the camera's z axis
        assert view.mean(0).abs().max() < 0.02  # 4 sigma of the mean for n = 20000
        assert torch.allclose((view**2).mean(0), torch.full((3,), 1 / 3, dtype=view.dtype), atol=0.01)
        # uniform on the sphere: z is uniform on [-1, 1]
        hist = torch.histc(view[:, 2].float(), bins=10, min=-1, max=1)
        assert (hist - 2000).abs().max() < 200

    def test_deterministic(self):
        a = random_view_rotations(4, torch.Generator().manual_seed(5))
        b = random_view_rotations(4, torch.Generator().manual_seed(5))
        assert torch.equal(a, b)

    def test_exception(self):
        with pytest.raises(ValueError, match="n must"):
            random_view_rotations(-1, torch.Generator())
