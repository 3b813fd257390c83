"""Benchmark: a 2 s cat episode through felis against a bare ``mj_step`` loop on the same model.

Episode: the cat released upside-down 1 m above the floor, 2 s at 1 kHz physics. felis runs it
through the whole stack at 100 Hz (MujocoRobot read/write with servo quantisation, the stand
PoseController, the safety layer, the loop and its timing); the anchor is the loop a MuJoCo user
would write by hand on the same compiled model and initial state: set ``ctrl`` every 10 steps and
call ``mj_step`` once per physics step. Batches are interleaved (bare, felis, bare, felis, …) so
both see the same machine; the ratio is the median of the per-pair ratios (felis ÷ bare), robust to
load that comes and goes; episodes per second are the medians of each. Goal: ratio ≥ 0.7.

    python bench/sim_speed.py [--repeats N] [--episodes K] [--json]
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

import mujoco
import numpy as np

from felis.controllers import PoseController
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.sim.scenarios import drop
from felis.spec import load_spec

DURATION, RATE = 2.0, 100.0


def felis_episodes(robot: MujocoRobot, k: int, log_dir=None) -> float:
    controller = PoseController("stand", duration=0.5)
    t0 = time.perf_counter()
    for i in range(k):
        robot.reset()
        drop(robot, 1.0, roll=180.0)
        log = None
        if log_dir is not None:
            from felis.logs.runlog import RunLog

            log = RunLog(log_dir / f"ep{i}.mcap", robot.spec)
        run_loop(robot, controller, duration=DURATION, rate_hz=RATE, log=log, keep_armed=True)
        if log is not None:
            log.close()
    return k / (time.perf_counter() - t0)


def bare_episodes(m: mujoco.MjModel, qpos0: np.ndarray, ctrl: np.ndarray, k: int) -> float:
    d = mujoco.MjData(m)
    substeps = int(round(1.0 / (RATE * m.opt.timestep)))
    ticks = int(DURATION * RATE)
    t0 = time.perf_counter()
    for _ in range(k):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = qpos0
        for _ in range(ticks):
            d.ctrl[:] = ctrl
            for _ in range(substeps):
                mujoco.mj_step(m, d)
    return k / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9, help="interleaved pairs of timed batches")
    ap.add_argument("--episodes", type=int, default=6, help="episodes per timed batch")
    ap.add_argument("--with-log", action="store_true", help="also time felis with MCAP logging")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    spec = load_spec("cat")
    robot = MujocoRobot(spec)
    robot.connect()
    robot.arm()
    drop(robot, 1.0, roll=180.0)
    qpos0 = robot.data.qpos.copy()
    bare_model = copy.deepcopy(robot.model)  # armed gains, same servo parameters
    ctrl = spec.pose("stand")
    felis_episodes(robot, 1)  # warm-up
    bare_episodes(bare_model, qpos0, ctrl, 1)
    f_runs, b_runs, l_runs = [], [], []
    tmp = None
    if args.with_log:
        import tempfile
        from pathlib import Path

        tmp = Path(tempfile.mkdtemp(prefix="felis-bench-"))
    for _ in range(args.repeats):
        b_runs.append(bare_episodes(bare_model, qpos0, ctrl, args.episodes))
        f_runs.append(felis_episodes(robot, args.episodes))
        if tmp is not None:
            l_runs.append(felis_episodes(robot, args.episodes, tmp))
    robot.close()
    bare, fel = statistics.median(b_runs), statistics.median(f_runs)
    ratios = sorted(f / b for f, b in zip(f_runs, b_runs, strict=True))
    ratio = statistics.median(ratios)
    result = {
        "episode": f"cat, {DURATION:g} s, physics {1 / bare_model.opt.timestep:g} Hz, loop {RATE:g} Hz",
        "bare_mj_step_episodes_per_s": round(bare, 2),
        "felis_episodes_per_s": round(fel, 2),
        "ratio": round(ratio, 3),
        "ratio_range": [round(ratios[0], 3), round(ratios[-1], 3)],
        "goal": ">= 0.7",
    }
    if l_runs:
        result["felis_with_mcap_log_episodes_per_s"] = round(statistics.median(l_runs), 2)
        result["ratio_with_log"] = round(statistics.median(l / b for l, b in zip(l_runs, b_runs, strict=True)), 3)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"sim_speed: {result['episode']}; medians of {args.repeats} × {args.episodes} episodes")
        print(f"  bare mj_step loop : {bare:8.2f} episodes/s   (anchor)")
        print(f"  felis             : {fel:8.2f} episodes/s   ratio {ratio:.3f} (pairs {ratios[0]:.3f}…"
              f"{ratios[-1]:.3f}; goal ≥ 0.7)")
        if l_runs:
            print(f"  felis + MCAP log  : {result['felis_with_mcap_log_episodes_per_s']:8.2f} episodes/s   "
                  f"ratio {result['ratio_with_log']:.3f}")


if __name__ == "__main__":
    main()
