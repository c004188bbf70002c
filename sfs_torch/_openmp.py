"""How idle OpenMP threads wait, for the processes that the package's commands own."""
import os

__all__ = ["SPIN_COUNT", "WAIT_VARIABLES", "short_openmp_waits"]

# libgomp's spins before an idle thread sleeps; chosen with benchmarks/openmp_waits.py
SPIN_COUNT = 3000
# the variables that say how idle threads wait; a user who set either has chosen
WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def short_openmp_waits() -> None:
    """Let idle OpenMP threads spin briefly and then sleep, unless the user chose
    (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` already set).

    Call it before torch starts its threads. Spinning for long (libgomp's default)
    starves other processes' work on a loaded machine; sleeping at once
    (``OMP_WAIT_POLICY=PASSIVE``) makes every short parallel op of the photometric
    refinement wait for a wake-up. Sets both: libgomp (torch's Linux wheels) takes
    ``GOMP_SPINCOUNT`` over the passive policy's zero spins, and other OpenMP runtimes,
    which ignore it, keep the passive policy. docs/pipeline.md has the measurements.
    """
    if not any(name in os.environ for name in WAIT_VARIABLES):
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        os.environ["GOMP_SPINCOUNT"] = str(SPIN_COUNT)
