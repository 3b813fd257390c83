"""Batched drops (`felis.sim.batch.DropBatch`) against the sequential path (`felis.loop.run_loop` with a
`LandingRecorder`): the same verdicts, the same figures within the tolerance the module states."""

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


@pytest.mark.parametrize("policy", ["shipped", "passive"])
def test_batched_equals_sequential(drops, policy):
    seq = run_drops_sequential(drops, policy, workers=1)
    bat = run_drops(drops, policy, workers=2)
    assert len(seq) == len(bat) == len(drops)
    for a, b in zip(seq, bat, strict=True):
        assert a.landed == b.landed and a.why == b.why and a.foot_only == b.foot_only
        assert a.touchdown_s == pytest.approx(b.touchdown_s, abs=1e-12)
        assert a.tilt_deg == pytest.approx(b.tilt_deg, abs=1e-3)  # stated tolerance: cold-started ticks
        assert a.waist_m == pytest.approx(b.waist_m, abs=1e-5)
        assert a.peak_impact == pytest.approx(b.peak_impact, rel=1e-3)
        assert a.final_tilt_deg == pytest.approx(b.final_tilt_deg, abs=1e-2)


def test_free_fall_identical_to_1e_6(drops):
    """Before touchdown the batch and the loop agree to 1e-6 (joint targets, attitude): no contacts, so the
    only difference is the solver's warm start, which free flight does not feel."""
    d = drops[0]
    seq = LandingSim()
    rec: list[np.ndarray] = []
    seq.run(d, "shipped", monitors=[lambda s, c: rec.append(np.concatenate([[s.t], s.q, s.imu.quat]))],
            duration=0.4)
    seq.close()
    sim = BatchLandingSim(nthread=1)
    got: list[np.ndarray] = []

    def record(k, st, sd, active):
        got.append(np.concatenate([st[0, -1, :], sd[0, -1, sim.batch._imu]]))

    ctl = batch_controller(sim.spec, "shipped", [d])
    sim.batch.run([d], ctl, sim.standing_waist_m, ticks=[40], record=record)
    sim.close()
    qadr = sim.batch._qadr
    for k in range(39):  # the loop's state at tick k+1 is the batch's after its tick k
        a, b = rec[k + 1], got[k]
        assert a[0] == pytest.approx(b[0], abs=1e-12)
        assert np.allclose(a[1:13], sim.batch._quantize(b[qadr][None])[0], atol=2e-3)  # one encoder tick
        assert np.allclose(a[13:17], b[-4:], atol=1e-6)


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
    """Touchdown compliance (`LandingController(touchdown_stiffness=…)`, `LandingBatch`'s, the batch's compliant
    model copies) judged the same in a batch as through `run_loop` and `MujocoRobot`, within the stated tolerance;
    the softened legs change the landing (the peak impact)."""
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
        assert a.landed == b.landed and a.why == b.why
        assert a.touchdown_s == pytest.approx(b.touchdown_s, abs=1e-12)
        assert a.tilt_deg == pytest.approx(b.tilt_deg, abs=1e-3)
        assert a.peak_impact == pytest.approx(b.peak_impact, rel=1e-3)
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
