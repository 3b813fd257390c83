"""The landing design study's cats (`felis.learning.landing.designs`): what each design changes in the model, that
the described cat stays bit for bit the same, per-joint motion speeds, bad designs one line each."""

from __future__ import annotations

import json
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing.designs import DESIGNS, Design, design_robot, design_sim, get_design, joint_speeds
from felis.learning.landing.optimum import DIMS, DT, decode, evaluate, motion_table, seeds
from felis.learning.landing.policy import MAX_SPEED
from felis.scenarios.drop import Drop
from felis.servos import SERVOS
from felis.spec import load_spec

CAT = load_spec("cat")
LEGS_TAIL = set(CAT.groups["legs"]) | set(CAT.groups["tail"])


def test_the_described_cat_is_unchanged_bit_for_bit():
    """Design ``cat``: the spec, no servo overrides, no model edit; its rollouts equal `BatchLandingSim`'s."""
    from felis.learning.landing.evaluate import BatchLandingSim

    spec, servo, edit = design_robot(DESIGNS["cat"])
    assert spec.joints == CAT.joints and servo is None and edit is None
    assert joint_speeds(spec) == MAX_SPEED  # one number: the motions are computed as before designs existed
    drops = [Drop(60.0, 0.0, 0.0, 1.0)] * 3
    xs = seeds()[[0, 3, 9]]
    a, b = BatchLandingSim(nthread=1), design_sim("cat", nthread=1)
    try:
        ra, rb = evaluate(a, drops, xs), evaluate(b, drops, xs)
    finally:
        a.close()
        b.close()
    assert [s for s, _ in ra] == [s for s, _ in rb]


def test_fast_limbs_puts_the_m077_on_legs_and_tail():
    spec, servo, _ = design_robot(DESIGNS["fast-limbs"])
    m077, m288 = SERVOS["XL330-M077-T"], SERVOS["XL330-M288-T"]
    for j in spec.joints:
        want = m077 if j.name in LEGS_TAIL else m288
        assert j.servo == want.name and j.max_velocity == pytest.approx(want.no_load_speed)
    v = joint_speeds(spec)
    assert isinstance(v, np.ndarray) and v[CAT.index("fl_pitch")] == pytest.approx(383 * 2 * np.pi / 60)
    assert servo is None  # built from the spec's models, as the described cat is
    sim = design_sim("fast-limbs", nthread=1)
    try:
        r = sim.batch.robot
        assert r.servo["fl_pitch"].torque_limit == pytest.approx(0.215)
        assert r.servo["spine_pitch"].torque_limit == pytest.approx(0.52)
        assert r.servo["tail_yaw"].damping == pytest.approx(0.215 / m077.no_load_speed)
    finally:
        sim.close()


def test_six_volts_scales_speed_and_stall_torque_and_other_paws_change_only_the_feet_contact_and_the_step():
    spec, servo, _ = design_robot(DESIGNS["6V"])
    m = SERVOS["XL330-M288-T"]
    assert np.allclose(spec.max_velocity, m.no_load_speed * 1.2)
    assert all(p.torque_limit == pytest.approx(m.stall_torque * 1.2) for p in servo.values())
    paw, base, soft = design_sim("4ms-paw", nthread=1), design_sim("cat", nthread=1), design_sim(
        "soft-rubber-paw", nthread=1)
    try:
        mp, mb = paw.batch.model, base.batch.model
        for g in range(mb.ngeom):
            name = mujoco.mj_id2name(mb, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
            want = [0.004, 1.0] if name.endswith("_foot") else list(mb.geom_solref[g])
            assert list(mp.geom_solref[g]) == pytest.approx(want), name
        assert sum((mujoco.mj_id2name(mb, mujoco.mjtObj.mjOBJ_GEOM, g) or "").endswith("_foot")
                   for g in range(mb.ngeom)) == 4
        # the described cat's step resolves its 2 ms paw (τ/4); the study's base runs at the 1 ms it was measured at
        assert (mb.opt.timestep, mp.opt.timestep, soft.batch.model.opt.timestep) == (0.0005, 0.001, 0.001)
        # the contact the solver uses: the feet's τ as it is (equal priorities would average it with the floor's
        # 4 ms), the floor's friction and solimp unchanged
        for m, tau in ((mp, 0.004), (mb, 0.002), (soft.batch.model, 0.003)):
            d = mujoco.MjData(m)
            for _ in range(int(round(0.3 / m.opt.timestep))):  # the cat settles onto its four feet
                mujoco.mj_step(m, d)
            feet = [c for c in d.contact[:d.ncon] if m.geom(c.geom2).name.endswith("_foot")]
            assert len(feet) == 4
            for c in feet:
                assert list(c.solref) == pytest.approx([tau, 1.0])
                assert list(c.solimp) == pytest.approx([0.95, 0.99, 0.001, 0.5, 2.0])
                assert c.friction[:3] == pytest.approx([0.9, 0.9, 0.005])
    finally:
        paw.close()
        base.close()
        soft.close()


def test_per_joint_speeds_make_each_joint_reach_its_waypoint_at_its_own_speed():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, DIMS)
    same = motion_table(x, 1.0, np.full(12, MAX_SPEED), 120)
    assert np.allclose(same, motion_table(x, 1.0, MAX_SPEED, 120))  # a vector of one speed: the same motion
    fast = np.full(12, MAX_SPEED)
    fast[4:] *= 3.0  # legs three times faster: the loop takes fewer ticks, no joint beyond its speed
    v = motion_table(x, 1.0, fast, 120)
    assert np.all(np.abs(v) <= fast * (1 + 1e-9))
    assert np.allclose(np.cumsum(v, axis=0)[-1] * DT, decode(x)[2], atol=1e-9)  # still ends in the posture
    moved = lambda t: int(np.argmax(np.abs(np.cumsum(t[:, 0]) * DT - decode(x)[0][0, 0]) < 1e-9))  # noqa: E731
    assert moved(v) <= moved(same)


@pytest.mark.parametrize("design, message", [
    (Design("x", "", servos={"paws": "XL330-M077-T"}), "no group 'paws'"),
    (Design("x", "", servos={"legs": "XL330-M999-T"}), "unknown servo model 'XL330-M999-T'"),
    (Design("x", "", servos={"legs": "XD430-T210-R"}), "no datasheet figures"),
    (Design("x", "", volts=7.5), "runs on 3.7–6 V, not 7.5 V"),
    (Design("x", "", paw_tau_s=0.0), "paw τ must be within"),
    (Design("x", "", timestep_s=0.0), "a physics step must be within"),
])
def test_bad_designs_are_one_line(design, message):
    with pytest.raises(ParameterError, match=message) as e:
        design_robot(design)
    assert "\n" not in str(e.value)
    with pytest.raises(ParameterError, match="unknown design 'cat-x'; designs: cat, 4ms-paw, fast-limbs"):
        get_design("cat-x")


def test_cli_design_is_checked_and_reported(tmp_path):
    drops = tmp_path / "d.json"
    drops.write_text(json.dumps([{"roll_deg": 0, "pitch_deg": 0, "yaw_deg": 0, "height_m": 0.3}]))
    bad = subprocess.run([sys.executable, "-m", "felis", "eval", "landing", "--drops", str(drops), "--design", "nope"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "invalid choice: 'nope'" in bad.stderr and "4ms-paw" in bad.stderr
    ok = subprocess.run([sys.executable, "-m", "felis", "eval", "landing", "--drops", str(drops), "--design", "6V",
                         "--policy", "stand", "--json"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    res = json.loads(ok.stdout)
    assert res["design"] == "6V" and res["total"] == 1
