"""`felis.learning.landing.caps`: closed-loop behaviours imitated from library motions, evolved over caps of starts,
dispatched by the start's up axis, mirrored for the other half of the sphere."""

from pathlib import Path

import numpy as np
import pytest


def test_cap_drops_cover_the_cap_round_the_axis_and_nothing_beyond():
    """`cap_drops`: yaw-0 drops whose up axes lie within the cap's radius of the axis, spread over it (cos of the
    angle uniform: a quarter of them within the radius of the cap of a quarter of the area), reproducible."""
    from felis.learning.landing import caps as caps
    from felis.learning.landing.library import drop_up
    u = np.array([0.3, 0.8, -0.2])
    u /= np.linalg.norm(u)
    drops = caps.cap_drops(u, 30.0, 2000, 1.0, np.random.default_rng(3))
    ups = np.array([drop_up(d) for d in drops])
    ang = np.degrees(np.arccos(np.clip(ups @ u, -1, 1)))
    assert all(d.yaw_deg == 0.0 and d.height_m == 1.0 for d in drops)
    assert ang.max() <= 30.0 + 1e-3 and ang.min() < 3.0
    quarter = np.degrees(np.arccos(1 - (1 - np.cos(np.radians(30))) / 4))  # the cap of a quarter of the area
    assert 0.2 < np.mean(ang <= quarter) < 0.3
    assert abs(np.mean(ups @ np.cross(u, [1.0, 0, 0]))) < 0.02  # no side of the axis favoured
    again = caps.cap_drops(u, 30.0, 2000, 1.0, np.random.default_rng(3))
    assert again == drops


def test_a_genome_round_trips_and_a_population_runs_as_its_members_alone():
    """`genome`/`with_genome` keep the behaviour (same velocities); `run_population` of [b, b'] on two drops gives
    each member's own scores and verdicts, as one batch of one behaviour does; a genome of the wrong length is one
    line."""
    from felis.errors import ParameterError
    from felis.learning.landing import cap_policy
    from felis.learning.landing import caps as caps
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour
    from felis.scenarios.drop import Drop
    rng = np.random.default_rng(2)
    units = [GeneUnit(p, tuple(range(KINDS[p].n_available)), 3, rng.normal(0, 0.5, (3, KINDS[p].n_available + 1)),
                      rng.normal(0, 0.5, (len(KINDS[p].outputs), 4)), MAX_SPEED) for p in PARTS]
    b = SimpleBehaviour(*units).check()
    g = cap_policy.genome(b)
    same = cap_policy.with_genome(b, g.copy())
    it = rng.uniform(-1, 1, (7, 15))
    assert np.array_equal(same.velocities_many(it), b.velocities_many(it))
    other = cap_policy.with_genome(b, g + rng.normal(0, 0.3, g.shape))
    with pytest.raises(ParameterError, match="a genome of"):
        cap_policy.with_genome(b, g[:-1])
    drops = [Drop(0.0, 0.0, 0.0, 0.3), Drop(40.0, -20.0, 0.0, 0.3)]
    sim = design_sim("cat", nthread=1)
    try:
        s2, l2 = caps.run_population(sim, [b, other], drops)
        s_b, l_b = caps.run_population(sim, [b], drops)
        s_o, l_o = caps.run_population(sim, [other], drops)
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
    from felis.learning.landing import caps as caps
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour
    from felis.scenarios.drop import Drop
    rng = np.random.default_rng(5)
    b = SimpleBehaviour(*[GeneUnit(p, tuple(range(KINDS[p].n_available)), 2,
                                   rng.normal(0, 0.5, (2, KINDS[p].n_available + 1)),
                                   rng.normal(0, 0.5, (len(KINDS[p].outputs), 3)), MAX_SPEED) for p in PARTS]).check()
    drops = [Drop(30.0, 0.0, 0.0, 0.3)]
    sim = design_sim("cat", nthread=1)
    try:
        start = float(caps.run_population(sim, [b], drops)[0].mean())
        best, f, rollouts, history = caps.evolve(sim, b, drops, generations=1, popsize=2, sigma=0.5, seed=0)
        again = float(caps.run_population(sim, [best], drops)[0].mean())
        with pytest.raises(ParameterError, match="generations ≥ 1"):
            caps.evolve(sim, b, drops, generations=0, popsize=2, sigma=0.5)
    finally:
        sim.close()
    assert f >= start and abs(again - f) < 1e-9 and history == [round(f, 4)] and rollouts == 3


def test_late_holds_the_joints_then_runs_the_policy_on_its_own_clock():
    """`Late`: zero velocity for the first k ticks, then an open-loop table read at t − k·DT, or a behaviour's
    velocities; a library motion started one tick late by it scores what `optimum.evaluate`'s own ``late_ticks``
    run does (its worst of on time and one tick late)."""
    from felis.learning.landing import caps as caps
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.library import load_library
    from felis.learning.landing.library_build import up_drop
    from felis.learning.landing.motion import DT
    from felis.learning.landing.optimum import OpenLoop, evaluate
    tables = np.arange(2 * 5 * 12, dtype=float).reshape(2, 5, 12)
    late = caps.Late(OpenLoop(tables), 2)
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
        (one,) = evaluate(sim, [d], x, wrap=lambda pol, n: caps.Late(pol, 1))
        (worst,) = evaluate(sim, [d], x, late_ticks=1)
    finally:
        sim.close()
    assert worst[0] == min(on_time[0], one[0]) and worst[1].landed == (on_time[1].landed and one[1].landed)


def _random_behaviour(rng, hidden=3):
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour

    return SimpleBehaviour(*[GeneUnit(p, tuple(range(KINDS[p].n_available)), hidden,
                                      rng.normal(0, 0.5, (hidden, KINDS[p].n_available + 1)),
                                      rng.normal(0, 0.5, (len(KINDS[p].outputs), hidden + 1)), MAX_SPEED)
                             for p in PARTS]).check()


def test_mirroring_is_an_involution_that_swaps_the_sides():
    from felis.learning.landing import cap_policy

    rng = np.random.default_rng(0)
    it, v = rng.normal(size=(4, 15)), rng.normal(size=(4, 12))
    assert np.array_equal(cap_policy.mirror_inputs(cap_policy.mirror_inputs(it)), it)
    assert np.array_equal(cap_policy.mirror_velocities(cap_policy.mirror_velocities(v)), v)
    m = cap_policy.mirror_inputs(it)
    assert np.array_equal(m[:, 7], it[:, 9]) and np.array_equal(m[:, 8], -it[:, 10])  # fl ← fr, roll negated
    assert np.array_equal(m[:, 4], -it[:, 4]) and np.array_equal(m[:, 5], it[:, 5])  # body roll negated, pitch kept
    w = cap_policy.mirror_velocities(v)
    assert np.array_equal(w[:, 1], -v[:, 1]) and np.array_equal(w[:, 10], v[:, 8]) and np.array_equal(w[:, 11],
                                                                                                      -v[:, 9])


def test_cap_policy_takes_the_nearest_centre_and_runs_a_mirror_start_as_the_mirror_image():
    """On the simulated cat: each cat keeps the behaviour whose centre is nearest its start's up axis (mirrored for
    u_y < 0), and a behaviour run mirrored from a start scores what it scores from that start's mirror image (the
    cat is left–right symmetric); two centres and one behaviour is one line."""
    from felis.errors import ParameterError
    from felis.learning.landing import cap_policy
    from felis.learning.landing.designs import design_sim
    from felis.scenarios.drop import Drop

    rng = np.random.default_rng(4)
    bs = [_random_behaviour(rng) for _ in range(3)]
    centres = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    drops = [Drop(10.0, 5.0, 0.0, 0.3), Drop(80.0, -10.0, 30.0, 0.3), Drop(-80.0, -10.0, 0.0, 0.3),
             Drop(20.0, 70.0, 0.0, 0.3)]
    sim = design_sim("cat", nthread=1)
    try:
        from felis.controllers.landing import LandingBatch
        from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ
        from felis.learning.landing.optimum import score

        def run(policy, ds):
            res = sim.batch.run(ds, LandingBatch(sim.spec, [policy]), sim.standing_waist_m, rate_hz=RATE_HZ,
                                margin_s=MARGIN_S)
            return [score(r, sim.standing_waist_m) for r in res]

        pol = cap_policy.CapPolicy(centres, bs)
        run(pol, drops)
        assert [pol.choice[i] for i in range(4)] == [(0, False), (1, False), (1, True), (2, False)]
        (plain,) = run(cap_policy.CapPolicy(centres[1:2], bs[1:2]), [Drop(60.0, 15.0, 0.0, 0.3)])
        (mirrored,) = run(cap_policy.CapPolicy(centres[1:2], bs[1:2]), [Drop(-60.0, 15.0, 0.0, 0.3)])
    finally:
        sim.close()
    assert abs(plain[0] - mirrored[0]) < 1e-3 and plain[1].landed == mirrored[1].landed
    assert plain[1].tilt_deg == pytest.approx(mirrored[1].tilt_deg, abs=0.05)
    with pytest.raises(ParameterError, match="2 centres for 1 behaviours"):
        cap_policy.CapPolicy(centres[:2], bs[:1])
    with pytest.raises(ParameterError, match="half u_y ≥ 0"):
        cap_policy.CapPolicy([[0.0, -1.0, 0.0]], bs[:1])


def test_cell_drops_are_the_starts_the_dispatch_gives_that_centre():
    from felis.errors import ParameterError
    from felis.learning.landing import cap_policy, caps
    from felis.learning.landing.library import drop_up
    from felis.learning.landing.library_build import fibonacci_ups

    centres = fibonacci_ups(24, 130.0)
    rng = np.random.default_rng(0)
    for k in (0, 4, len(centres) - 1):
        drops = caps.cell_drops(centres, k, 42.0, 40, 1.0, rng)
        u = np.array([drop_up(d) for d in drops])
        assert len(drops) == 40 and np.all(u[:, 1] >= 0) and all(d.yaw_deg == 0 for d in drops)
        assert np.all(cap_policy.nearest_centre(centres, u) == k)
        assert np.degrees(np.arccos(np.clip(u @ centres[k], -1, 1))).max() <= 42.0 + 1e-3
    with pytest.raises(ParameterError, match="fewer than 5 starts of its cell"):
        caps.cell_drops(np.array([[0, 0, 1.0], [0, 0, 1.0]]), 1, 10.0, 5, 1.0, rng)  # a twin takes its cell


def test_a_cap_policy_file_is_a_policy_wherever_one_is_named(tmp_path):
    """``caps`` names the shipped file; a caps file is told from a motion library by its format, so `check_policy`,
    `make_policy` (one cat: `CapRule`), `batch_controller` (`CapPolicy`) and `felis run landing`'s controller all run
    it; a library file stays a library."""
    from felis.controllers import make_controller
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing import cap_policy
    from felis.learning.landing.evaluate import batch_controller, caps_path, check_policy, library_path, make_policy
    from felis.learning.landing.library import DEFAULT_LIBRARY
    from felis.scenarios.drop import Drop
    from felis.spec import load_spec

    assert cap_policy.is_caps_file(cap_policy.SHIPPED_CAPS) and not cap_policy.is_caps_file(DEFAULT_LIBRARY)
    assert not cap_policy.is_caps_file(tmp_path / "none.json")
    copy = tmp_path / "mine.json"
    copy.write_bytes(cap_policy.SHIPPED_CAPS.read_bytes())
    for name in ("caps", str(copy)):
        assert check_policy(name) == name and library_path(name) is None and caps_path(name) is not None
        assert isinstance(make_policy(name, Drop(0.0, 0.0, 0.0, 1.0)).policy, cap_policy.CapRule)
        b = batch_controller(load_spec("cat"), name, [Drop(0.0, 0.0, 0.0, 1.0)])
        assert isinstance(b, LandingBatch) and isinstance(b.policies[0], cap_policy.CapPolicy)
        assert isinstance(make_controller("landing", policy=Path(name), drop_height=1.0).policy, cap_policy.CapRule)
    assert library_path(str(DEFAULT_LIBRARY)) == DEFAULT_LIBRARY and caps_path(str(DEFAULT_LIBRARY)) is None


def test_a_cap_rule_is_its_batch_for_one_cat():
    """`CapRule` picks at its first call what `CapPolicy` picks for that cat (mirrored in the other half) and keeps
    it: the same velocities, to rounding, tick after tick, while the attitude changes."""
    from felis.learning.landing import cap_policy

    _, centres, behaviours = cap_policy.load_caps(cap_policy.SHIPPED_CAPS)
    rng = np.random.default_rng(5)
    it = rng.uniform(-0.9, 0.9, (2, 6, 15))  # two cats, six ticks each
    it[0, :, 4] = np.abs(it[0, :, 4])  # the first rolled one way (u_y > 0)
    it[1, :, 4] = -np.abs(it[1, :, 4])  # the second the other way: u_y < 0, mirrored
    batch = cap_policy.CapPolicy(centres, behaviours)
    rules = [cap_policy.CapRule(centres, behaviours) for _ in range(2)]
    for k in range(6):
        t = np.full(2, k * 0.01)
        want = batch(it[:, k], t, np.arange(2))
        got = np.array([rules[i](it[i, k], t[i]) for i in range(2)])
        assert np.allclose(got, want, rtol=0, atol=1e-12) and np.abs(want).max() > 0.1
    assert rules[0].batch.choice[0] == batch.choice[0] and rules[1].batch.choice[0] == batch.choice[1]
    assert batch.choice[1][1] and not batch.choice[0][1]


def _caps_doc(**edit) -> dict:
    import json

    from felis.learning.landing import cap_policy

    d = json.loads(cap_policy.SHIPPED_CAPS.read_text())
    d["caps"] = d["caps"][:2]
    for k, v in edit.items():
        d["caps"][0][k] = v
    return d


@pytest.mark.parametrize("edit, says", [
    ({"genome": [0.0] * 5}, "a genome of 5 weights"),
    ({"centre": [0.0, 0.5, 0.5]}, "not a unit vector"),
    ({"centre": [0.0, -1.0, 0.0]}, "half u_y ≥ 0"),
    ({"genome": None}, "caps: "),
], ids=["short-genome", "centre-off-the-sphere", "centre-mirrored", "no-genome"])
def test_a_bad_cap_policy_file_is_one_line_naming_it_where_a_policy_is_named(tmp_path, edit, says):
    """`felis eval landing --policy FILE` and `felis run landing --policy FILE` refuse a broken caps file in one line
    that names it and says what is wrong (not as a broken motion library), and run nothing."""
    import json
    import subprocess
    import sys

    p = tmp_path / "bad.json"
    p.write_text(json.dumps(_caps_doc(**edit)))
    nan = tmp_path / "nan.json"
    d = _caps_doc()
    d["caps"][1]["genome"][3] = float("nan")
    nan.write_text(json.dumps(d))
    for f, what in ((p, says), (nan, "not a finite number")):
        for argv in (["eval", "landing", "--drops", "random:1", "--policy", str(f)],
                     ["run", "landing", "--robot", "cat", "--height", "1", "--policy", str(f)]):
            r = subprocess.run([sys.executable, "-m", "felis", *argv], capture_output=True, text=True, timeout=120)
            err = r.stderr.strip()
            assert r.returncode != 0 and r.stdout == "" and "\n" not in err, err
            assert f"caps: {f}" in err and what in err and "library" not in err, err
