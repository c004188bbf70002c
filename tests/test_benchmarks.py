"""The benchmark scripts' own argument checks and helpers (their measurements are in docs/, not in tests)."""
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
    assert "for the tuning sides (validation, spare)" in done.stderr


def test_bas_relief_refuses_a_negative_first_light():
    # a negative start would slice the lightings from their end
    done = subprocess.run([sys.executable, str(BENCHMARKS / "bas_relief.py"), "--first-light", "-1"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--first-light must be >= 0, got -1" in done.stderr


def test_bas_relief_refuses_a_negative_lighting_prior_weight():
    # a negative weight would reward improbable lightings: refused before any image is made
    done = subprocess.run([sys.executable, str(BENCHMARKS / "bas_relief.py"), "--lighting-prior", "0.3", "-1"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--lighting-prior weights must be >= 0, got [0.3, -1.0]" in done.stderr


def test_bas_relief_refuses_converging_without_hypotheses():
    # --converging says how the hypotheses are refined: alone it would be silently ignored
    done = subprocess.run([sys.executable, str(BENCHMARKS / "bas_relief.py"), "--converging"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--converging refines the --hypotheses" in done.stderr


def _results():
    """benchmarks/_results.py, which the scripts import from their own folder."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import _results
    finally:
        sys.path.remove(str(BENCHMARKS))
    return _results


def test_paired_bootstrap_of_a_uniform_change_is_exact():
    # every resample moves by the same amount: the intervals shrink to the change itself
    first = [3.0, 7.5, 1.0, 12.0, 9.0]
    out = _results().paired_bootstrap(first, [x - 0.5 for x in first], draws=200)
    assert out["median"] == pytest.approx(-0.5) and out["mean"] == pytest.approx(-0.5)
    assert out["median_interval"] == pytest.approx([-0.5, -0.5]) and out["mean_interval"] == pytest.approx([-0.5, -0.5])


def test_paired_bootstrap_intervals_of_one_large_change():
    # one image of ten 10 deg worse: the mean moves by 1, and a resample without it (about a third of them) by 0
    first = list(range(10))
    second = first[:9] + [19.0]
    out = _results().paired_bootstrap(first, second, draws=4000, level=0.5)
    assert out["mean"] == pytest.approx(1.0) and out["median"] == 0.0
    low, high = out["mean_interval"]
    assert low == 0.0 and 1.0 <= high <= 2.0


def test_ratio_over_shapes_is_exact_when_every_shape_has_the_same_ratio():
    prior = [8.0, 12.0, 20.0, 30.0, 10.0, 14.0]
    out = _results().ratio_over_shapes([0.5 * p for p in prior], prior, ["a", "a", "b", "b", "c", "c"], draws=300)
    assert out == pytest.approx([0.5, 0.5])


def test_ratio_over_shapes_spans_the_shapes_own_ratios():
    # shape a at 0.25x its prior, shape b at 1x; a draw of both gives median 2.5 / 4
    errors, prior, shapes = [1.0, 1.0, 4.0, 4.0], [4.0] * 4, ["a", "a", "b", "b"]
    low, high = _results().ratio_over_shapes(errors, prior, shapes, draws=2000)
    assert (low, high) == (pytest.approx(0.25), pytest.approx(1.0))
    low, high = _results().ratio_over_shapes(errors, prior, shapes, draws=2000, level=0.2)
    assert low == high == pytest.approx(0.625)


def test_ratio_over_shapes_refuses_unmatched_values():
    with pytest.raises(ValueError, match="one value per image"):
        _results().ratio_over_shapes([1.0, 2.0], [1.0, 2.0], ["a"])


def test_median_per_shape_takes_each_shapes_own_median_in_first_seen_order():
    medians = _results().median_per_shape([4.0, 1.0, 10.0, 2.0, 30.0], ["b", "a", "b", "a", "b"])
    assert list(medians) == ["b", "a"]
    assert medians == {"b": 10.0, "a": 1.5}


def test_median_per_shape_refuses_unmatched_values():
    with pytest.raises(ValueError, match="one entry per image"):
        _results().median_per_shape([1.0, 2.0], ["a"])


def test_paired_bootstrap_refuses_unpaired_values():
    with pytest.raises(ValueError, match="one value per image"):
        _results().paired_bootstrap([1.0, 2.0], [1.0])


@pytest.mark.parametrize("arguments, message", [
    (["--first-shape", "-1"], "--first-shape must be >= 0, got -1"),
    (["--first-light", "-1"], "--first-light must be >= 0, got -1"),
    (["--first-shape", "8", "--shapes", "3"], "--first-shape + --shapes: n must be an integer in [0, 10] on the "
                                               "validation side, got 11"),
    (["--side", "spare", "--shapes", "5000"], "on the spare side, got 5000"),
])
def test_tune_refuses_shapes_and_lightings_the_side_does_not_have(arguments, message):
    done = subprocess.run([sys.executable, str(BENCHMARKS / "tune.py"), *arguments],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert message in done.stderr


@pytest.mark.parametrize("arguments, message", [
    (["--views", "0"], "--views must be at least 1, got 0"),
    (["--tilt-std", "-0.1"], "--log-scale-std and --tilt-std must be >= 0"),
    (["--side", "test", "--shapes", "11"], "n must be an integer in [0, 10] on the test side, got 11"),
    (["--weights", "no_such_file.npz"], "'no_such_file.npz' holds no relief prior's weights"),
])
def test_relief_floor_refuses_bad_arguments_before_any_view(arguments, message):
    done = subprocess.run([sys.executable, str(BENCHMARKS / "relief_floor.py"), *arguments],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert message in done.stderr
