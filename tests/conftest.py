import os

os.environ.setdefault("MUJOCO_GL", "egl")
# `make test` runs the suite on every core (pytest-xdist), so a test shares its core with another worker and
# with the children both start: a reply from a virtual bus may come a scheduling slice late. The default
# slack on a pty is 10 ms; 40 ms here, for every bus a test or its subprocesses open without their own
# (tests of timeouts give theirs). The product's default is unchanged.
os.environ.setdefault("FELIS_TIMEOUT_MARGIN_MS", "40")
# The same load can leave a host silent longer than the servos' 0.1 s deadman: the emulated servos keep their Bus
# Watchdog on the wall clock, so a stalled test process trips it as it would a real servo (the run stops, rightly,
# and the test fails for the machine's sake: teleop through two virtual buses did, in `make test`). Every run a test
# starts arms a 1 s deadman; tests of the deadman itself set 0.1 s (`BUS_WATCHDOG_S`) themselves.
os.environ.setdefault("FELIS_BUS_WATCHDOG_MS", "1000")

from hypothesis import settings  # noqa: E402

# Property tests are deterministic (DESIGN: tests are fast and deterministic): the same examples on
# every run, so CI cannot go red on a case no one has seen. HYPOTHESIS_PROFILE=explore searches anew.
settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


def load_bench(name: str):
    """A ``bench/<name>.py`` script as a module (bench scripts are not a package), for smoke tests."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
