"""Tasks, backend-free (`felis.scenarios`): the drop and push validators, the seeded draws, and the landing
and fall verdicts on hand-made recorded truth."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.scenarios import (
    FALL_TILT_DEG,
    MAX_DROP_HEIGHT,
    TILT_DEG,
    WINDOW_S,
    Drop,
    FallTruth,
    LandingTruth,
    Push,
    check_drop,
    check_push,
    drop_from_values,
    drops_from,
    fall_reason,
    fall_verdict,
    landed,
    landing_verdict,
    make_drop,
    pushes_from,
    random_drops,
    random_pushes,
)

STANDING = 0.115  # m
BODIES = ("world", "upper_body", "lower_body", "head", "fl_foot", "fr_foot", "hl_foot", "hr_foot", "fl_thigh")
UPPER, LOWER, HEAD, FOOT, THIGH = 1, 2, 3, 4, 8


# ------------------------------------------------------------------------------------------ drops
def test_drop_type_carries_the_fall_time_and_the_summary_names():
    d = make_drop(1.0, 180, -20, 45)
    assert d == Drop(180.0, -20.0, 45.0, 1.0)
    assert d.fall_time == math.sqrt(2 * 1.0 / 9.81)
    assert (d.height, d.roll, d.pitch, d.yaw) == (1.0, 180.0, -20.0, 45.0)
    assert d.as_dict() == {"roll_deg": 180.0, "pitch_deg": -20.0, "yaw_deg": 45.0, "height_m": 1.0}
    assert drop_from_values((1.0, 180, -20, 45)) == d


@pytest.mark.parametrize("args, message", [
    ((-1,), "drop height must be above 0 and at most 20 m, got -1"),
    ((0,), "drop height must be above 0 and at most 20 m, got 0"),
    ((20.5,), "drop height must be above 0 and at most 20 m, got 20.5"),
    ((1, 400), "drop roll must be within ±360 degrees, got 400"),
    ((1, 0, -361), "drop pitch must be within ±360 degrees, got -361"),
    ((1, 0, 0, 1e3), "drop yaw must be within ±360 degrees, got 1000"),
    (("x",), "height must be a number, got 'x'"),
    ((float("nan"),), "height must be finite, got nan"),
    ((1, float("inf")), "roll must be finite, got inf"),
])
def test_make_drop_errors_are_one_clear_line(args, message):
    with pytest.raises(ParameterError) as e:
        make_drop(*args)
    assert str(e.value) == message


@pytest.mark.parametrize("values, needle", [
    ((1, 0, 0), "a drop is four finite numbers"), ((1, 0, 0, float("nan")), "four finite numbers"),
    ("abcd", "four finite numbers"), (None, "four finite numbers"),
    ((0, 0, 0, 0), "drop height must be above 0"), ((1, 400, 0, 0), "drop roll must be within ±360"),
])
def test_drop_from_values_errors(values, needle):
    with pytest.raises(ParameterError, match=needle):
        drop_from_values(values)


@pytest.mark.parametrize("change, message", [
    ({"height_m": None}, "here: missing height_m"),
    ({"height_m": 21}, "here: height_m must be above 0 and at most 20 m, got 21"),
    ({"roll_deg": 361}, "here: roll_deg must be within ±360 degrees, got 361"),
    ({"pitch_deg": "0"}, "here: pitch_deg must be a finite number, got '0'"),
])
def test_check_drop_errors_name_where_and_field(change, message):
    item = {k: v for k, v in {"roll_deg": 0, "pitch_deg": 0, "yaw_deg": 0, "height_m": 1, **change}.items()
            if v is not None}
    with pytest.raises(ParameterError) as e:
        check_drop(item, "here")
    assert str(e.value) == message


def test_limits_are_inclusive_where_documented():
    assert make_drop(MAX_DROP_HEIGHT, -360, 360, 0).height_m == MAX_DROP_HEIGHT
    with pytest.raises(ParameterError):
        make_drop(math.nextafter(MAX_DROP_HEIGHT, 21))


def test_drop_draws_are_deterministic_by_seed(tmp_path):
    assert random_drops(50, seed=7) == random_drops(50, seed=7) != random_drops(50, seed=8)
    assert drops_from("random:5", 3, 2.0) == random_drops(5, 3, 2.0)
    p = tmp_path / "drops.json"
    p.write_text(json.dumps([d.as_dict() for d in random_drops(3, 1)]))
    assert [d.as_dict() for d in drops_from(str(p))] == [d.as_dict() for d in random_drops(3, 1)]


# ------------------------------------------------------------------------------------------ pushes
def test_push_validator_and_draws(tmp_path):
    good = {"body": "upper_body", "direction_deg": 450, "impulse_ns": 0.5, "t_s": 1.0, "phase": "stand"}
    assert check_push(good) == Push("upper_body", 90.0, 0.5, 1.0, "stand")
    assert check_push(good).impulse() == pytest.approx([0, 0.5, 0])
    for bad, needle in [({**good, "body": "tail"}, "body 'tail'"), ({**good, "impulse_ns": 60}, "impulse_ns"),
                        ({**good, "t_s": 0.1}, "t_s must be within 0.5"), ({**good, "phase": "fly"}, "phase 'fly'")]:
        with pytest.raises(ParameterError, match=needle):
            check_push(bad, "p")
    assert random_pushes(20, seed=2) == random_pushes(20, seed=2) != random_pushes(20, seed=3)
    assert pushes_from("random:4", 5) == random_pushes(4, 5)
    with pytest.raises(ParameterError, match="random:N"):
        pushes_from("random:x")


# --------------------------------------------------------------------------------- landing verdict
def _truth(*, touchdown=0.45, end=1.5, up_z=1.0, waist=0.11, off_foot=-1, off_from=None, off_until=None,
           never=False) -> LandingTruth:
    """Hand-made recorded truth at 1 kHz: in the air until ``touchdown``, then a foot on the floor; from
    ``off_from`` (default: touchdown) to ``off_until`` (default: the end) body ``off_foot`` touches too;
    the pose (``up_z``, ``waist``) as given from touchdown on (upright and high before)."""
    t = np.round(np.arange(1, int(round(end * 1000)) + 1) * 1e-3, 9)
    down = np.zeros(len(t), bool) if never else t >= touchdown - 1e-12
    floor = np.where(down, FOOT, -1)
    off = np.full(len(t), -1)
    if off_foot >= 0:
        lo = touchdown if off_from is None else off_from
        hi = end if off_until is None else off_until
        sel = down & (t >= lo - 1e-12) & (t <= hi + 1e-12)
        off[sel] = off_foot
        floor[sel & (t < touchdown + 1e-12)] = off_foot
    return LandingTruth(t=t, up_z=np.where(down, up_z, 1.0), waist_m=np.where(down, waist, 0.5), floor_body=floor,
                        off_foot_body=off, bodies=BODIES, standing_waist_m=STANDING)


def test_lands_on_its_feet():
    v = landing_verdict(_truth())
    assert v.landed and v.foot_only and v.reasons == () and v.why == ""
    assert v.touchdown_t == pytest.approx(0.45) and v.first_body == "fl_foot" and v.touch_body is None
    assert v.tilt_deg == 0.0 and v.waist_m == 0.11 and v.standing_waist_m == STANDING
    assert landed(v.foot_only, v.tilt_deg, v.waist_m, STANDING)


def test_on_its_back():
    v = landing_verdict(_truth(up_z=-1.0, waist=0.04, off_foot=UPPER))
    assert not v.landed and not v.foot_only and v.touch_body == "upper_body" and v.touch_t == pytest.approx(0.45)
    assert v.tilt_deg == pytest.approx(180.0)
    assert [k for k, _ in v.reasons] == ["upper_body touched the ground", f"tilt > {TILT_DEG:g}°",
                                         "waist < half standing"]
    assert v.why.startswith("upper_body touched the ground 0.000 s after touchdown; tilt 180° after 0.5 s")


def test_on_its_side_feet_only():
    v = landing_verdict(_truth(up_z=0.0))
    assert not v.landed and v.foot_only and v.tilt_deg == pytest.approx(90.0)
    assert v.reasons == ((f"tilt > {TILT_DEG:g}°", "tilt 90° after 0.5 s"),)


def test_legs_splayed_with_the_belly_down():
    low = landing_verdict(_truth(waist=0.05))  # upright, feet only, but the waist is down
    assert not low.landed and low.foot_only and low.tilt_deg == 0.0
    assert low.reasons == (("waist < half standing", "waist 0.050 m < half standing (0.058 m) after 0.5 s"),)
    belly = landing_verdict(_truth(waist=0.05, off_foot=LOWER, off_from=0.6))  # … and the belly on the floor
    assert [k for k, _ in belly.reasons] == ["lower_body touched the ground", "waist < half standing"]
    assert belly.touch_t - belly.touchdown_t == pytest.approx(0.15)


def test_nan_never_lands():
    v = landing_verdict(_truth(up_z=float("nan")))
    assert not v.landed and math.isnan(v.tilt_deg) and v.reasons[0][0] == f"tilt > {TILT_DEG:g}°"
    w = landing_verdict(_truth(waist=float("nan")))
    assert not w.landed and w.reasons[0][0] == "waist < half standing"
    assert not landed(True, float("nan"), STANDING, STANDING) and not landed(True, 0.0, float("nan"), STANDING)


def test_the_window():
    after = landing_verdict(_truth(off_foot=HEAD, off_from=0.45 + WINDOW_S + 0.01))  # after the window: ignored
    assert after.landed and after.touch_body is None
    inside = landing_verdict(_truth(off_foot=THIGH, off_from=0.45 + WINDOW_S, off_until=0.45 + WINDOW_S))
    assert not inside.landed and inside.touch_body == "fl_thigh"  # its last step still counts
    early = landing_verdict(_truth(end=0.45 + WINDOW_S - 0.01))
    assert not early.landed and early.tilt_deg is None and [k for k, _ in early.reasons] == ["run ended too early"]
    never = landing_verdict(_truth(never=True))
    assert not never.landed and never.touchdown_t is None and never.reasons == (("never touched down",) * 2,)
    first = landing_verdict(_truth(off_foot=HEAD, off_from=0.0, off_until=0.45))  # head first
    assert first.first_body == "head" and first.touch_body == "head"


# ------------------------------------------------------------------------------------------ falls
def test_fall_rule_and_verdict():
    assert fall_reason(10.0, None) == ""
    assert fall_reason(FALL_TILT_DEG, None) == ""
    assert fall_reason(61.0, None) == "upper body tilted 61°"
    assert fall_reason(5.0, "lower_body") == "lower_body touched the ground"
    t = np.arange(5) * 0.01
    standing = fall_verdict(FallTruth(t, np.array([1, 3, 2, 4, 1.0]), np.full(5, -1), BODIES))
    assert not standing.fell and standing.t is None and standing.max_tilt_deg == 4.0
    tipped = fall_verdict(FallTruth(t, np.array([1, 30, 70, 80, 90.0]), np.full(5, -1), BODIES))
    assert tipped.fell and tipped.t == 0.02 and tipped.why == "upper body tilted 70°" and tipped.max_tilt_deg == 70.0
    knee = fall_verdict(FallTruth(t, np.array([1, 5, 9, 9, 9.0]), np.array([-1, THIGH, -1, -1, -1]), BODIES))
    assert knee.fell and knee.t == 0.01 and knee.why == "fl_thigh touched the ground" and knee.max_tilt_deg == 5.0


def test_scenarios_import_only_felis_core():
    code = ("import sys, felis.scenarios; bad = [m for m in sys.modules if m.split('.')[0] in "
            "('mujoco', 'torch') or m.startswith(('felis.sim', 'felis.controllers', 'felis.learning', "
            "'felis.drivers', 'felis.cli'))]; print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
