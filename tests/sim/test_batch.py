"""Batched drops (`felis.sim.batch.DropBatch`) against the sequential path (`felis.loop.run_loop` with a
`LandingRecorder`): the same outcomes, bit for bit (`mujoco.batch.Batch` keeps each cat's warm start)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing.evaluate import (
    BatchLandingSim,
    LandingSim,
    batch_controller,
    run_drops,
    run_drops_sequential,
    shipped_policy,
)
from felis.scenarios.drop import Drop, random_drops


@pytest.fixture(scope="module")
def drops():
    return random_drops(6, seed=0, heights=(1.0,)) + [Drop(20.0, -30.0, 10.0, 1.0), Drop(0.0, 0.0, 0.0, 0.5)]


def _same(a, b, rel: float = 0.0) -> bool:
    """Two outcomes' every figure equal, unrounded (floats within ``rel``; NaN equal to NaN: a figure a drop does
    not have); the policy's name apart."""
    x, y = vars(a), vars(b)
    return x.keys() == y.keys() and all(k == "policy" or
        x[k] == y[k] or (isinstance(x[k], float) and (math.isnan(x[k]) and math.isnan(y[k])
                                                      or math.isclose(x[k], y[k], rel_tol=rel)))
        for k in x)


@pytest.mark.parametrize("policy", ["passive", "library", "shipped", "caps", "caps+library"])
def test_batched_equals_sequential(drops, policy):
    """The physics is the loop's bit for bit, so a controller that computes the same numbers in both gives every
    figure exactly: the pose held, and the motion library (its table's rows on a simulation's ticks,
    `LibraryRule`). The evolved nets' batched ``einsum`` rounds in another order than one cat's matrix product
    (≤ 4e-15 on their outputs), which a drop carries to ~1e-13 of its figures; so do the cap policy's nets
    (`CapRule` one cat, `CapPolicy` the batch), and the default, ``caps+library``, which votes by attitude between
    them and the library at 1 m and 3 m (2.5 m: nearer 3 m by the ratio; the 3 m vote sends the upside-down drop to
    the 3 m cap policy, the others to the library)."""
    if policy == "caps+library":
        drops = drops + [Drop(40.0, 10.0, 0.0, 3.0), Drop(-100.0, 20.0, 0.0, 2.5), Drop(180.0, 0.0, 0.0, 3.0)]
    seq = run_drops_sequential(drops, policy, workers=1)
    bat = run_drops(drops, policy, workers=2)
    assert len(seq) == len(bat) == len(drops)
    assert any(a.touchdown_s is not None for a in seq)  # contacts, where a cold solver start would show
    for a, b in zip(seq, bat, strict=True):
        assert _same(a, b, 0.0 if policy in ("passive", "library") else 1e-9), (vars(a), vars(b))


def test_every_tick_is_the_loops_through_touchdown(drops):
    """The batch's state after each tick is the loop's, exactly: time, joint angles as the servos report
    them, the IMU's attitude, in free flight and through the impact (the solver's warm start kept)."""
    d = drops[-1]  # 0.5 m: touchdown within the run
    seq = LandingSim()
    rec: list[np.ndarray] = []
    seq.run(d, "passive", monitors=[lambda s, c: rec.append(np.concatenate([[s.t], s.q, s.imu.quat]))],
            duration=0.6)
    seq.close()
    sim = BatchLandingSim(nthread=1)
    got: list[np.ndarray] = []

    def record(k, st, sd, active):
        got.append(np.concatenate([st[0, -1, :], sd[0, -1, sim.batch._imu]]))

    ctl = batch_controller(sim.spec, "passive", [d])
    (res,) = sim.batch.run([d], ctl, sim.standing_waist_m, ticks=[60], record=record)
    sim.close()
    assert res.truth.t.size and res.truth.t[0] < 0.5  # it touched down
    qadr = sim.batch._qadr
    for k in range(59):  # the loop's state at tick k+1 is the batch's after its tick k
        a, b = rec[k + 1], got[k]
        assert a[0] == b[0]
        assert np.array_equal(a[1:13], sim.batch._quantize(b[qadr][None])[0])
        assert np.array_equal(a[13:17], b[-4:])


def test_results_do_not_depend_on_threads_or_batch(drops):
    a = run_drops(drops, "shipped", workers=1)
    b = run_drops(drops[::-1], "shipped", workers=2)[::-1]
    for x, y in zip(a, b, strict=True):
        assert x.as_dict() == y.as_dict()


def test_upright_drop_lands_and_upside_down_does_not():
    out = run_drops([Drop(0.0, 0.0, 0.0, 0.3), Drop(180.0, 0.0, 0.0, 0.3)], "passive", workers=1)
    assert out[0].landed and not out[1].landed
    assert out[1].tilt_deg > 150 and math.isfinite(out[1].peak_impact)


def test_a_stacked_population_gives_each_row_its_own_behaviour():
    from felis.learning.landing.nets import random_simple
    from felis.learning.landing.policy import StackedSimple

    rng = np.random.default_rng(3)
    pop = [random_simple(rng, 8) for _ in range(5)]
    index = rng.integers(0, 5, size=40)
    it = rng.uniform(-1, 1, (40, 15))
    got = StackedSimple(pop, index).velocities_many(it)
    want = np.stack([pop[i].velocities(it[b]) for b, i in enumerate(index)])
    assert np.allclose(got, want, rtol=0, atol=1e-12)


def test_touchdown_compliance_batched_equals_sequential():
    """Touchdown compliance (`LandingController(touchdown_stiffness=…)`, `LandingBatch`'s, the batch's per-cat
    gains) judged the same in a batch as through `run_loop` and `MujocoRobot` (to the nets' rounding,
    `test_batched_equals_sequential`); the softened legs change the landing (the peak impact)."""
    from felis.controllers.landing import LandingBatch, LandingController
    from felis.learning.landing.policy import load_policy

    behaviour, _ = load_policy(shipped_policy())
    drops = [Drop(0.0, 0.0, 0.0, 3.0), Drop(20.0, -30.0, 10.0, 3.0), Drop(-40.0, 10.0, 0.0, 1.0)]
    seq_sim, bat_sim = LandingSim(), BatchLandingSim(nthread=2)
    try:
        seq = [seq_sim.run(d, LandingController(behaviour, touchdown_stiffness=0.3)) for d in drops]
        bat = bat_sim.run(drops, LandingBatch(bat_sim.spec, [behaviour], touchdown_stiffness=0.3))
        stiff = bat_sim.run(drops, LandingBatch(bat_sim.spec, [behaviour]))
    finally:
        seq_sim.close()
        bat_sim.close()
    for a, b in zip(seq, bat, strict=True):
        assert _same(a, b, 1e-9), (vars(a), vars(b))
    assert any(abs(s.peak_impact - b.peak_impact) > 0.01 * s.peak_impact for s, b in zip(stiff, bat, strict=True))


def test_a_finer_physics_step_runs_more_steps_a_tick_and_the_same_free_fall():
    # 0.25 ms: 40 steps a 10 ms tick; before touchdown free fall is the same to the integrator's order
    d = Drop(0.0, 0.0, 0.0, 1.0)
    heights = {}
    for dt in (0.001, 0.00025):
        sim = BatchLandingSim(nthread=1, timestep=dt)
        shapes, z = [], []

        def record(k, st, sd, active, sim=sim, shapes=shapes, z=z):
            shapes.append(st.shape[1])
            z.append(sd[0, -1, sim.batch._waist])

        ctl = batch_controller(sim.spec, "passive", [d])
        (res,) = sim.batch.run([d], ctl, sim.standing_waist_m, ticks=[30], record=record)
        sim.close()
        assert set(shapes) == {round(0.01 / dt)}
        heights[dt] = z[29]  # waist height after 0.3 s of free fall
    assert heights[0.001] == pytest.approx(heights[0.00025], abs=2e-3)
    with pytest.raises(ParameterError, match="physics step"):
        BatchLandingSim(nthread=1, timestep=0.0)
    sim = BatchLandingSim(nthread=1, timestep=0.0003)  # 10 ms is no whole number of 0.3 ms steps
    with pytest.raises(ParameterError, match="whole physics steps"):
        sim.batch.run([d], batch_controller(sim.spec, "passive", [d]), sim.standing_waist_m)
    sim.close()


def test_a_cat_whose_physics_diverges_is_reported_and_stopped_and_the_others_are_untouched():
    """A cat whose state blows up (qvel set absurd in its row of the batch's live state, as
    `test_sim_backend` does to one `MujocoRobot`) comes back diverged, stepped no further; every other cat
    of its batch gets what it gets without it, bit for bit."""
    from felis.learning.landing.evaluate import outcome_of

    drops = [Drop(0.0, 0.0, 0.0, 0.5), Drop(30.0, 0.0, 0.0, 0.5), Drop(0.0, 40.0, 0.0, 1.0)]
    sim = BatchLandingSim(nthread=2)
    try:
        clean = sim.batch.run(drops, batch_controller(sim.spec, "passive", drops), sim.standing_waist_m)
        rows: list[np.ndarray] = []

        def poke(k, st, sd, active):
            rows.append(active.copy())
            if k == 5:
                sim.batch._sims.bind("qvel")[1] = 1e12  # the cat's row of the batch's state

        got = sim.batch.run(drops, batch_controller(sim.spec, "passive", drops), sim.standing_waist_m, record=poke)
    finally:
        sim.close()
    assert got[1].diverged and not clean[1].diverged
    assert 1 in rows[6] and all(1 not in r for r in rows[7:])  # its tick 6 ran (and stopped), then no more
    assert outcome_of(drops[1], "passive", got[1], sim.standing_waist_m).why == "physics diverged"
    for i in (0, 2):
        assert not got[i].diverged and got[i].peak_impact == clean[i].peak_impact
        assert got[i].final_up_z == clean[i].final_up_z
        assert np.array_equal(got[i].truth.t, clean[i].truth.t)
        assert np.array_equal(got[i].truth.up_z, clean[i].truth.up_z)
