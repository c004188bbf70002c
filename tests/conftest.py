import os

# as the command does (sfs_torch.cli): spinning OpenMP threads slow a loaded 2-core runner
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
import torch  # noqa: E402


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="run slow accuracy tests")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: accuracy runs on disjoint train/test shapes")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="needs --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))])
def device(request):
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request):
    return request.param


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    # Tests never touch the user's cache: every session gets its own.
    monkeypatch.setenv("SFS_TORCH_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture()
def database_loads(monkeypatch):
    """The configs of every ``load_database`` call during the test, whoever makes it."""
    import sfs_torch.evaluate as evaluate
    import sfs_torch.geometry_db as geometry_db
    import sfs_torch.pipeline as pipeline

    loads = []
    original = geometry_db.load_database

    def counted(cfg, **kwargs):
        loads.append(cfg)
        return original(cfg, **kwargs)

    monkeypatch.setattr(geometry_db, "load_database", counted)
    monkeypatch.setattr(pipeline, "load_database", counted)  # estimate()'s own import of it
    monkeypatch.setattr(evaluate, "load_database", counted)  # and sfs-torch-eval's
    return loads
