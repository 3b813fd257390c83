"""Benchmark: landing-training rollouts against a bare ``mj_step`` loop, and the pool speed-up 1 → 2 workers.

**Episodes per second, one process.** An episode is one job of `felis train landing`: a seeded random
simple behaviour (`random_simple`) dropped in one of the 7 training orientations from 3 m, 200 ticks
at 100 Hz, 1 kHz physics (`landing.task.run_rollout`: `LandingSim.run` with the `LandingController`,
the `LandingRecorder` sub-step hook and the motion recorder), timed two ways: the *rollout* alone, and
the whole *job* the evaluator maps (`landing.task.evaluate_job`: the rollout, then its features and
scores D and S). The anchor is the loop a MuJoCo user would write by hand on the same compiled model
(a copy, armed gains and servo parameters included): reset, the same initial state, then per tick set
``ctrl`` and call ``mj_step`` once per physics step. Its ``ctrl`` per tick is the one felis wrote in
that episode (recorded once beforehand), so both do the same physics; the final states are compared
bit for bit. A batch is one episode per orientation; batches interleave (bare, rollout, job, bare, …)
and each ratio is the median of the per-batch ratios (felis ÷ bare).

**Process-pool speed-up.** One simple-stage generation's evaluations (``--population`` individuals
per orientation × 7 orientations, in training's job order) through the evaluator training uses
(`make_evaluator` with `init_worker`): ``workers=1`` (inline, in this process) against ``workers=2``
(a process pool), with the evaluator's default chunking unless ``--chunksize``. Both are long-lived, as
in training: their first map (pool start-up, one simulation built per worker) is left out of the
speed-up; its time is reported beside the steady maps' medians. Maps interleave (1, 2, 1, 2, …); the
speed-up is the median of the per-pair ratios (time with 1 ÷ time with 2). Goal: ≥ 1.7×. The results
of the two are compared for equality (they must be identical). The default map, 8 × 7 = 56 jobs, is
cut into 8 batches of 7, four per worker, as a full 24 × 7 generation is (8 batches of 21); at 28 jobs
the default chunking makes 7 batches of 4, so one worker runs 16 jobs to the other's 12 and the
speed-up cannot pass 1.75× (``--population 4``; ``--chunksize 1`` lifts it to about 1.9×).

**Batched rollouts** (issue 21). The same generation's jobs (``--population`` individuals × 7 orientations)
as one batch of `felis.sim.batch.DropBatch` (`mujoco.rollout` on every core, 10 physics steps per tick, the
policies of the whole batch evaluated in numpy once per tick, the verdict's truth from sensors): physics
steps per second, policy and verdict included. Two anchors in the same run: *open loop*, `mujoco.rollout`
of the very controls the batch sent (recorded on a first run), on the same threads, in one call per batch
(the physics alone: goal ratio ≥ 0.8); and *today*, the sequential rollouts (`run_rollout`, one process,
as part 1 times them; goal ≥ 2×). Runs interleave (open loop, batch, sequential, …); medians.

    python bench/landing_speed.py [--repeats N] [--population P] [--chunksize C] [--json] [--batched-only]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import time
from dataclasses import dataclass

import mujoco
import mujoco.rollout
import numpy as np

from felis.learning.common.evaluator import _chunk, make_evaluator
from felis.learning.landing import task as lk
from felis.learning.landing import train as lt
from felis.learning.landing.config import TrainConfig
from felis.learning.landing.nets import random_simple

GOAL = 1.7


@dataclass
class Replay:
    """What the bare loop needs to redo an episode: its initial state and the ``ctrl`` of every tick."""

    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray  # (ticks, nu)
    final_qpos: np.ndarray  # felis's state at the end, for the bit-for-bit check


def setup(population: int, seed: int = 0) -> tuple[lk.Task, list[tuple]]:
    """The training task (default config and samples) and one generation's jobs, as `_simple_generation`
    builds them: one population of seeded random simple behaviours per orientation, orientation-major."""
    cfg = TrainConfig(population=max(2, population), seed=seed)
    task, _ = lk.make_task(cfg, lk.load_task_samples(cfg, None))
    rng = np.random.default_rng(seed)
    pops = [[random_simple(rng, cfg.max_hidden) for _ in range(population)] for _ in range(task.k)]
    return task, [(b, k) for k in range(task.k) for b in pops[k]]


def capture(sim, task: lk.Task, job: tuple) -> Replay:
    """Run ``job``'s episode once as `run_rollout` does, recording the initial state and each tick's ctrl."""
    from felis.controllers.landing import LandingController
    from felis.scenarios.drop import Drop

    behaviour, k = job
    d = sim.robot.data
    ctrls: list[np.ndarray] = []
    start: list[np.ndarray] = []

    def monitor(state, command) -> None:  # after the write, before the physics steps of this tick
        if not ctrls:
            start.extend((d.qpos.copy(), d.qvel.copy()))
        ctrls.append(d.ctrl.copy())

    roll, pitch, yaw = task.orientations[k]
    sim.run(Drop(roll, pitch, yaw, task.heights_m[k]), LandingController(behaviour), monitors=[monitor],
            duration=task.steps / lt.RATE_HZ)
    return Replay(start[0], start[1], np.array(ctrls), d.qpos.copy())


def bare_episodes(m: mujoco.MjModel, d: mujoco.MjData, replays: list[Replay]) -> float:
    """Seconds for the hand-written loop over ``replays``."""
    substeps = int(round(1.0 / (lt.RATE_HZ * m.opt.timestep)))
    t0 = time.perf_counter()
    for r in replays:
        mujoco.mj_resetData(m, d)
        d.qpos[:] = r.qpos
        d.qvel[:] = r.qvel
        mujoco.mj_forward(m, d)
        for c in r.ctrl:
            d.ctrl[:] = c
            for _ in range(substeps):
                mujoco.mj_step(m, d)
    return time.perf_counter() - t0


def rollout_episodes(jobs: list[tuple]) -> float:
    """Seconds for the rollouts alone (`run_rollout`) of ``jobs`` on this process's worker simulation."""
    sim, task = lk._WORKER
    t0 = time.perf_counter()
    for behaviour, k in jobs:
        lk.run_rollout(sim, task, behaviour, k)
    return time.perf_counter() - t0


def job_episodes(jobs: list[tuple]) -> float:
    """Seconds for the whole jobs (`evaluate_job`: rollout and scoring)."""
    t0 = time.perf_counter()
    for j in jobs:
        lk.evaluate_job(j)
    return time.perf_counter() - t0


def episode_speed(task: lk.Task, jobs: list[tuple], repeats: int) -> dict:
    """Part 1 (module doc): episodes/s of bare, rollout and job, and the medians of the per-batch ratios."""
    batch = [next(j for j in jobs if j[1] == k) for k in range(task.k)]  # one episode per orientation
    lk.init_worker(task)
    try:
        sim = lk._WORKER[0]
        replays = [capture(sim, task, j) for j in batch]
        m = copy.deepcopy(sim.robot.model)  # armed gains, same servo parameters
        d = mujoco.MjData(m)
        same = []
        for r in replays:  # the anchor redoes felis's physics exactly
            bare_episodes(m, d, [r])
            same.append(bool(np.array_equal(d.qpos, r.final_qpos)))
        rollout_episodes(batch[:1])  # warm-up
        job_episodes(batch[:1])
        b_s, r_s, j_s = [], [], []
        for _ in range(repeats):
            b_s.append(bare_episodes(m, d, replays))
            r_s.append(rollout_episodes(batch))
            j_s.append(job_episodes(batch))
    finally:
        lk.release_worker()
    n = len(batch)
    rate = lambda s: round(n / statistics.median(s), 2)  # noqa: E731
    r_ratio = sorted(b / r for b, r in zip(b_s, r_s, strict=True))
    j_ratio = sorted(b / j for b, j in zip(b_s, j_s, strict=True))
    return {
        "episode": f"cat, {task.k} training orientations from {task.heights_m[0]:g} m, {task.steps} ticks at "
                   f"{lt.RATE_HZ:g} Hz, physics {1 / m.opt.timestep:g} Hz, seeded random simple behaviour",
        "episodes_per_batch": n,
        "bare_mj_step_episodes_per_s": rate(b_s),
        "rollout_episodes_per_s": rate(r_s),
        "job_episodes_per_s": rate(j_s),
        "rollout_ratio": round(statistics.median(r_ratio), 3),
        "rollout_ratio_range": [round(r_ratio[0], 3), round(r_ratio[-1], 3)],
        "job_ratio": round(statistics.median(j_ratio), 3),
        "job_ratio_range": [round(j_ratio[0], 3), round(j_ratio[-1], 3)],
        "anchor_same_physics": all(same),
    }


def pool_speedup(task: lk.Task, jobs: list[tuple], repeats: int, chunksize: int | None = None) -> dict:
    """Part 2 (module doc): one generation's map with 1 and with 2 workers, start-up apart."""
    evs = {w: make_evaluator(None, w, initializer=lk.init_worker, initargs=(task,), chunksize=chunksize)
           for w in (1, 2)}
    try:
        first, times = {}, {1: [], 2: []}
        ref = None
        identical = True
        for w, ev in evs.items():  # first map: start-up (fork, one simulation per worker) + the jobs
            t0 = time.perf_counter()
            out = np.array(ev.map(lk.evaluate_job, jobs))
            first[w] = time.perf_counter() - t0
            ref = out if ref is None else ref
            identical &= bool(np.array_equal(out, ref, equal_nan=True))
        for _ in range(repeats):
            for w, ev in evs.items():
                t0 = time.perf_counter()
                out = np.array(ev.map(lk.evaluate_job, jobs))
                times[w].append(time.perf_counter() - t0)
                identical &= bool(np.array_equal(out, ref, equal_nan=True))
    finally:
        for ev in evs.values():
            ev.close()
        lk.release_worker()
    ratios = sorted(a / b for a, b in zip(times[1], times[2], strict=True))
    speedup = statistics.median(ratios)
    n, size = len(jobs), _chunk(len(jobs), 2, chunksize)
    return {
        "jobs_per_map": n,
        "chunksize_2_workers": size,
        "batches_2_workers": -(-n // size),
        "episodes_per_s_1_worker": round(n / statistics.median(times[1]), 2),
        "episodes_per_s_2_workers": round(n / statistics.median(times[2]), 2),
        "first_map_s": {str(w): round(t, 3) for w, t in first.items()},  # with start-up
        "map_s": {str(w): round(statistics.median(t), 3) for w, t in times.items()},  # steady, medians
        "speedup": round(speedup, 3),
        "speedup_range": [round(ratios[0], 3), round(ratios[-1], 3)],
        "goal": f">= {GOAL}",
        "met": speedup >= GOAL,
        "identical_results": identical,
    }


BATCH_GOAL_OPEN_LOOP = 0.8
BATCH_GOAL_TODAY = 2.0


def batched_speed(task: lk.Task, jobs: list[tuple], repeats: int) -> dict:
    """Part 3 (module doc): the jobs as one batch against open-loop `mujoco.rollout` and the sequential path."""
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.scenarios.drop import Drop

    drops = [Drop(*task.orientations[k], task.heights_m[k]) for _, k in jobs]
    behaviours = [b for b, _ in jobs]
    ticks = [task.steps] * len(jobs)
    sim = BatchLandingSim()
    batch = sim.batch
    B, T, P = len(jobs), task.steps, int(round(1.0 / (lt.RATE_HZ * batch.model.opt.timestep)))  # steps per tick
    ctrl = np.zeros((B, T * P, batch.model.nu))

    def record(k, st, sd, active):
        ctrl[active, k * P:(k + 1) * P] = batch.last_ctrl

    def run_batch(rec=None) -> float:
        t0 = time.perf_counter()
        res = batch.run(drops, LandingBatch(sim.spec, behaviours, np.arange(B)), sim.standing_waist_m, ticks=ticks,
                        record=rec)
        assert len(res) == B
        return time.perf_counter() - t0

    run_batch(record)  # the controls, for the open-loop anchor (and a warm-up)
    start, _ = batch.initial(drops)
    out_state = np.empty((B, T * P, batch.nstate))
    out_sens = np.empty((B, T * P, batch.model.nsensordata))
    pool = mujoco.rollout.Rollout(nthread=batch.nthread)  # the anchor's threads: as many as the batch's
    datas = [mujoco.MjData(batch.model) for _ in range(batch.nthread)]

    def open_loop() -> float:
        t0 = time.perf_counter()
        pool.rollout(batch.model, datas, start, ctrl, nstep=T * P, state=out_state, sensordata=out_sens)
        return time.perf_counter() - t0

    lk.init_worker(task)
    try:
        open_s, batch_s, seq_s = [], [], []
        for _ in range(repeats):
            open_s.append(open_loop())
            batch_s.append(run_batch())
            seq_s.append(rollout_episodes(jobs))
    finally:
        lk.release_worker()
        sim.close()
        pool.close()
    steps = B * T * P
    med = statistics.median
    r_open = sorted(o / b for o, b in zip(open_s, batch_s, strict=True))
    r_today = sorted(q / b for q, b in zip(seq_s, batch_s, strict=True))
    return {
        "batch": f"{B} cats ({len(jobs) // task.k} individuals × {task.k} orientations), {T} ticks, "
                 f"{batch.nthread} threads",
        "open_loop_steps_per_s": round(steps / med(open_s)),
        "batched_steps_per_s": round(steps / med(batch_s)),
        "sequential_steps_per_s": round(steps / med(seq_s)),
        "ratio_open_loop": round(med(r_open), 3),
        "ratio_open_loop_range": [round(r_open[0], 3), round(r_open[-1], 3)],
        "ratio_today": round(med(r_today), 3),
        "ratio_today_range": [round(r_today[0], 3), round(r_today[-1], 3)],
        "goals": f"open loop >= {BATCH_GOAL_OPEN_LOOP}, today >= {BATCH_GOAL_TODAY}",
        "met_open_loop": med(r_open) >= BATCH_GOAL_OPEN_LOOP,
        "met_today": med(r_today) >= BATCH_GOAL_TODAY,
        "met": med(r_open) >= BATCH_GOAL_OPEN_LOOP and med(r_today) >= BATCH_GOAL_TODAY,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="interleaved timed batches (each part)")
    ap.add_argument("--population", type=int, default=8, help="individuals per orientation in the pool's map")
    ap.add_argument("--chunksize", type=int, default=None, help="jobs per pool batch (default: the evaluator's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--batched-only", action="store_true", help="part 3 only (batched rollouts)")
    args = ap.parse_args()

    task, jobs = setup(args.population, args.seed)
    if args.batched_only:
        b = batched_speed(task, jobs, args.repeats)
        print(json.dumps({"cpus": os.cpu_count(), "batched": b}, indent=2))
        return
    result = {"cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2),
              "repeats": args.repeats, "one_process": episode_speed(task, jobs, args.repeats),
              "pool": pool_speedup(task, jobs, args.repeats, args.chunksize),
              "batched": batched_speed(task, jobs, args.repeats)}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    e, p = result["one_process"], result["pool"]
    print(f"landing_speed: {e['episode']}; medians of {args.repeats} batches")
    print(f"  bare mj_step loop      : {e['bare_mj_step_episodes_per_s']:8.2f} episodes/s   (anchor; same physics: "
          f"{'yes' if e['anchor_same_physics'] else 'NO'})")
    print(f"  felis rollout          : {e['rollout_episodes_per_s']:8.2f} episodes/s   ratio {e['rollout_ratio']:.3f} "
          f"(batches {e['rollout_ratio_range'][0]:.3f}…{e['rollout_ratio_range'][1]:.3f})")
    print(f"  felis job (+ scoring)  : {e['job_episodes_per_s']:8.2f} episodes/s   ratio {e['job_ratio']:.3f} "
          f"(batches {e['job_ratio_range'][0]:.3f}…{e['job_ratio_range'][1]:.3f})")
    print(f"  evaluator, {p['jobs_per_map']} jobs per map (pool: {p['batches_2_workers']} batches of "
          f"≤ {p['chunksize_2_workers']}); first map (with start-up, excluded) {p['first_map_s']['1']:.2f} s "
          f"inline, {p['first_map_s']['2']:.2f} s pool")
    print(f"    1 worker             : {p['episodes_per_s_1_worker']:8.2f} episodes/s   "
          f"({p['map_s']['1']:.2f} s a map)")
    print(f"    2 workers            : {p['episodes_per_s_2_workers']:8.2f} episodes/s   "
          f"({p['map_s']['2']:.2f} s a map) "
          f"speed-up {p['speedup']:.2f}× "
          f"(pairs {p['speedup_range'][0]:.2f}…{p['speedup_range'][1]:.2f}; goal ≥ {GOAL}×: "
          f"{'met' if p['met'] else 'NOT met'})")
    print(f"    identical results    : {'yes' if p['identical_results'] else 'NO'}")
    b = result["batched"]
    print(f"  batched ({b['batch']}), physics steps/s:")
    print(f"    open-loop mujoco.rollout: {b['open_loop_steps_per_s']:9d}   (anchor: the same controls)")
    print(f"    felis batch             : {b['batched_steps_per_s']:9d}   ratio {b['ratio_open_loop']:.3f} "
          f"(runs {b['ratio_open_loop_range'][0]:.3f}…{b['ratio_open_loop_range'][1]:.3f}; goal ≥ "
          f"{BATCH_GOAL_OPEN_LOOP}: {'met' if b['met_open_loop'] else 'NOT met'})")
    print(f"    sequential (today)      : {b['sequential_steps_per_s']:9d}   batch ÷ today {b['ratio_today']:.2f}× "
          f"(runs {b['ratio_today_range'][0]:.2f}…{b['ratio_today_range'][1]:.2f}; goal ≥ {BATCH_GOAL_TODAY}×: "
          f"{'met' if b['met_today'] else 'NOT met'})")


if __name__ == "__main__":
    main()
