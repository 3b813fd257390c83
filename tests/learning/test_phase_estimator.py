"""The online phase estimator (`felis.learning.phase.estimator`) and its figures (`felis.learning.phase.evaluate`):
a tiny PAE trained here on a real MuJoCo gait recording for the mechanics, the shipped weights for what
they must show."""

from __future__ import annotations

import math

import numpy as np
import pytest

from felis.controllers.balance import BalanceMonitor
from felis.controllers.stepping import SteppingController
from felis.errors import PhaseError
from felis.hal import State
from felis.learning.phase.data import record_sim
from felis.learning.phase.estimator import DEFAULT_WEIGHTS, PhaseEstimator, calibrate, phase_track
from felis.learning.phase.evaluate import gate_comparison, phase_metrics
from felis.learning.phase.infer import load_pae_numpy
from felis.learning.phase.pae import save_pae
from felis.learning.phase.train import PhaseTrainConfig, train_phase
from felis.scenarios.push import Push
from felis.sim.bodymodel import load_body_model
from felis.spec import load_spec


@pytest.fixture(scope="module")
def spec():
    return load_spec("cat")


@pytest.fixture(scope="module")
def gait():
    return record_sim(((1.0, 0.0, 0.0), (4.0, 2.0, 0.5), (1.5, 0.0, 0.0)), name="tiny")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, gait):
    """A small PAE (window 50) trained for a few epochs, calibrated, saved as `felis train phase` does."""
    cfg = PhaseTrainConfig(window=50, n_phases=3, hidden=8, kernel=9, epochs=6, batch=16, stride=4, fld_steps=4)
    model, _ = train_phase([gait.q], None, cfg, joints=gait.joints)
    path = tmp_path_factory.mktemp("phase") / "tiny.npz"
    save_pae(path, model)
    pae, _ = load_pae_numpy(path)
    cal = calibrate(pae, [gait.q], [gait.stepping])
    save_pae(path, model, {"phase_estimator": cal})
    return path


def _feed(est, q, rate, t0=0.0):
    for k, row in enumerate(q):
        est(State(t=t0 + k / rate, q=row, dq=np.zeros_like(row)))


def test_estimator_matches_the_offline_track(tiny, gait):
    """Fed the recording frame by frame, the estimator's phase, frequency and amplitude are those of
    `phase_track` at the last frame (the phase carried to the window's end)."""
    est = PhaseEstimator(tiny, joints=gait.joints)
    n = 380
    _feed(est, gait.q[:n], gait.rate_hz)
    tr = phase_track(est.pae, gait.q[:n])
    c = est.channel
    g = est.gait(gait.t[n - 1])
    assert g.frequency_hz == pytest.approx(tr["freq"][n - 1, c], rel=1e-9)
    assert g.amplitude == pytest.approx(tr["amp"][n - 1, c], rel=1e-9)
    assert abs((g.phase - tr["phase"][n - 1, c] + 0.5) % 1 - 0.5) < 1e-9
    assert g.swing is None and g.touchdown_s == 0.0


def test_estimator_resamples_a_slower_loop(tiny, gait):
    """A 50 Hz loop: the window is interpolated onto the model's 100 Hz grid; the estimate is close to the
    one from every frame."""
    n = 380
    full, half = PhaseEstimator(tiny), PhaseEstimator(tiny)
    _feed(full, gait.q[:n], 100.0)
    _feed(half, gait.q[:n:2], 50.0)
    assert half.current is not None
    assert half.current.frequency_hz == pytest.approx(full.current.frequency_hz, rel=0.05)
    assert half.current.amplitude == pytest.approx(full.current.amplitude, rel=0.1)


def test_estimator_unknown_until_a_window_and_after_bad_reads(tiny, gait):
    est = PhaseEstimator(tiny)
    W = est.pae.config.window
    _feed(est, gait.q[:W - 1], 100.0)
    assert est.gait((W - 2) / 100) is None  # not a full window yet
    _feed(est, gait.q[W - 1:W], 100.0, t0=(W - 1) / 100)
    assert est.gait((W - 1) / 100) is not None
    bad = gait.q[W].copy()
    bad[3] = math.nan
    est(State(t=W / 100, q=bad, dq=np.zeros(12)))  # a failed read: unknown again, counted
    assert est.gait(W / 100) is None and est.errors == 1
    assert est.gait(10.0) is None  # no fresh frames: unknown


def test_estimator_refuses_mismatched_weights(tmp_path, tiny, spec):
    est = PhaseEstimator(tiny)
    other = load_spec("arm")
    with pytest.raises(PhaseError, match="joints") as e:
        est.reset(other)
    assert "\n" not in str(e.value)
    with pytest.raises(PhaseError, match="joints"):
        PhaseEstimator(tiny, joints=["a", "b"])
    # a PAE without the calibration
    from felis.learning.phase.pae import load_pae

    model, _ = load_pae(tiny)
    bare = tmp_path / "bare.npz"
    save_pae(bare, model)
    with pytest.raises(PhaseError, match="calibration"):
        PhaseEstimator(bare)
    with pytest.raises(PhaseError):
        PhaseEstimator(tmp_path / "missing.npz")


def test_phase_metrics_structure(tiny, gait):
    pae, meta = load_pae_numpy(tiny)
    m = phase_metrics(pae, meta["phase_estimator"]["channel"], [gait])
    assert len(m["segments"]) == 1
    seg = m["segments"][0]
    assert seg["commanded_hz"] == 2.0 and abs(seg["contact_hz"] - 2.0) < 0.05
    assert m["amp_standing_median"] < m["amp_stepping_median"]


# ------------------------------------------------------------------------------- the shipped weights
def test_shipped_weights_exist():
    """`felis train phase` made them; they are part of the repository."""
    assert DEFAULT_WEIGHTS.is_file()
    assert DEFAULT_WEIGHTS.stat().st_size < 200_000


def test_shipped_estimator_tells_stepping_from_standing_in_the_loop(spec):
    """On MuJoCo at 100 Hz: standing, then trotting at 1.8 Hz (a frequency the training never held): the
    estimator says not stepping while standing, stepping at the trot's frequency (or a multiple) within
    15 %, and the monitor it gates stays quiet."""
    from felis.loop import run_loop
    from felis.sim import MujocoRobot
    from felis.sim.scenarios import set_pose

    body = load_body_model(spec)
    est = PhaseEstimator(joints=[j.name for j in spec.joints])
    mon = BalanceMonitor(body, gait=est.gait)
    rows = []

    def watch(state, command):
        g = est.gait(state.t)
        rows.append((state.t, g.stepping if g else None, g.frequency_hz if g else math.nan, mon.alarm))

    ctl = SteppingController.scheduled(((2.5, 0.0, 0.0), (5.0, 1.8, 0.5)))
    with MujocoRobot(spec) as robot:
        set_pose(robot, spec.pose("stand"))
        run_loop(robot, ctl, duration=7.0, monitors=[est, mon, watch])
    t = np.array([r[0] for r in rows])
    standing = [r for r in rows if 1.5 < r[0] < 2.5]
    trotting = [r for r in rows if t[-1] - 2.0 < r[0]]
    assert standing and all(r[1] is False for r in standing)
    assert trotting and all(r[1] is True for r in trotting)
    f = np.median([r[2] for r in trotting])
    n = max(1, round(f / 1.8))
    assert abs(f / (n * 1.8) - 1) < 0.15
    assert not any(r[3] for r in rows)


def test_gate_comparison_runs_the_three_monitors_on_the_same_pushes():
    pushes = [Push("upper_body", 90.0, 0.9, 1.7, "step"), Push("lower_body", 0.0, 0.3, 1.8, "step"),
              Push("upper_body", 270.0, 1.0, 0.6, "stand")]
    out = gate_comparison(pushes, DEFAULT_WEIGHTS, workers=1)
    assert out["pushes"] == 3 and out["step"]["pushes"] == 2 and out["stand"]["pushes"] == 1
    for row in out["rows"]:
        assert set(row["alarm_t_s"]) == {"clock", "phase", "none"}
    # standing, the estimator says no gait: its monitor is the ungated one
    stand = out["rows"][2]
    assert stand["alarm_t_s"]["phase"] == stand["alarm_t_s"]["none"]


# ------------------------------------------------------------------------------- the commands
def test_felis_train_and_eval_phase_tiny(tmp_path, capsys):
    """`felis train phase` end to end on shortened schedules (weights, calibration, results file), then
    `felis eval phase` with those weights on two pushes."""
    import json

    from felis.cli.main import main

    out = tmp_path / "tiny.npz"
    rc = main(["train", "phase", "--scale", "0.3", "--epochs", "2", "--window", "50", "--phases", "3", "--hidden",
               "8", "--fld-steps", "4", "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert out.is_file() and (tmp_path / "tiny.results.json").is_file()
    assert res["best_epoch"] in (1, 2) and set(res["heldout_prediction"]["pred_mse_mean"]) >= {"fld", "const_vel",
                                                                                                 "last_cycle"}
    est = PhaseEstimator(out)  # calibrated: usable by the estimator as is
    assert 0 <= est.channel < 3
    pushes = tmp_path / "pushes.json"
    pushes.write_text(json.dumps([{"body": "upper_body", "direction_deg": 90, "impulse_ns": 0.5, "t_s": 1.6,
                                   "phase": "step"},
                                  {"body": "lower_body", "direction_deg": 0, "impulse_ns": 0.4, "t_s": 0.6,
                                   "phase": "stand"}]))
    data = tmp_path / "gait.npz"
    assert main(["phase", "record", "--set", "heldout", "--scale", "0.3", "--out", str(data)]) == 0
    capsys.readouterr()
    rc = main(["eval", "phase", "--weights", str(out), "--data", str(data), "--pushes", str(pushes), "--workers", "1",
               "--json", "--out", str(tmp_path / "r.json")])
    assert rc == 0
    r = json.loads(capsys.readouterr().out)
    assert r["gate"]["pushes"] == 2 and set(r["gate"]["step"]) >= {"clock", "phase", "none"}
    assert json.loads((tmp_path / "r.json").read_text()) == r


@pytest.mark.parametrize("args, message", [
    (["--weights", "{tmp}/missing.npz"], "no phase weights"),
    (["--weights", "{bare}"], "calibration"),
    (["--weights", "{tiny}", "--pushes", "random:-3"], "random"),
    (["--weights", "{tiny}", "--out", "{tmp}/r.txt"], ".json"),
    (["--weights", "{tiny}", "--data", "{train}", "--pushes", "none"], "no recordings of split 'heldout'"),
])
def test_felis_eval_phase_bad_input_is_one_line(tmp_path, capsys, tiny, args, message):
    from felis.cli.main import main
    from felis.learning.phase.pae import load_pae

    model, _ = load_pae(tiny)
    bare = tmp_path / "bare.npz"
    save_pae(bare, model)
    train = tmp_path / "train.npz"
    if any("{train}" in a for a in args):  # a gait-data file without held-out recordings
        from felis.learning.phase.data import save_recordings

        save_recordings(train, [record_sim(((1.0, 0.0, 0.0), (2.5, 2.0, 0.5)), name="t", split="train")],
                        set_name="train")
    args = [a.format(tmp=tmp_path, bare=bare, tiny=tiny, train=train) for a in args]
    rc = main(["eval", "phase", *args])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and message in err and "\n" not in err


def test_felis_run_balance_with_the_phase_gate(tmp_path, capsys):
    """`felis run balance --gate phase`: the shipped estimator feeds the monitor of a guarded trot."""
    import json

    from felis.cli.main import main

    rc = main(["run", "balance", "--robot", "cat", "--base", "step-in-place", "--gate", "phase", "--duration", "3",
               "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["run"]["controller"] == "step-in-place+balance" and out["run"]["ok"]
    assert out["controller"]["alarm_t"] is None  # a quiet trot
    rc = main(["run", "stand", "--robot", "cat", "--gate", "phase"])
    err = capsys.readouterr().err
    assert rc != 0 and "belong to the balance controller" in err
