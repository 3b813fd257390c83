import os

os.environ.setdefault("MUJOCO_GL", "egl")

from hypothesis import settings  # noqa: E402

# Property tests are deterministic (DESIGN: tests are fast and deterministic): the same examples on
# every run, so CI cannot go red on a case no one has seen. HYPOTHESIS_PROFILE=explore searches anew.
settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
