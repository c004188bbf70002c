"""The benchmark scripts' own argument checks (their measurements are in docs/, not in tests)."""
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.mark.parametrize("script, arguments", [
    ("tune.py", ["--exposure", "0.2"]),
    ("tune.py", ["--light-seed", "3"]),
    ("bas_relief.py", ["--exposure", "0.2"]),
])
def test_validation_side_options_are_refused_on_the_test_side(script, arguments):
    # the test side's R&H probes keep their own exposure and orientation: the option used to be ignored
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), "--side", "test", *arguments],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "for the validation side" in done.stderr


def test_bas_relief_refuses_a_negative_lighting_prior_weight():
    # a negative weight would reward improbable lightings: refused before any image is made
    done = subprocess.run([sys.executable, str(BENCHMARKS / "bas_relief.py"), "--lighting-prior", "0.3", "-1"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--lighting-prior weights must be >= 0, got [0.3, -1.0]" in done.stderr
