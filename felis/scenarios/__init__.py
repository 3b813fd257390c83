"""Tasks, backend-free (`felis.scenarios`): drops and pushes, and the verdicts on what happened.

* `drop`: the one `Drop` type, its validator, drops files and random drops;
* `push`: the one `Push` type, its validator, push files and random pushes;
* `verdicts`: did it land (`landing_verdict`)? did it fall (`fall_verdict`)? — pure functions of the truth
  a simulator recorded (`felis.sim.landing`, `felis.sim.pushes`).

Only felis core is imported here: controllers, the simulation and the evaluations all share these.
"""

from felis.scenarios.drop import (
    MAX_ANGLE_DEG,
    MAX_DROP_HEIGHT,
    Drop,
    check_drop,
    drop_from_values,
    drops_from,
    euler_drops,
    load_drops,
    make_drop,
    random_drops,
)
from felis.scenarios.push import (
    BODIES,
    FALL_WINDOW_S,
    MAX_IMPULSE,
    PHASES,
    Push,
    check_push,
    load_pushes,
    pushes_from,
    random_pushes,
)
from felis.scenarios.verdicts import (
    FALL_TILT_DEG,
    TILT_DEG,
    WAIST_FRACTION,
    WINDOW_S,
    FallTruth,
    FallVerdict,
    LandingTruth,
    LandingVerdict,
    fall_reason,
    fall_verdict,
    landed,
    landing_verdict,
)

__all__ = [
    "BODIES", "FALL_TILT_DEG", "FALL_WINDOW_S", "MAX_ANGLE_DEG", "MAX_DROP_HEIGHT", "MAX_IMPULSE", "PHASES",
    "TILT_DEG", "WAIST_FRACTION", "WINDOW_S", "Drop", "FallTruth", "FallVerdict", "LandingTruth", "LandingVerdict",
    "Push", "check_drop", "check_push", "drop_from_values", "drops_from", "euler_drops", "fall_reason", "fall_verdict",
    "landed", "landing_verdict", "load_drops", "load_pushes", "make_drop", "pushes_from", "random_drops",
    "random_pushes",
]
