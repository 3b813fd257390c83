"""Benchmark: a 2 s cat episode through felis against a bare ``mj_step`` loop on the same model.

Episode: the cat released upside-down 1 m above the floor, 2 s at the model's physics rate (2 kHz since
2026-11-29, 1 kHz before). felis runs it
through the whole stack at 100 Hz (MujocoRobot read/write with servo quantisation, the stand
PoseController, the safety layer, the loop and its timing); the anchor is the loop a MuJoCo user
would write by hand on the same compiled model and initial state: set ``ctrl`` every tick's steps and
call ``mj_step`` once per physics step. Each timed batch of felis is put between two of the anchor
(bare, felis, bare, …), and its ratio is the anchor's mean time of the two over its own: the machines this
runs on (shared 2-core VMs) change speed by ±30 % from one second to the next, and a ratio against the
anchor measured a second earlier carries that in full. The ratio printed is the median over the rounds;
episodes per second are the medians of each. Goal: ratio ≥ 0.7.

With ``--with-log`` it also times felis writing the full run log each episode (every channel of
`felis.logs.runlog`: joint states and commands, the transforms of every body, IMU, contacts, timing, the
/robot scene; goal ≥ 0.65), and the same with a live view (`felis.logs.live`) serving the channels on
127.0.0.1, first with no client, then with one client (a separate process speaking the Foxglove WebSocket
protocol, subscribed to every channel and reading all it gets; goal ≥ 0.6 each). In a round each variant
is timed between two anchor batches; the client is connected for a second series of rounds (bare, live with
the client, bare, …), so that connecting it is not timed.

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
    ap.add_argument("--repeats", type=int, default=15, help="rounds (each variant between two anchor batches)")
    ap.add_argument("--episodes", type=int, default=3, help="episodes per timed batch")
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
    series: dict[str, list[float]] = {}  # variant -> ratio per round (anchor time / variant time)
    rates: dict[str, list[float]] = {}  # variant -> episodes/s per round

    def timed(name: str, run) -> None:
        """One round of ``run`` between two anchor batches."""
        b0 = bare_episodes(bare_model, qpos0, ctrl, args.episodes)
        x = run()
        b1 = bare_episodes(bare_model, qpos0, ctrl, args.episodes)
        rates.setdefault("bare", []).extend((b0, b1))
        rates.setdefault(name, []).append(x)
        series.setdefault(name, []).append(x * 0.5 * (1.0 / b0 + 1.0 / b1))

    tmp = view = client = None
    if args.with_log:
        import tempfile
        from pathlib import Path

        from felis.logs.live import LiveView

        tmp = Path(tempfile.mkdtemp(prefix="felis-bench-"))
        view = LiveView(("127.0.0.1", 0))
    try:
        for _ in range(args.repeats):
            timed("felis", lambda: felis_episodes(robot, args.episodes))
            if tmp is not None:
                timed("log", lambda: felis_episodes(robot, args.episodes, tmp))
                timed("live", lambda: felis_episodes(robot, args.episodes, tmp, live=view))
        if view is not None:
            client = live_client(view.url)
            felis_episodes(robot, 1, tmp, live=view)  # the client subscribes to the channels as they appear
            for _ in range(args.repeats):
                timed("client", lambda: felis_episodes(robot, args.episodes, tmp, live=view))
    finally:
        if client is not None and client.poll() is None:
            client.kill()
            client.wait()
        if view is not None:
            view.close()
    robot.close()
    bare, fel = statistics.median(rates["bare"]), statistics.median(rates["felis"])
    ratios = sorted(series["felis"])
    ratio = statistics.median(ratios)
    result = {
        "episode": f"cat, {DURATION:g} s, physics {1 / bare_model.opt.timestep:g} Hz, loop {RATE:g} Hz",
        "bare_mj_step_episodes_per_s": round(bare, 2),
        "felis_episodes_per_s": round(fel, 2),
        "ratio": round(ratio, 3),
        "ratio_range": [round(ratios[0], 3), round(ratios[-1], 3)],
        "goal": ">= 0.7",
    }
    if "log" in series:
        def med(name):
            return round(statistics.median(series[name]), 3)

        result["felis_with_mcap_log_episodes_per_s"] = round(statistics.median(rates["log"]), 2)
        result["ratio_with_log"] = med("log")
        result["ratio_with_log_and_live_no_client"] = med("live")
        result["ratio_with_log_and_live_one_client"] = med("client")
        result["goal_with_log"] = ">= 0.65; live >= 0.6"
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"sim_speed: {result['episode']}; medians of {args.repeats} rounds of {args.episodes} episodes, "
              "each variant between two anchor batches")
        print(f"  bare mj_step loop : {bare:8.2f} episodes/s   (anchor)")
        print(f"  felis             : {fel:8.2f} episodes/s   ratio {ratio:.3f} (pairs {ratios[0]:.3f}…"
              f"{ratios[-1]:.3f}; goal ≥ 0.7)")
        if "log" in series:
            print(f"  felis + MCAP log  : {result['felis_with_mcap_log_episodes_per_s']:8.2f} episodes/s   "
                  f"ratio {result['ratio_with_log']:.3f} (goal ≥ 0.65)")
            print(f"  + live, no client : ratio {result['ratio_with_log_and_live_no_client']:.3f} (goal ≥ 0.6)")
            print(f"  + live, 1 client  : ratio {result['ratio_with_log_and_live_one_client']:.3f} (goal ≥ 0.6)")


if __name__ == "__main__":
    main()
