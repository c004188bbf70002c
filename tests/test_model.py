from dataclasses import replace

import pytest
import torch
from test_pipeline import TINY, scene  # noqa: F401  (the shared sphere fixture)

import sfs_torch
from sfs_torch import geometry_db, pipeline
from sfs_torch.geometry_db import DatabaseConfig, GeometryDatabase
from sfs_torch.model import ShapeFromShading
from sfs_torch.pipeline import Estimate, PipelineConfig, estimate, resolve_config

# TINY without the stages that cost seconds on a CPU (photometric refinement, refit round)
FAST = dict(TINY, refine={"when": "never"}, refine_rounds=0, keep_prior=False)


@pytest.fixture(scope="module")
def tiny_estimates(scene):
    """The module's and the function's estimate of the same image, with TINY."""
    _, mask, _, image = scene
    return ShapeFromShading(TINY, progress=False)(image, mask), estimate(image, mask, config=TINY, progress=False)


def assert_same_estimate(a: Estimate, b: Estimate) -> None:
    for name in ("normals", "confidence", "lighting", "depth", "mask"):
        x, y = getattr(a, name), getattr(b, name)
        if y is None:
            assert x is None, name
        else:
            torch.testing.assert_close(x, y, rtol=0, atol=0, msg=lambda m: f"{name}: {m}")


class TestShapeFromShading:
    def test_smoke(self, scene, tiny_estimates):
        normals, mask, _, _ = scene
        est, _ = tiny_estimates
        assert isinstance(est, Estimate)
        assert est.normals.shape == (3, 64, 64) and est.confidence.shape == (1, 64, 64)
        # an estimated lighting's joint refinement fits a surface: its depth map
        assert est.lighting.shape == (3, 9) and est.depth.shape == (1, 64, 64)
        norms = est.normals.norm(dim=0)[mask[0]]
        torch.testing.assert_close(norms, torch.ones_like(norms))
        # the sphere's normals, roughly (test_pipeline measures the accuracy)
        cos = (est.normals * normals).sum(0)[mask[0]]
        assert float(torch.rad2deg(torch.acos(cos.clamp(-1, 1))).median()) < 10.0

    def test_config(self):
        model = ShapeFromShading(TINY, progress=False)
        assert model.config == resolve_config(TINY) and isinstance(model.config, PipelineConfig)
        assert model.config.forest.n_trees == TINY["forest"]["n_trees"]
        assert ShapeFromShading(resolve_config(TINY)).config == model.config
        assert ShapeFromShading().config == PipelineConfig()
        assert "database='blobby'" in repr(model)
        assert sfs_torch.ShapeFromShading is ShapeFromShading

    def test_holds_no_parameters(self):
        # no parameters or buffers, even with the database held: .to() has nothing to move,
        # the input's device rules, and state_dict() stays empty
        model = ShapeFromShading(TINY, progress=False)
        model.database()
        assert model.to("cpu") is model and model.to(torch.float64) is model
        assert list(model.parameters()) == [] and list(model.buffers()) == [] and model.state_dict() == {}

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, scene, batch):
        _, mask, _, image = scene
        small_image = torch.nn.functional.avg_pool2d(image, 2)
        small_mask = torch.nn.functional.avg_pool2d(mask[None].float(), 2)[0] > 0.5
        images = torch.stack([small_image, small_image.flip(-1), small_image.flip(-2)][:batch])
        masks = torch.stack([small_mask, small_mask.flip(-1), small_mask.flip(-2)][:batch])
        est = ShapeFromShading(FAST, progress=False)(images, masks)
        assert est.normals.shape == (batch, 3, 32, 32) and est.confidence.shape == (batch, 1, 32, 32)
        assert est.lighting.shape == (batch, 3, 9) and est.mask.shape == (batch, 1, 32, 32)
        assert float(est.normals[~masks.expand(-1, 3, -1, -1)].abs().max()) == 0.0

    def test_exception(self, scene):
        _, mask, _, image = scene
        with pytest.raises(ValueError, match="config"):
            ShapeFromShading({"forest": {"n_tree": 3}})
        model = ShapeFromShading(TINY, progress=False)
        with pytest.raises(ValueError, match="image"):
            model(image[:2], mask)
        with pytest.raises(ValueError, match="mask"):
            model(image, mask[:, :32])
        with pytest.raises(ValueError, match="integrate"):
            model(image, mask, integrate="l3")
        with pytest.raises(ValueError, match="focal"):
            model(image, mask, focal=-5.0)
        with pytest.raises(ValueError, match="lighting"):
            model(image, mask, lighting=torch.zeros(3, 4))

    @pytest.mark.skip(
        reason="not differentiable: the forest routes each pixel by hard thresholds on its features, so the "
        "normals are piecewise constant in the image; its leaf statistics carry no gradient"
    )
    def test_gradcheck(self):
        pass

    def test_module(self, tiny_estimates):
        # the module is estimate() with its config: identical output on the same input
        assert_same_estimate(*tiny_estimates)

    def test_module_keywords(self, scene):
        # camera, known lighting and integration reach estimate() unchanged
        _, mask, sh, image = scene
        kwargs = dict(lighting=sh, focal=60.0, principal_point=(31.0, 33.0), integrate="l2")
        got = ShapeFromShading(FAST, progress=False)(image, mask, **kwargs)
        expected = estimate(image, mask, config=FAST, progress=False, **kwargs)
        assert got.depth is not None
        assert_same_estimate(got, expected)

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")
    def test_cuda_end_to_end(self, scene):
        _, mask, sh, image = scene
        model = ShapeFromShading(TINY, progress=False).to("cuda")
        image, mask = image.cuda(), mask.cuda()
        for kwargs in (dict(integrate="l2"), dict(lighting=sh.cuda(), focal=60.0)):
            est = model(image, mask, **kwargs)
            for name in ("normals", "confidence", "lighting", "depth", "mask"):
                value = getattr(est, name)
                if value is not None:
                    assert value.is_cuda, f"{name} is on {value.device} with {kwargs}"
                    assert bool(torch.isfinite(value.float()).all()), name
            norms = est.normals.norm(dim=0)[mask[0]]
            torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-4, rtol=0)


@pytest.fixture()
def load_calls(monkeypatch):
    """Configs that the geometry database was loaded for; estimate() must not load it itself."""
    calls = []
    load = geometry_db.load_database

    def counting(cfg, **kwargs):
        calls.append(replace(cfg))
        return load(cfg, **kwargs)

    monkeypatch.setattr(geometry_db, "load_database", counting)
    monkeypatch.setattr(pipeline, "load_database", lambda *a, **k: pytest.fail("estimate() loaded the database"))
    return calls


class TestDatabaseHeldOnce:
    """The module loads the example-geometry database once and passes it to estimate() (needs estimate(database=))."""

    def test_loaded_once(self, scene, load_calls):
        _, mask, sh, image = scene
        model = ShapeFromShading(FAST, progress=False)
        first = model(image, mask, lighting=sh)
        second = model(image, mask, lighting=sh)
        model(image.numpy().transpose(1, 2, 0), mask)  # a numpy image: the CPU copy too
        assert load_calls == [DatabaseConfig(**TINY["database"])]
        assert_same_estimate(first, second)
        assert model.database() is model.database("cpu") is model.database(torch.device("cpu"))

    def test_same_as_estimate(self, scene, load_calls):
        # the held database gives what estimate() gives when it loads the file itself
        _, mask, sh, image = scene
        model = ShapeFromShading(FAST, progress=False)
        got = model(image, mask, lighting=sh)
        expected = estimate(image, mask, lighting=sh, config=FAST, progress=False,
                            database=geometry_db.load_database(model.config.database, progress=False))
        assert_same_estimate(got, expected)

    def test_config_change_and_clear(self, load_calls):
        model = ShapeFromShading(TINY, progress=False)
        db = model.database()
        assert isinstance(db, GeometryDatabase) and model.database() is db and len(load_calls) == 1
        model.config.database.seed = 1  # another database: the held one is dropped
        assert model.database() is not db and load_calls[-1].seed == 1 and len(load_calls) == 2
        model.clear_database()
        model.database()
        assert len(load_calls) == 3

    def test_on_the_input_device(self, device, load_calls):
        model = ShapeFromShading(TINY, progress=False)
        db = model.database(device)
        fields = (db.normals, db.masks, db.silhouette, db.shape_id, db.view_id)
        assert all(t.device.type == device.type for t in fields)
        assert model.database(device) is db and len(load_calls) == 1
        torch.testing.assert_close(db.normals.cpu(), model.database().normals, rtol=0, atol=0)

    @pytest.mark.parametrize("bad, message", [
        ("foo", r"^device must be a torch.device or a name such as 'cpu' or 'cuda:0', got 'foo'$"),
        (3.5, r"^device must be a torch.device .*got 3.5$"),
    ])
    def test_a_bad_device_is_refused_before_loading(self, bad, message, load_calls):
        with pytest.raises(ValueError, match=message):
            ShapeFromShading(TINY, progress=False).database(bad)
        assert load_calls == []

    @pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
    def test_cuda_without_cuda_is_refused_before_loading(self, load_calls):
        with pytest.raises(ValueError, match=r"^device 'cuda': torch .* sees no CUDA device here$"):
            ShapeFromShading(TINY, progress=False).database("cuda")
        assert load_calls == []

    def test_estimate_checks_the_database(self, scene):
        _, mask, sh, image = scene
        db = geometry_db.load_database(DatabaseConfig(**TINY["database"]), progress=False)
        smaller = replace(db, normals=db.normals[:, :, 1:-1, 1:-1], masks=db.masks[:, :, 1:-1, 1:-1])
        with pytest.raises(ValueError, match="database.normals"):
            estimate(image, mask, lighting=sh, config=FAST, progress=False, database=smaller)
        with pytest.raises(ValueError, match="n_shapes"):
            estimate(image, mask, lighting=sh, config=dict(FAST, database=dict(TINY["database"], n_shapes=3)),
                     progress=False, database=db)
        with pytest.raises(TypeError, match="GeometryDatabase"):
            estimate(image, mask, lighting=sh, config=FAST, progress=False, database=db.normals)
