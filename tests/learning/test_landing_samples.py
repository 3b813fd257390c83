"""Motion samples for the landing nets (issue 5, seed 000 §6.5): spine rules as data, rollouts, and the
shipped samples file (loads, replays to the stored result, rejects bad files in one line)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing.features import FEATURE_BODIES
from felis.learning.landing.policy import MAX_SPEED
from felis.learning.landing.samples import (
    STEPS,
    TRAIN_HEIGHT_M,
    TRAINING_ORIENTATIONS,
    SpineRule,
    circle_waypoints,
    load_samples,
    rollout,
    rule_from_waypoints,
    rule_score,
)

SHIPPED = Path(__file__).resolve().parents[2] / "learning" / "weights" / "landing_samples.json"


@pytest.fixture(scope="module")
def sim():
    from felis.learning.landing.evaluate import LandingSim

    s = LandingSim()
    yield s
    s.close()


# ------------------------------------------------------------------------------------------ rule
def test_rule_picks_the_segment_containing_t():
    rule = SpineRule(((0.1, 2.0, -1.0), (0.25, -3.0, 0.5)))
    for t, spine in [(0.0, (2.0, -1.0)), (0.09, (2.0, -1.0)), (0.1, (-3.0, 0.5)), (0.24, (-3.0, 0.5)),
                     (0.25, (0.0, 0.0)), (1.5, (0.0, 0.0))]:
        v = rule(None, t)
        assert v.shape == (12,)
        assert tuple(v[:2]) == spine
        assert not v[2:].any()  # tail and legs fixed


def test_rule_boundaries_tolerate_float_sums_of_ticks():
    rule = SpineRule(((0.07, 1.0, 0.0), (0.2, 2.0, 0.0)))
    t = sum([0.01] * 7)  # 0.07000000000000001 or 0.06999999999999999 depending on the sum
    assert rule(None, t)[0] == 2.0
    assert rule(None, 0.07 - 1e-12)[0] == 2.0
    assert rule(None, 0.069)[0] == 1.0


def test_rule_json_round_trip():
    rule = rule_from_waypoints(circle_waypoints(-1))
    again = SpineRule.from_dict(json.loads(json.dumps(rule.as_dict())))
    assert again == rule
    for t in np.arange(0.0, 1.0, 0.01):
        assert np.array_equal(again(None, t), rule(None, t))


@pytest.mark.parametrize("segments, words", [
    (((0.1, 1.0),), "(t_end, vs1, vs2)"),
    (((0.2, 1.0, 0.0), (0.1, 1.0, 0.0)), "not after"),
    (((0.0, 1.0, 0.0),), "not after"),
    (((0.1, MAX_SPEED + 1, 0.0),), "exceeds"),
    (((0.1, float("nan"), 0.0),), "finite"),
    (((0.1, True, 0.0),), "finite"),
])
def test_bad_rules_are_one_line_errors(segments, words):
    with pytest.raises(ParameterError, match=None) as e:
        SpineRule(segments)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_rule_from_bad_dict():
    for d in (None, {}, {"segments": "x"}, {"segments": [1, 2]}, {"segments": [[0.1, 1, "a"]]}):
        with pytest.raises(ParameterError):
            SpineRule.from_dict(d)


def test_waypoints_are_reached_at_whole_ticks_within_servo_speed():
    w = np.array([(0.5, 0.0), (0.5, 0.0), (-0.3, 0.73)])
    rule = rule_from_waypoints(w)
    assert len(rule.segments) == 2  # the repeated waypoint adds nothing
    q, t_prev = np.zeros(2), 0.0
    for t_end, v1, v2 in rule.segments:
        assert abs(t_end * 100 - round(t_end * 100)) < 1e-9
        assert max(abs(v1), abs(v2)) <= MAX_SPEED
        q += np.array([v1, v2]) * (t_end - t_prev)
        t_prev = t_end
    assert np.allclose(q, w[-1])


# ------------------------------------------------------------------------------------------ rollout
def test_rollout_shapes(sim):
    r = rollout(sim, (180.0, 0.0, 0.0), rule_from_waypoints(circle_waypoints(1)))
    assert r.vectors.shape == (STEPS, len(FEATURE_BODIES), 3)
    assert r.heights_mm.shape == r.up_z.shape == r.lower_up_z.shape == (STEPS,)
    assert 2900 < r.heights_mm[0] < 3200 and r.heights_mm[-1] < 500
    assert r.up_z[0] == pytest.approx(-1.0, abs=1e-6)
    assert -1.0 <= r.final_up_z <= 1.0 and np.isfinite(rule_score(r))
    assert r.outcome.drop.height_m == TRAIN_HEIGHT_M


def test_rollout_takes_an_object_with_velocities(sim):
    class Still:
        def velocities(self, it):
            assert it.shape == (15,)
            return np.zeros(12)

    r = rollout(sim, (90.0, 0.0, 0.0), Still())
    assert r.vectors.shape[0] == STEPS and not r.landed


def test_rollout_rejects_a_bad_orientation(sim):
    with pytest.raises(ParameterError):
        rollout(sim, (180.0, 0.0), SpineRule(()))


# ------------------------------------------------------------------------------------------ shipped
def test_shipped_samples_load():
    samples = load_samples(SHIPPED)
    assert len(samples) == 7
    assert tuple(s.orientation for s in samples) == TRAINING_ORIENTATIONS
    for s in samples:
        assert s.height_m == TRAIN_HEIGHT_M
        assert s.vectors.shape == (STEPS, len(FEATURE_BODIES), 3) and s.heights_mm.shape == (STEPS,)
        assert s.rule.segments


def test_replaying_a_stored_rule_reproduces_it():
    """The shipped samples were recorded on the cat as described until 2026-11-29 (`4ms-paw`): on it they replay."""
    from felis.learning.landing.evaluate import LandingSim

    s = load_samples(SHIPPED)[1]
    sim = LandingSim(design="4ms-paw")
    try:
        assert sim.robot.model.opt.timestep == 0.001
        r = rollout(sim, s.orientation, s.rule, s.height_m)
    finally:
        sim.close()
    assert r.final_up_z == pytest.approx(s.final_up_z, abs=1e-3)
    assert r.landed == s.landed
    assert np.allclose(r.heights_mm[:60], s.heights_mm[:60], atol=1e-3)  # the fall, before any contact
    assert np.allclose(r.vectors[:60], s.vectors[:60], atol=1e-6)


# ------------------------------------------------------------------------------------------ bad files
@pytest.fixture()
def copy(tmp_path):
    shutil.copy(SHIPPED, tmp_path / SHIPPED.name)
    shutil.copy(SHIPPED.with_suffix(".npz"), tmp_path / SHIPPED.with_suffix(".npz").name)
    return tmp_path / SHIPPED.name


def _edit(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def _one_line(path, words):
    with pytest.raises(ParameterError) as e:
        load_samples(path)
    msg = str(e.value)
    assert "\n" not in msg and words in msg, msg


def test_missing_file(tmp_path):
    _one_line(tmp_path / "none.json", "no such landing samples file")


def test_not_json(copy):
    copy.write_text("{nope")
    _one_line(copy, "not JSON")


def test_other_format(copy):
    _edit(copy, lambda d: d.update(format="something"))
    _one_line(copy, "not a landing samples file")


def test_missing_arrays(copy):
    copy.with_suffix(".npz").unlink()
    _one_line(copy, "no such landing samples arrays file")


def test_corrupt_arrays(copy):
    copy.with_suffix(".npz").write_bytes(b"PK\x03\x04garbage")
    _one_line(copy, "corrupt landing samples arrays")


def test_arrays_that_do_not_match(copy):
    _edit(copy, lambda d: d["samples"].pop())
    _one_line(copy, "do not match")


def test_bad_rule_in_file(copy):
    _edit(copy, lambda d: d["samples"][2]["rule"].update(segments=[[0.1, 99.0, 0.0]]))
    _one_line(copy, "sample 2")


def test_missing_field(copy):
    _edit(copy, lambda d: d["samples"][0].pop("final_up_z"))
    _one_line(copy, "missing final_up_z")
