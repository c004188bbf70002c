import os

import pytest

from sfs_torch._openmp import SPIN_COUNT, short_openmp_waits


@pytest.fixture
def clean_environment(monkeypatch):
    for name in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_short_spin_waits_when_the_user_chose_nothing(clean_environment):
    short_openmp_waits()
    assert os.environ["GOMP_SPINCOUNT"] == str(SPIN_COUNT) == "3000"
    # for OpenMP runtimes other than libgomp, which ignore GOMP_SPINCOUNT
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"


@pytest.mark.parametrize("name, value", [("OMP_WAIT_POLICY", "PASSIVE"), ("OMP_WAIT_POLICY", "ACTIVE"),
                                         ("GOMP_SPINCOUNT", "100")])
def test_a_users_choice_is_left_alone(clean_environment, name, value):
    clean_environment.setenv(name, value)
    short_openmp_waits()
    assert os.environ[name] == value
    assert [n for n in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if n in os.environ] == [name]
