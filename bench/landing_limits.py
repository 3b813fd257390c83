"""What limits landing from random orientations: servo speed and fall time (issue 5, docs/landing.md).

For a few start orientations this measures how far the best spine rule turns the cat in the air
before touchdown, and whether it lands (`felis.sim.drops.landed`), while changing one thing at a time:

1. **servo speed** ×1, ×2, ×4 from 3 m. A ×k servo is the XL330 model with k× the no-load speed and
   k× the stall torque (so k× the position gain's torque per radian and the same back-EMF damping,
   `felis.sim.servo`); the safety layer's per-tick step limit (the spec's ``max_velocity``) is raised
   k× too, and the rule commands the spine at k× the XL330's no-load speed. Nothing else changes.
2. **fall time** at ×1 from 1, 3, 5 and 10 m (fall time √(2h/g): 0.45, 0.78, 1.01, 1.43 s).
3. **control**: dropped upright (0, 0, 0) from 1, 3, 5 and 10 m with the spine straight (no search): does a cat
   that is already righted land by the rule at all.

**Rule.** The tail and legs hold the release pose; the spine (pitch, yaw) goes round a closed loop of
`N_WAYPOINTS` angle waypoints within ±1 rad at the commanded speed (each leg of the loop as many whole
ticks as the faster joint needs), again and again until touchdown: the loop is the "waist moves close to
a circle" of seed 000 §6.5, repeated so that a faster servo or a longer fall gets more loops. Below a
waist height of 0.5 m `LandingController` holds the spine straight, as in every landing run.

**Search** per case: cross-entropy over the 2·`N_WAYPOINTS` angles, `GENERATIONS` × `POPULATION`
rollouts; generation 0 holds the two circles (diamonds, both directions) and the waypoints of the tuned
rule in ``learning/weights/landing_samples.json`` for that orientation. Score = rotation / 180° + [landed].
Deterministic per case (its generator is seeded by the case index).

**Rotation.** The tilt of a body is the angle of its up-axis from vertical; the cat's tilt is the mean of
the upper and lower body's. Rotation = start tilt − tilt at the last control tick before touchdown (the
first floor contact of any geom). Righting needs the start tilt minus at most 30° (the `landed` rule's
tilt bound), and feet-first contact in practice needs the feet well below the body.

Run (about 4 min on 2 cores)::

    MUJOCO_GL=egl .venv/bin/python bench/landing_limits.py [--json OUT.json] [--workers N] [--quick]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

DT = 0.01
N_WAYPOINTS = 6
WAYPOINT_LIMIT = 1.0  # rad
POPULATION = 24
ELITES = 6
GENERATIONS = 20
INIT_SPREAD = 0.8
MIN_SPREAD = 0.1
SPEEDS = (1.0, 2.0, 4.0)
HEIGHTS = (1.0, 3.0, 5.0, 10.0)
ORIENTATIONS = ((180.0, 0.0, 0.0), (90.0, 0.0, 0.0))
UPRIGHT = (0.0, 0.0, 0.0)  # control: dropped already upright, spine straight, no search
BASE_HEIGHT = 3.0
G = 9.81


# ----------------------------------------------------------------------------------------- the model
def make_sim(speed: float = 1.0):
    """A `LandingSim` whose servos are ``speed``× faster (module doc)."""
    from felis.learning.landing_eval import LandingSim
    from felis.servos import servo_model
    from felis.sim import MujocoRobot
    from felis.sim.drops import standing_waist_height
    from felis.sim.servo import servo_params
    from felis.spec import load_spec

    k = float(speed)
    base = load_spec("cat")
    spec = replace(base, joints=tuple(replace(j, max_velocity=j.max_velocity * k) for j in base.joints))
    servo = {}
    for j in spec.joints:
        m = servo_model(j.servo)
        servo[j.name] = servo_params(replace(m, stall_torque=m.stall_torque * k, no_load_speed=m.no_load_speed * k),
                                     p_gain=m.position_p_gain, m_per_rad=j.m_per_rad)
    sim = LandingSim.__new__(LandingSim)
    sim.spec = spec
    sim.feet = tuple(spec.sensors.contacts)
    sim.robot = MujocoRobot(spec, servo=servo)
    sim.robot.connect()
    sim.standing_waist_m = standing_waist_height(sim.robot)
    return sim


# ----------------------------------------------------------------------------------------- the rule
class LoopRule:
    """Spine velocities (12 joint velocities, tail and legs 0) moving the spine from straight round the
    closed loop of ``waypoints`` (N, 2) rad at ``speed`` rad/s, repeated for ``duration`` s. The target
    path is precomputed per tick, so the controller's integrated targets hit it exactly."""

    def __init__(self, waypoints, speed: float, duration: float, dt: float = DT):
        w = np.clip(np.round(np.asarray(waypoints, dtype=float).reshape(-1, 2), 3), -WAYPOINT_LIMIT, WAYPOINT_LIMIT)
        n_ticks = int(math.ceil(duration / dt)) + 2
        path, prev, i = [np.zeros(2)], np.zeros(2), 0
        while len(path) < n_ticks:
            p = w[i % len(w)]
            i += 1
            d = p - prev
            ticks = math.ceil(float(np.abs(d).max()) / (speed * dt) - 1e-9)
            if ticks <= 0:
                if i > 2 * len(w) and len(path) == 1:
                    break  # every waypoint is straight: hold
                continue
            path += [prev + d * (s / ticks) for s in range(1, ticks + 1)]
            prev = p
        path = np.array(path[:n_ticks])
        self.v = np.zeros((n_ticks, 12))
        self.v[1:len(path), :2] = np.diff(path, axis=0) / dt
        self.dt = dt

    def __call__(self, it, t: float) -> np.ndarray:
        i = int(round(t / self.dt))
        return self.v[i].copy() if 0 <= i < len(self.v) else np.zeros(12)


def circle(sign: int) -> np.ndarray:
    ring = [(1.0, 0.0), (0.0, sign * 1.0), (-1.0, 0.0), (0.0, -sign * 1.0)]
    return np.array([ring[i % 4] for i in range(N_WAYPOINTS)])


def stored_waypoints(orientation) -> np.ndarray | None:
    """The tuned rule's waypoints for ``orientation`` from landing_samples.json, if there is one."""
    from felis.learning.landing_samples import DEFAULT_SAMPLES_PATH

    try:
        doc = json.loads(DEFAULT_SAMPLES_PATH.read_text())
    except (OSError, ValueError):
        return None
    for s in doc.get("samples", []):
        if [float(x) for x in s["orientation"]] == [float(x) for x in orientation]:
            w = np.asarray(s["waypoints_rad"], dtype=float)
            return w if w.shape == (N_WAYPOINTS, 2) else None
    return None


# ----------------------------------------------------------------------------------------- measure
def _tilt(z: float) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, z))))


def measure(sim, orientation, height_m: float, speed: float, waypoints, duration: float | None = None) -> dict:
    """One drop of ``sim`` (from `make_sim` (``speed``)) under the loop rule of ``waypoints``: the tilt at
    release and at the last tick before touchdown (or at the end of the run if it never touches down),
    the rotation (start − touchdown tilt, degrees), and the landing outcome."""
    from felis.controllers.landing import LandingController
    from felis.learning.landing_nets import MAX_SPEED
    from felis.sim.drops import Drop

    fall = math.sqrt(2.0 * height_m / G)
    rule = LoopRule(waypoints, speed * MAX_SPEED, fall + 0.1)
    robot = sim.robot
    upper, lower = robot.root_body, robot.body_id("lower_body")
    rec: list[tuple[float, float, float, float]] = []

    def monitor(state, command) -> None:
        d = robot.data
        rec.append((float(d.time), float(d.xmat[upper, 8]), float(d.xmat[lower, 8]),
                    math.degrees(float(np.linalg.norm(d.cvel[upper, :3])))))

    out = sim.run(Drop(*orientation, height_m), LandingController(rule), monitors=[monitor], duration=duration)
    a = np.array(rec)
    td = out.touchdown_s
    before = np.flatnonzero(a[:, 0] <= td + 1e-9) if td is not None else np.arange(len(a))
    i = int(before[-1]) if before.size else 0
    start = 0.5 * (_tilt(a[0, 1]) + _tilt(a[0, 2]))
    at_td = 0.5 * (_tilt(a[i, 1]) + _tilt(a[i, 2]))
    return {"orientation": list(orientation), "height_m": height_m, "speed": speed, "fall_s": round(fall, 3),
            "touchdown_s": None if td is None else round(td, 3), "start_tilt_deg": round(start, 1),
            "tilt_at_touchdown_deg": round(at_td, 1), "upper_tilt_deg": round(_tilt(a[i, 1]), 1),
            "lower_tilt_deg": round(_tilt(a[i, 2]), 1), "rotation_deg": round(start - at_td, 1),
            "upper_rate_deg_s": round(float(a[i, 3]), 0),
            "landed": bool(out.landed), "why": out.why or None,
            "waypoints_rad": np.round(np.asarray(waypoints, dtype=float).reshape(-1, 2), 3).tolist()}


def search(sim, orientation, height_m: float, speed: float, seed: int, generations: int = GENERATIONS,
           population: int = POPULATION) -> tuple[dict, int]:
    """Best loop rule for one case by the module doc's cross-entropy search; (its measurement, rollouts)."""
    rng = np.random.default_rng(seed)
    dims = 2 * N_WAYPOINTS
    seeds = [circle(+1).ravel(), circle(-1).ravel()]
    w = stored_waypoints(orientation)
    if w is not None:
        seeds.append(w.ravel())
    mean, spread = np.zeros(dims), np.full(dims, INIT_SPREAD)
    best: tuple[float, dict] | None = None
    used = 0
    for g in range(generations):
        x = np.clip(mean + spread * rng.standard_normal((population, dims)), -WAYPOINT_LIMIT, WAYPOINT_LIMIT)
        if g == 0:
            for i, s in enumerate(seeds[:population]):
                x[i] = s
        elif best is not None:
            x[0] = np.asarray(best[1]["waypoints_rad"]).ravel()
        scores = np.empty(population)
        for i in range(population):
            r = measure(sim, orientation, height_m, speed, x[i])
            scores[i] = r["rotation_deg"] / 180.0 + (1.0 if r["landed"] else 0.0)
            if best is None or scores[i] > best[0]:
                best = (float(scores[i]), r)
        used += population
        elite = x[np.argsort(-scores, kind="stable")[:ELITES]]
        mean, spread = elite.mean(axis=0), np.maximum(elite.std(axis=0), MIN_SPREAD)
    assert best is not None
    return best[1], used


def cases() -> list[tuple[int, tuple, float, float]]:
    """(index, orientation, height, speed): the speed sweep at 3 m, then the height sweep at ×1."""
    out = []
    for o in ORIENTATIONS:
        for k in SPEEDS:
            out.append((o, BASE_HEIGHT, k))
        for h in HEIGHTS:
            if h != BASE_HEIGHT:
                out.append((o, h, 1.0))
    out += [(UPRIGHT, h, 1.0) for h in HEIGHTS]
    return [(i, *c) for i, c in enumerate(out)]


_SIMS: dict[float, object] = {}


def _run_case(args) -> dict:
    index, orientation, height, speed, generations, population = args
    if speed not in _SIMS:
        _SIMS[speed] = make_sim(speed)
    t0 = time.perf_counter()
    if tuple(orientation) == UPRIGHT:
        return {**measure(_SIMS[speed], orientation, height, speed, np.zeros((N_WAYPOINTS, 2))), "rollouts": 1,
                "search_s": round(time.perf_counter() - t0, 1)}
    r, n = search(_SIMS[speed], orientation, height, speed, seed=index, generations=generations,
                  population=population)
    return {**r, "rollouts": n, "search_s": round(time.perf_counter() - t0, 1)}


def run(workers: int | None = None, generations: int = GENERATIONS, population: int = POPULATION) -> list[dict]:
    jobs = [(*c, generations, population) for c in cases()]
    # longest first (high drops, then fast servos) so two workers finish together; results back in case order
    order = sorted(range(len(jobs)), key=lambda i: (-jobs[i][2], -jobs[i][3], i))
    workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    if workers == 1:
        res = [_run_case(jobs[i]) for i in order]
    else:
        with ProcessPoolExecutor(workers) as pool:
            res = list(pool.map(_run_case, [jobs[i] for i in order], chunksize=1))
    out: list[dict] = [{}] * len(jobs)
    for i, r in zip(order, res, strict=True):
        out[i] = r
    return out


def table(rows: list[dict]) -> str:
    head = (f"{'orientation':<16} {'servo':>5} {'drop m':>6} {'fall s':>6} {'start°':>6} {'tilt at td°':>11} "
            f"{'upper/lower°':>12} {'rotation°':>9} {'ω td°/s':>7} {'landed':>6}  why not (first reason)")
    lines = [head, "-" * len(head)]
    for r in rows:
        o = "(" + ", ".join(f"{v:g}" for v in r["orientation"]) + ")"
        lines.append(f"{o:<16} {'×' + format(r['speed'], 'g'):>5} {r['height_m']:>6g} {r['fall_s']:>6.2f} "
                     f"{r['start_tilt_deg']:>6.0f} {r['tilt_at_touchdown_deg']:>11.0f} "
                     f"{r['upper_tilt_deg']:>5.0f}/{r['lower_tilt_deg']:<6.0f} {r['rotation_deg']:>9.0f} "
                     f"{r['upper_rate_deg_s']:>7.0f} {'yes' if r['landed'] else 'no':>6}  "
                     f"{(r['why'] or '').split(';')[0]}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", metavar="OUT", help="also write the rows as JSON")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--quick", action="store_true", help="2 generations of 8 (a smoke run)")
    a = p.parse_args(argv)
    gens, pop = (2, 8) if a.quick else (GENERATIONS, POPULATION)
    t0 = time.perf_counter()
    rows = run(a.workers, gens, pop)
    wall = time.perf_counter() - t0
    print(table(rows))
    print(f"{sum(r['rollouts'] for r in rows)} rollouts, {wall:.0f} s wall")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"command": " ".join(["bench/landing_limits.py", *(argv or sys.argv[1:])]),
                       "generations": gens, "population": pop, "wall_s": round(wall, 1), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
