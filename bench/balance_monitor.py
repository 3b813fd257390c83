"""Per-tick cost of the XCoM balance monitor against the simulated robot's own read, measured in the same run.

    python bench/balance_monitor.py [--ticks 3000]

Records the states of a pushed, trotting cat (MuJoCo), then times on those same states: the anchor
(`MujocoRobot.read`, what every tick pays anyway), the monitor with the simulator's truth, and the
monitor estimating CoM and feet from joint angles and the IMU (`felis.bodymodel`, the hardware path).
Prints median and p99 in µs and ratios to the anchor. Goal (issue 7): ≤ 50 µs per tick in the loop.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _time(fn, items, repeat: int = 3) -> np.ndarray:
    best = None
    for _ in range(repeat):
        out = np.empty(len(items))
        for k, x in enumerate(items):
            t0 = time.perf_counter()
            fn(x)
            out[k] = time.perf_counter() - t0
        best = out if best is None else np.minimum(best, out)
    return best * 1e6


def main() -> int:
    from felis.controllers.balance import BalanceMonitor
    from felis.controllers.stepping import SteppingController
    from felis.loop import run_loop
    from felis.scenarios.push import Push
    from felis.sim import MujocoRobot
    from felis.sim.bodymodel import load_body_model
    from felis.sim.pushes import Pusher
    from felis.sim.scenarios import set_pose
    from felis.spec import load_spec

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=3000)
    args = ap.parse_args()
    spec = load_spec("cat")
    body = load_body_model(spec)
    states = []
    ctl = SteppingController()
    with MujocoRobot(spec) as robot:
        set_pose(robot, spec.pose("stand"))
        push = Pusher(robot, Push("upper_body", 60, 0.3, 2.0, "step"))
        run_loop(robot, ctl, duration=args.ticks / 100, monitors=[push, lambda s, c: states.append(s)])
        anchor = _time(lambda s: robot.read(), states)
    truth = BalanceMonitor(body, gait=ctl.gait)
    est = BalanceMonitor(body, gait=ctl.gait, use_truth=False)
    t_truth = _time(truth.assess, states)
    t_est = _time(est.assess, states)
    a = float(np.median(anchor))
    print(f"balance monitor, {len(states)} ticks of a trotting, pushed cat (best of 3 passes)")
    for name, t in (("anchor: MujocoRobot.read()", anchor), ("monitor, simulator truth", t_truth),
                    ("monitor, estimate from joints + IMU", t_est)):
        print(f"  {name:38s} median {np.median(t):6.1f} µs  p99 {np.percentile(t, 99):6.1f} µs  "
              f"= {np.median(t) / a:5.2f}× anchor")
    ok = np.median(t_truth) <= 50 and np.median(t_est) <= 50
    print(f"goal ≤ 50 µs per tick: {'met' if ok else 'NOT met'} (median)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
