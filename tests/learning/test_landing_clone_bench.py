"""``bench/landing_clone.py``: a simple behaviour of the paper's nets fitted by regression to a library motion."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_clone.py"


def test_fit_recovers_a_behaviour_it_can_represent():
    """The known-good case: velocities made by a simple behaviour with every input (h = 4) are fitted by one of the
    same shape to a small fraction of their spread, and the fit is a valid `SimpleBehaviour` that runs as the
    controller runs it."""
    import torch

    from felis.errors import ParameterError
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour

    rng = np.random.default_rng(1)
    units = []
    for p in PARTS:
        k = KINDS[p]
        w1, w2 = rng.normal(0, 0.5, size=(4, k.n_available + 1)), rng.normal(0, 0.5, size=(len(k.outputs), 5))
        units.append(GeneUnit(p, tuple(range(k.n_available)), 4, w1, w2, MAX_SPEED))
    teacher = SimpleBehaviour(*units).check()
    it = rng.uniform(-1, 1, size=(300, 15))
    v = teacher.velocities_many(it)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the bench runs it: a small net, and the other test worker on the other core
    try:
        policy, rms, behaviour = load_bench("landing_clone").fit(it, v, hidden=4, steps=800)
    finally:
        torch.set_num_threads(threads)
    assert isinstance(behaviour, SimpleBehaviour) and behaviour.check() is behaviour
    assert rms < 0.1 * float(np.std(v)), (rms, float(np.std(v)))
    assert np.allclose(policy(it[:5]), behaviour.velocities_many(it[:5]))
    with pytest.raises(ParameterError, match="hidden ≥ 1"):
        load_bench("landing_clone").fit(it, v, hidden=0, steps=1)


def test_clone_bench_runs_one_motion():
    r = subprocess.run([sys.executable, str(BENCH), "--n", "1", "--steps", "50", "--json"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    (m,) = res["motions"]
    assert m["open_loop_landed"] is True and m["ticks"] == 145 and np.isfinite(m["rms_rad_s"])
    assert res["clone_landed"] == int(m["clone_landed"]) and res["motions_tried"] == 1 + len(res["skipped_not_landing"])
    bad = subprocess.run([sys.executable, str(BENCH), "--n", "0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--n and --hidden must be ≥ 1" in bad.stderr


def test_the_shipped_clone_runs_are_what_the_docs_say():
    """docs/landing.md "Whether a net holds one" and the README: of 24 motions that land their start, the paper-size
    fit lands 12, with DAgger 14, 64 neurons and a clock 6; median velocity error 0.69, 0.79, 0.61 rad/s."""
    root = BENCH.parents[1]
    runs = json.loads((root / "learning" / "weights" / "landing_clone-1m.json").read_text())["runs"]
    got = {k: (len(r["motions"]), r["clone_landed"], round(float(np.median([m["rms_rad_s"] for m in r["motions"]])), 2))
           for k, r in runs.items()}
    assert got == {"paper-size": (24, 12, 0.69), "dagger-3": (24, 14, 0.79), "64-hidden-clock": (24, 6, 0.61)}
    for r in runs.values():
        assert all(m["open_loop_landed"] for m in r["motions"]) and len(r["skipped_not_landing"]) == 4
        assert r["clone_landed"] == sum(m["clone_landed"] for m in r["motions"])
    assert runs["paper-size"]["hidden"] == 8 and runs["dagger-3"]["rounds"] == 3 and runs["64-hidden-clock"]["clock"]
    assert [m["entry"] for m in runs["paper-size"]["motions"]] == [m["entry"] for m in runs["dagger-3"]["motions"]]
    text = " ".join((root / "docs" / "landing.md").read_text().split())
    assert "| 12 of 24 | 0.69 rad/s |" in text and "| 14 of 24 |" in text and "| 6 of 24 | 0.61 rad/s |" in text
    assert "drop 12 times of 24" in " ".join((root / "README.md").read_text().split())


# ------------------------------------------------------------------ the fitted behaviour evolved over a cap of starts


def test_cap_drops_cover_the_cap_round_the_axis_and_nothing_beyond():
    """`cap_drops`: yaw-0 drops whose up axes lie within the cap's radius of the axis, spread over it (cos of the
    angle uniform: a quarter of them within the radius of the cap of a quarter of the area), reproducible."""
    from felis.learning.landing.library import drop_up

    bench = load_bench("landing_clone")
    u = np.array([0.3, 0.8, -0.2])
    u /= np.linalg.norm(u)
    drops = bench.cap_drops(u, 30.0, 2000, 1.0, np.random.default_rng(3))
    ups = np.array([drop_up(d) for d in drops])
    ang = np.degrees(np.arccos(np.clip(ups @ u, -1, 1)))
    assert all(d.yaw_deg == 0.0 and d.height_m == 1.0 for d in drops)
    assert ang.max() <= 30.0 + 1e-3 and ang.min() < 3.0
    quarter = np.degrees(np.arccos(1 - (1 - np.cos(np.radians(30))) / 4))  # the cap of a quarter of the area
    assert 0.2 < np.mean(ang <= quarter) < 0.3
    assert abs(np.mean(ups @ np.cross(u, [1.0, 0, 0]))) < 0.02  # no side of the axis favoured
    again = bench.cap_drops(u, 30.0, 2000, 1.0, np.random.default_rng(3))
    assert again == drops


def test_a_genome_round_trips_and_a_population_runs_as_its_members_alone():
    """`genome`/`with_genome` keep the behaviour (same velocities); `run_population` of [b, b'] on two drops gives
    each member's own scores and verdicts, as one batch of one behaviour does; a genome of the wrong length is one
    line."""
    from felis.errors import ParameterError
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour
    from felis.scenarios.drop import Drop

    bench = load_bench("landing_clone")
    rng = np.random.default_rng(2)
    units = [GeneUnit(p, tuple(range(KINDS[p].n_available)), 3, rng.normal(0, 0.5, (3, KINDS[p].n_available + 1)),
                      rng.normal(0, 0.5, (len(KINDS[p].outputs), 4)), MAX_SPEED) for p in PARTS]
    b = SimpleBehaviour(*units).check()
    g = bench.genome(b)
    same = bench.with_genome(b, g.copy())
    it = rng.uniform(-1, 1, (7, 15))
    assert np.array_equal(same.velocities_many(it), b.velocities_many(it))
    other = bench.with_genome(b, g + rng.normal(0, 0.3, g.shape))
    with pytest.raises(ParameterError, match="a genome of"):
        bench.with_genome(b, g[:-1])
    drops = [Drop(0.0, 0.0, 0.0, 0.3), Drop(40.0, -20.0, 0.0, 0.3)]
    sim = design_sim("cat", nthread=1)
    try:
        s2, l2 = bench.run_population(sim, [b, other], drops)
        s_b, l_b = bench.run_population(sim, [b], drops)
        s_o, l_o = bench.run_population(sim, [other], drops)
    finally:
        sim.close()
    assert s2.shape == (2, 2) and l2.dtype == bool
    assert np.allclose(s2[0], s_b[0], atol=1e-9) and np.allclose(s2[1], s_o[0], atol=1e-9)
    assert np.array_equal(l2, np.vstack([l_b, l_o]))
    assert np.all(np.isfinite(s2)) and np.all((s2 >= -1) & (s2 <= 8))


def test_evolve_keeps_the_best_it_scored_and_refuses_a_bad_budget():
    """One generation of two on one drop: the behaviour returned scores (run again) what `evolve` says, which is at
    least its start's; the history has one entry; a zero budget is one line."""
    from felis.errors import ParameterError
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour
    from felis.scenarios.drop import Drop

    bench = load_bench("landing_clone")
    rng = np.random.default_rng(5)
    b = SimpleBehaviour(*[GeneUnit(p, tuple(range(KINDS[p].n_available)), 2,
                                   rng.normal(0, 0.5, (2, KINDS[p].n_available + 1)),
                                   rng.normal(0, 0.5, (len(KINDS[p].outputs), 3)), MAX_SPEED) for p in PARTS]).check()
    drops = [Drop(30.0, 0.0, 0.0, 0.3)]
    sim = design_sim("cat", nthread=1)
    try:
        start = float(bench.run_population(sim, [b], drops)[0].mean())
        best, f, rollouts, history = bench.evolve(sim, b, drops, generations=1, popsize=2, sigma=0.5, seed=0)
        again = float(bench.run_population(sim, [best], drops)[0].mean())
        with pytest.raises(ParameterError, match="generations ≥ 1"):
            bench.evolve(sim, b, drops, generations=0, popsize=2, sigma=0.5)
    finally:
        sim.close()
    assert f >= start and abs(again - f) < 1e-9 and history == [round(f, 4)] and rollouts == 3


def test_clone_bench_evolves_one_motion_over_its_cap():
    r = subprocess.run([sys.executable, str(BENCH), "--n", "1", "--steps", "50", "--evolve", "1", "--popsize", "2",
                        "--train", "2", "--test", "2", "--late", "1", "--json"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    (m,) = res["motions"]
    p = m["patch"]
    assert (p["train"], p["test"], p["evolution_rollouts"]) == (2, 2, 2 + 2 * 2)
    assert all(0 <= p[k] <= 2 for k in p if k.endswith(("_train", "_test")) and k != "late_test")
    assert p["evolved_lands_own"] in (True, False) and len(p["best_after_generation"]) == 1
    assert res["evolution"]["generations"] == 1 and res["evolution"]["evolved_lands_test"] == p["evolved_lands_test"]
    assert list(p["late_test"]) == ["1"] and all(0 <= c <= 2 for c in p["late_test"]["1"].values())
    assert res["evolution"]["late_test"] == p["late_test"]
    for bad in (["--evolve", "-1"], ["--evolve", "2", "--clock"], ["--evolve", "2", "--patch", "0"],
                ["--evolve", "2", "--late", "-1"]):
        out = subprocess.run([sys.executable, str(BENCH), *bad], capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and "--evolve must be ≥ 0" in out.stderr, (bad, out.stderr)


def test_late_holds_the_joints_then_runs_the_policy_on_its_own_clock():
    """`Late`: zero velocity for the first k ticks, then an open-loop table read at t − k·DT, or a behaviour's
    velocities; a library motion started one tick late by it scores what `optimum.evaluate`'s own ``late_ticks``
    run does (its worst of on time and one tick late)."""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.library import load_library
    from felis.learning.landing.library_build import up_drop
    from felis.learning.landing.motion import DT
    from felis.learning.landing.optimum import OpenLoop, evaluate

    bench = load_bench("landing_clone")
    tables = np.arange(2 * 5 * 12, dtype=float).reshape(2, 5, 12)
    late = bench.Late(OpenLoop(tables), 2)
    t = np.array([0.0, 1.0, 2.0, 3.0, 2.0]) * DT
    v = late(np.zeros((5, 15)), t, np.array([0, 0, 0, 0, 1]))
    assert np.array_equal(v[:2], np.zeros((2, 12)))
    assert np.array_equal(v[2:], tables[[0, 0, 1], [0, 1, 0]])
    shelf = load_library().shelf(1.0)
    e = int(np.flatnonzero(shelf.landed)[0])
    d, x = up_drop(shelf.up[e], 1.0), shelf.x[e][None]
    sim = design_sim("cat", nthread=1)
    try:
        (on_time,) = evaluate(sim, [d], x)
        (one,) = evaluate(sim, [d], x, wrap=lambda pol, n: bench.Late(pol, 1))
        (worst,) = evaluate(sim, [d], x, late_ticks=1)
    finally:
        sim.close()
    assert worst[0] == min(on_time[0], one[0]) and worst[1].landed == (on_time[1].landed and one[1].landed)
