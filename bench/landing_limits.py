"""What limits landing from random orientations: servo speed, fall time, which joints move (issue 5).

For a few start orientations this measures how far the best loop rule turns the cat in the air before
touchdown, and whether it lands (`felis.scenarios.verdicts.landed`), while changing one thing at a time (the results:
docs/landing.md, "What limits it"):

1. **servo speed** ×1, ×2, ×4 from 3 m. A ×k servo is the XL330 model with k× the no-load speed and
   k× the stall torque (so k× the position gain's torque per radian and the same back-EMF damping,
   `felis.sim.servo`); the safety layer's per-tick step limit (the spec's ``max_velocity``) is raised
   k× too, and the rule commands the spine at k× the XL330's no-load speed. Nothing else changes.
2. **fall time** at ×1 from 1, 3, 5 and 10 m (fall time √(2h/g): 0.45, 0.78, 1.01, 1.43 s).
3. **control**: dropped upright (0, 0, 0) from 1, 3, 5 and 10 m with the spine straight (no search): does a cat
   that is already righted land by the rule at all.
4. **whole body** at ×1 from 1 and 3 m: the tail and legs move too (rule below). The other cases move the
   spine only, like the paper's motion samples (§6.5); this one measures what the XL330s allow, not what
   the spine allows.

**Spine rule.** The tail and legs hold the release pose; the spine (pitch, yaw) goes round a closed loop
of `N_WAYPOINTS` angle waypoints within ±1 rad at the commanded speed (each leg of the loop as many whole
ticks as the fastest joint needs), again and again until touchdown: the loop is the "waist moves close to
a circle" of seed 000 §6.5, repeated so that a faster servo or a longer fall gets more loops. Below a
waist height of 0.5 m `LandingController` holds the spine straight, as in every landing run.

**Whole-body rule.** The same loop over 8 angles per waypoint: spine (pitch, yaw), tail (pitch, yaw),
front legs (pitch, roll) and hind legs (pitch, roll), the two legs of a pair moving together (the same
joint angles, so their roll swings add up). Leg angles within ±1.5 rad (the joints allow ±90°). The
legs carry 63 % of the cat's roll inertia, so a leg moving round a loop (swinging across the roll axis
out, along it back) turns the body the other way, as the spine's loop does. `RETURN_S` before the
predicted touchdown every joint heads straight back to the release pose (legs down) at full speed.

**Search** per case: cross-entropy over the waypoint angles, `GENERATIONS` × `POPULATION` rollouts;
generation 0 holds the two circles (diamonds, both directions) and the waypoints of the tuned rule in
``learning/weights/landing_samples.json`` for that orientation, all on the spine with the rest held.
Score = rotation / 180° + [landed]. The whole body has 4× the angles and one search of
`BODY_GENERATIONS` × `BODY_POPULATION` can end far from another (76° or 150° for (180, 0, 0) from 3 m,
from two of these generation 0s), so it keeps the best of three (`BODY_STARTS`): generation 0 as above,
as above plus the legs' loop (`leg_loop`: roll out, pitch up, roll back, pitch down) both ways with the
spine's circle both ways, and random only.
Deterministic per case (its generators are seeded by the case index).

**Rotation.** The tilt of a body is the angle of its up-axis from vertical; the cat's tilt is the mean of
the upper and lower body's. Rotation = start tilt − tilt at the last control tick before touchdown (the
first floor contact of any geom). Righting needs the start tilt minus at most 30° (the `landed` rule's
tilt bound), and feet-first contact in practice needs the feet well below the body.

Run (about 12 min on 2 cores)::

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
BODY_GENERATIONS = 30
BODY_POPULATION = 32
BODY_HEIGHTS = (1.0, 3.0)
BODY_STARTS = ("spine", "legs", "none")  # whole body: one search from each generation 0 (`search`)
RETURN_S = 0.15  # whole body: back to the release pose this long before the predicted touchdown
# whole body: the 12 joints from the 8 angles of a waypoint (spine p/y, tail p/y, front legs p/r, hind legs p/r)
BODY_JOINTS = (0, 1, 2, 3, 4, 5, 4, 5, 6, 7, 6, 7)
BODY_LIMITS = (1.0, 1.0, 1.0, 1.0, 1.5, 1.5, 1.5, 1.5)  # rad
SPEEDS = (1.0, 2.0, 4.0)
HEIGHTS = (1.0, 3.0, 5.0, 10.0)
ORIENTATIONS = ((180.0, 0.0, 0.0), (90.0, 0.0, 0.0))
UPRIGHT = (0.0, 0.0, 0.0)  # control: dropped already upright, spine straight, no search
BASE_HEIGHT = 3.0
G = 9.81


# ----------------------------------------------------------------------------------------- the model
def make_sim(speed: float = 1.0):
    """A `LandingSim` whose servos are ``speed``× faster (module doc)."""
    from felis.learning.landing.evaluate import LandingSim, standing_waist_height
    from felis.servos import servo_model
    from felis.sim import MujocoRobot
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
    """Joint velocities (12) moving from the release pose (all 0) round the closed loop of ``waypoints`` at
    ``speed`` rad/s, repeated for ``duration`` s. ``waypoints`` (N, 2): the spine rule (tail and legs 0);
    with ``body``, (N, 8): the whole-body rule, which heads back to 0 from ``duration − 0.1 − return_s`` s
    (module doc).
    The target path is precomputed per tick, so the controller's integrated targets hit it exactly."""

    def __init__(self, waypoints, speed: float, duration: float, dt: float = DT, body: bool = False,
                 return_s: float = RETURN_S):
        w = np.asarray(waypoints, dtype=float)
        if body:
            w = np.clip(np.round(w.reshape(-1, 8), 3), -np.array(BODY_LIMITS), BODY_LIMITS)[:, BODY_JOINTS]
        else:
            w = np.clip(np.round(w.reshape(-1, 2), 3), -WAYPOINT_LIMIT, WAYPOINT_LIMIT)
        n_ticks = int(math.ceil(duration / dt)) + 2
        path, prev, i = [np.zeros(w.shape[1])], np.zeros(w.shape[1]), 0
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
        if body:  # back to the release pose before touchdown, at full speed
            k = max(1, int(round((duration - 0.1 - return_s) / dt)))
            if k < len(path):
                p = path[k]
                ticks = max(1, math.ceil(float(np.abs(p).max()) / (speed * dt) - 1e-9))
                back = [p * (1.0 - s / ticks) for s in range(1, ticks + 1)]
                path = np.vstack([path[:k + 1], *back, np.zeros((max(0, n_ticks - k - 1 - ticks), 12))])[:n_ticks]
        self.v = np.zeros((n_ticks, 12))
        self.v[1:len(path), :w.shape[1]] = np.diff(path, axis=0) / dt
        self.dt = dt

    def __call__(self, it, t: float) -> np.ndarray:
        i = int(round(t / self.dt))
        return self.v[i].copy() if 0 <= i < len(self.v) else np.zeros(12)


def circle(sign: int) -> np.ndarray:
    ring = [(1.0, 0.0), (0.0, sign * 1.0), (-1.0, 0.0), (0.0, -sign * 1.0)]
    return np.array([ring[i % 4] for i in range(N_WAYPOINTS)])


def leg_loop(sign: int) -> np.ndarray:
    """(N, 2) leg (pitch, roll) waypoints: roll out across the roll axis, pitch up along it, roll back, pitch
    down, and again; ``sign`` picks the roll direction."""
    r = sign * BODY_LIMITS[5]
    ring = [(0.0, r), (BODY_LIMITS[4], r), (BODY_LIMITS[4], 0.0), (0.0, 0.0)]
    return np.array([ring[i % 4] for i in range(N_WAYPOINTS)])


def stored_waypoints(orientation) -> np.ndarray | None:
    """The tuned rule's waypoints for ``orientation`` from landing_samples.json, if there is one."""
    from felis.learning.landing.samples import DEFAULT_SAMPLES_PATH

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


def measure(sim, orientation, height_m: float, speed: float, waypoints, duration: float | None = None,
            body: bool = False) -> dict:
    """One drop of ``sim`` (from `make_sim` (``speed``)) under the loop rule of ``waypoints`` (the
    whole-body rule with ``body``): the tilt at release and at the last tick before touchdown (or at the
    end of the run if it never touches down), the rotation (start − touchdown tilt, degrees), and the
    landing outcome."""
    from felis.controllers.landing import LandingController
    from felis.learning.landing.policy import MAX_SPEED
    from felis.scenarios.drop import Drop

    fall = math.sqrt(2.0 * height_m / G)
    rule = LoopRule(waypoints, speed * MAX_SPEED, fall + 0.1, body=body)
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
    return {"orientation": list(orientation), "height_m": height_m, "speed": speed,
            "joints": "whole body" if body else "spine", "fall_s": round(fall, 3),
            "touchdown_s": None if td is None else round(td, 3), "start_tilt_deg": round(start, 1),
            "tilt_at_touchdown_deg": round(at_td, 1), "upper_tilt_deg": round(_tilt(a[i, 1]), 1),
            "lower_tilt_deg": round(_tilt(a[i, 2]), 1), "rotation_deg": round(start - at_td, 1),
            "upper_rate_deg_s": round(float(a[i, 3]), 0),
            "landed": bool(out.landed), "why": out.why or None,
            "waypoints_rad": np.round(np.asarray(waypoints, dtype=float).reshape(-1, 8 if body else 2), 3).tolist()}


def search(sim, orientation, height_m: float, speed: float, seed, generations: int = GENERATIONS,
           population: int = POPULATION, body: bool = False, start: str = "spine") -> tuple[dict, int]:
    """Best loop rule for one case by the module doc's cross-entropy search; (its measurement, rollouts).
    ``start``: what generation 0 holds besides random draws: "spine" (the spine's circles and tuned rule),
    "legs" (those and the legs' loop with the spine's circles; whole body only) or "none"."""
    rng = np.random.default_rng(seed)
    width = 8 if body else 2
    dims = width * N_WAYPOINTS
    limit = np.tile(BODY_LIMITS if body else (WAYPOINT_LIMIT,) * 2, N_WAYPOINTS)
    spine = [circle(+1), circle(-1)]
    w = stored_waypoints(orientation)
    if w is not None:
        spine.append(w)
    seeds = []
    for sw in spine if start in ("spine", "legs") else ():  # on the spine, the rest held
        x0 = np.zeros((N_WAYPOINTS, width))
        x0[:, :2] = sw
        seeds.append(x0.ravel())
    if body and start == "legs":  # and the legs' loop (module doc) both ways, with the spine's circle both ways
        for sign in (+1, -1):
            for sw in spine[:2]:
                x0 = np.zeros((N_WAYPOINTS, width))
                x0[:, :2] = sw
                x0[:, 4:6] = x0[:, 6:8] = leg_loop(sign)
                seeds.append(x0.ravel())
    mean, spread = np.zeros(dims), np.full(dims, INIT_SPREAD)
    best: tuple[float, dict] | None = None
    used = 0
    for g in range(generations):
        x = np.clip(mean + spread * rng.standard_normal((population, dims)), -limit, limit)
        if g == 0:
            for i, s in enumerate(seeds[:population]):
                x[i] = s
        elif best is not None:
            x[0] = np.asarray(best[1]["waypoints_rad"]).ravel()
        scores = np.empty(population)
        for i in range(population):
            r = measure(sim, orientation, height_m, speed, x[i], body=body)
            scores[i] = r["rotation_deg"] / 180.0 + (1.0 if r["landed"] else 0.0)
            if best is None or scores[i] > best[0]:
                best = (float(scores[i]), r)
        used += population
        elite = x[np.argsort(-scores, kind="stable")[:ELITES]]
        mean, spread = elite.mean(axis=0), np.maximum(elite.std(axis=0), MIN_SPREAD)
    assert best is not None
    return best[1], used


def cases() -> list[tuple[int, tuple, float, float, bool]]:
    """(index, orientation, height, speed, whole body): the speed sweep at 3 m, the height sweep at ×1,
    the upright control, then the whole body at ×1."""
    out = []
    for o in ORIENTATIONS:
        for k in SPEEDS:
            out.append((o, BASE_HEIGHT, k, False))
        for h in HEIGHTS:
            if h != BASE_HEIGHT:
                out.append((o, h, 1.0, False))
    out += [(UPRIGHT, h, 1.0, False) for h in HEIGHTS]
    out += [(o, h, 1.0, True) for o in ORIENTATIONS for h in BODY_HEIGHTS]
    return [(i, *c) for i, c in enumerate(out)]


_SIMS: dict[float, object] = {}


def _run_case(args) -> dict:
    index, orientation, height, speed, body, generations, population = args
    if speed not in _SIMS:
        _SIMS[speed] = make_sim(speed)
    t0 = time.perf_counter()
    if tuple(orientation) == UPRIGHT:
        return {**measure(_SIMS[speed], orientation, height, speed, np.zeros((N_WAYPOINTS, 2))), "rollouts": 1,
                "search_s": round(time.perf_counter() - t0, 1)}
    if not body:
        r, n = search(_SIMS[speed], orientation, height, speed, seed=index, generations=generations,
                      population=population)
        return {**r, "rollouts": n, "search_s": round(time.perf_counter() - t0, 1)}
    best, n = None, 0
    for k, start in enumerate(BODY_STARTS):  # the best of independent searches: one alone varies a lot
        r, used = search(_SIMS[speed], orientation, height, speed, seed=[index, k], generations=generations,
                         population=population, body=True, start=start)
        n += used
        r = {**r, "start": start}
        if best is None or (r["landed"], r["rotation_deg"]) > (best["landed"], best["rotation_deg"]):
            best = r
    return {**best, "rollouts": n, "search_s": round(time.perf_counter() - t0, 1)}


def run(workers: int | None = None, generations: int = GENERATIONS, population: int = POPULATION,
        body_generations: int = BODY_GENERATIONS, body_population: int = BODY_POPULATION) -> list[dict]:
    jobs = [(*c, *((body_generations, body_population) if c[4] else (generations, population))) for c in cases()]
    # longest first (whole body, high drops, then fast servos) so two workers finish together; results back
    # in case order
    order = sorted(range(len(jobs)), key=lambda i: (-jobs[i][4], -jobs[i][2], -jobs[i][3], i))
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
    head = (f"{'orientation':<16} {'joints':<10} {'servo':>5} {'drop m':>6} {'fall s':>6} {'start°':>6} "
            f"{'tilt at td°':>11} {'upper/lower°':>12} {'rotation°':>9} {'ω td°/s':>7} {'landed':>6}  "
            "why not (first reason)")
    lines = [head, "-" * len(head)]
    for r in rows:
        o = "(" + ", ".join(f"{v:g}" for v in r["orientation"]) + ")"
        lines.append(f"{o:<16} {r['joints']:<10} {'×' + format(r['speed'], 'g'):>5} {r['height_m']:>6g} "
                     f"{r['fall_s']:>6.2f} {r['start_tilt_deg']:>6.0f} {r['tilt_at_touchdown_deg']:>11.0f} "
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
    body_gens, body_pop = (2, 8) if a.quick else (BODY_GENERATIONS, BODY_POPULATION)
    t0 = time.perf_counter()
    rows = run(a.workers, gens, pop, body_gens, body_pop)
    wall = time.perf_counter() - t0
    print(table(rows))
    print(f"{sum(r['rollouts'] for r in rows)} rollouts, {wall:.0f} s wall")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"command": " ".join(["bench/landing_limits.py", *(argv or sys.argv[1:])]),
                       "generations": gens, "population": pop, "body_generations": body_gens,
                       "body_population": body_pop, "wall_s": round(wall, 1), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
