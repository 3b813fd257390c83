"""Benchmark: a 2 s cat episode through felis against a bare ``mj_step`` loop on the same model.

Episode: the cat released upside-down 1 m above the floor, 2 s at 1 kHz physics. felis runs it
through the whole stack at 100 Hz (MujocoRobot read/write with servo quantisation, the stand
PoseController, the safety layer, the loop and its timing); the anchor is the loop a MuJoCo user
would write by hand on the same compiled model and initial state: set ``ctrl`` every 10 steps and
call ``mj_step`` once per physics step. Batches are interleaved (bare, felis, bare, felis, …) so
both see the same machine; the ratio is the median of the per-pair ratios (felis ÷ bare), robust to
load that comes and goes; episodes per second are the medians of each. Goal: ratio ≥ 0.7.

With ``--with-log`` it also times felis writing the full run log each episode (every channel of
`felis.logs.runlog`: joint states and commands, the transforms of every body, IMU, contacts, timing, the
/robot scene; goal ≥ 0.65), and the same with a live view (`felis.logs.live`) serving the channels on
127.0.0.1, first with no client, then with one client (a separate process speaking the Foxglove WebSocket
protocol, subscribed to every channel and reading all it gets; goal ≥ 0.6 each).

    python bench/sim_speed.py [--repeats N] [--episodes K] [--with-log] [--json]
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


def felis_episodes(robot: MujocoRobot, k: int, log_dir=None, live=None) -> float:
    """``log_dir``: each episode writes the full log (every channel, /tf of every body, the /robot scene);
    ``live``: a `felis.logs.live.LiveView` gets the same channels (``log_dir`` None: live only)."""
    controller = PoseController("stand", duration=0.5)
    t0 = time.perf_counter()
    for i in range(k):
        robot.reset()
        drop(robot, 1.0, roll=180.0)
        log = None
        if log_dir is not None or live is not None:
            from felis.logs.runlog import RunLog
            from felis.sim.scene import MujocoPoses, model_scene

            log = RunLog(None if log_dir is None else log_dir / f"ep{i}.mcap", robot.spec,
                         scene=model_scene(robot.model), poses=MujocoPoses(robot), live=live)
        run_loop(robot, controller, duration=DURATION, rate_hz=RATE, log=log, keep_armed=True)
        if log is not None:
            log.close()
    return k / (time.perf_counter() - t0)


CLIENT = r"""
import asyncio, json, sys
import websockets

async def main(url):
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        print("connected", flush=True)
        n = 0
        async for msg in ws:
            if isinstance(msg, str):
                m = json.loads(msg)
                if m.get("op") == "advertise":
                    subs = [{"id": c["id"], "channelId": c["id"]} for c in m["channels"]]
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            else:
                n += 1

asyncio.run(main(sys.argv[1]))
"""


def live_client(url: str):
    """A Foxglove WebSocket client in its own process, subscribed to every channel as it is advertised."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", CLIENT, url], stdout=subprocess.PIPE, text=True)
    if proc.stdout.readline().strip() != "connected":
        raise RuntimeError("the live client did not connect")
    return proc


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
    f_runs, b_runs, l_runs, v_runs, c_runs = [], [], [], [], []
    tmp = view = client = None
    if args.with_log:
        import tempfile
        from pathlib import Path

        from felis.logs.live import LiveView

        tmp = Path(tempfile.mkdtemp(prefix="felis-bench-"))
        view = LiveView(("127.0.0.1", 0))
    try:
        for _ in range(args.repeats):
            b_runs.append(bare_episodes(bare_model, qpos0, ctrl, args.episodes))
            f_runs.append(felis_episodes(robot, args.episodes))
            if tmp is not None:
                l_runs.append(felis_episodes(robot, args.episodes, tmp))
                v_runs.append(felis_episodes(robot, args.episodes, tmp, live=view))
                client = live_client(view.url)
                c_runs.append(felis_episodes(robot, args.episodes, tmp, live=view))
                client.kill()
                client.wait()
    finally:
        if client is not None and client.poll() is None:
            client.kill()
        if view is not None:
            view.close()
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
        def pair(runs):
            return round(statistics.median(x / b for x, b in zip(runs, b_runs, strict=True)), 3)

        result["felis_with_mcap_log_episodes_per_s"] = round(statistics.median(l_runs), 2)
        result["ratio_with_log"] = pair(l_runs)
        result["ratio_with_log_and_live_no_client"] = pair(v_runs)
        result["ratio_with_log_and_live_one_client"] = pair(c_runs)
        result["goal_with_log"] = ">= 0.65; live >= 0.6"
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"sim_speed: {result['episode']}; medians of {args.repeats} × {args.episodes} episodes")
        print(f"  bare mj_step loop : {bare:8.2f} episodes/s   (anchor)")
        print(f"  felis             : {fel:8.2f} episodes/s   ratio {ratio:.3f} (pairs {ratios[0]:.3f}…"
              f"{ratios[-1]:.3f}; goal ≥ 0.7)")
        if l_runs:
            print(f"  felis + MCAP log  : {result['felis_with_mcap_log_episodes_per_s']:8.2f} episodes/s   "
                  f"ratio {result['ratio_with_log']:.3f} (goal ≥ 0.65)")
            print(f"  + live, no client : ratio {result['ratio_with_log_and_live_no_client']:.3f} (goal ≥ 0.6)")
            print(f"  + live, 1 client  : ratio {result['ratio_with_log_and_live_one_client']:.3f} (goal ≥ 0.6)")


if __name__ == "__main__":
    main()
