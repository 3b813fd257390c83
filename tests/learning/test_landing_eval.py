"""Landing evaluation (issue 5): the `landed` rule on constructed cases, the drops file parser, real
drops judged on MuJoCo, and `felis eval landing` (through its own `register_eval`)."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from felis.cli.landing import cmd_eval_landing, register_eval, register_train
from felis.errors import ParameterError
from felis.learning.landing.evaluate import LandingSim, check_policy, run_drops, summarise
from felis.scenarios import (
    TILT_DEG,
    WAIST_FRACTION,
    WINDOW_S,
    Drop,
    check_drop,
    drops_from,
    landed,
    load_drops,
    random_drops,
)

STANDING = 0.115  # m, about the cat's; any positive value works for the pure rule
GOOD = {"roll_deg": 10, "pitch_deg": -20.5, "yaw_deg": 350, "height_m": 1.0}


# ----------------------------------------------------------------------------------- the pure rule
def test_landed_when_every_condition_holds():
    assert landed(True, 0.0, STANDING, STANDING)
    assert landed(True, 29.9, 0.6 * STANDING, STANDING)


@pytest.mark.parametrize("foot_only, tilt, waist", [
    (False, 0.0, STANDING),  # a non-foot body touched
    (True, 31.0, STANDING),  # too tilted
    (True, 180.0, STANDING),  # on its back
    (True, 0.0, 0.4 * STANDING),  # waist too low (crouched flat)
    (True, 0.0, 0.0),
    (True, math.nan, STANDING),  # bad measurements never land
    (True, 0.0, math.nan),
])
def test_each_condition_alone_fails(foot_only, tilt, waist):
    assert not landed(foot_only, tilt, waist, STANDING)


def test_boundaries():
    """Within 30° (inclusive); above half the standing waist (strict)."""
    assert TILT_DEG == 30.0 and WAIST_FRACTION == 0.5 and WINDOW_S == 0.5
    assert landed(True, 30.0, STANDING, STANDING)
    assert not landed(True, math.nextafter(30.0, 31.0), STANDING, STANDING)
    assert not landed(True, 0.0, 0.5 * STANDING, STANDING)
    assert landed(True, 0.0, math.nextafter(0.5 * STANDING, 1.0), STANDING)


# ----------------------------------------------------------------------------------- drops files
def _write(tmp_path, doc, name="drops.json"):
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


def test_good_file(tmp_path):
    p = _write(tmp_path, [GOOD, {"roll_deg": -360, "pitch_deg": 360, "yaw_deg": 0, "height_m": 20}])
    assert load_drops(p) == [Drop(10.0, -20.5, 350.0, 1.0), Drop(-360.0, 360.0, 0.0, 20.0)]
    assert drops_from(str(p)) == load_drops(p)


@pytest.mark.parametrize("item, field", [
    ({k: v for k, v in GOOD.items() if k != "height_m"}, "missing height_m"),
    ({**GOOD, "roll_deg": "10"}, "roll_deg"),
    ({**GOOD, "pitch_deg": None}, "pitch_deg"),
    ({**GOOD, "yaw_deg": True}, "yaw_deg"),
    ({**GOOD, "height_m": -1.0}, "height_m"),
    ({**GOOD, "height_m": 0}, "height_m"),
    ({**GOOD, "height_m": 20.5}, "height_m"),
    ({**GOOD, "roll_deg": 361}, "roll_deg"),
    ({**GOOD, "extra": 1}, "'extra'"),
    ([1, 2, 3, 4], "expected an object"),
])
def test_bad_item_is_one_line_naming_file_index_and_field(tmp_path, item, field):
    p = _write(tmp_path, [GOOD, item])
    with pytest.raises(ParameterError) as e:
        load_drops(p)
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg and "drop 1" in msg and field in msg


def test_nan_and_infinity_rejected(tmp_path):
    for bad in ("NaN", "Infinity", "-Infinity"):
        p = _write(tmp_path, '[{"roll_deg": 0, "pitch_deg": 0, "yaw_deg": 0, "height_m": ' + bad + "}]")
        with pytest.raises(ParameterError, match=r"drop 0: height_m must be a finite number") as e:
            load_drops(p)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("text, what", [
    ("{not json", "not JSON"),
    ("[]", "non-empty JSON list"),
    ('{"roll_deg": 0}', "non-empty JSON list"),
])
def test_bad_file_is_one_line(tmp_path, text, what):
    p = _write(tmp_path, text)
    with pytest.raises(ParameterError, match=what) as e:
        load_drops(p)
    assert "\n" not in str(e.value) and str(p) in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(ParameterError, match="no such drops file"):
        load_drops(tmp_path / "nope.json")


def test_check_drop_names_where():
    with pytest.raises(ParameterError, match=r"^here: missing roll_deg$"):
        check_drop({"pitch_deg": 0, "yaw_deg": 0, "height_m": 1}, "here")


def test_random_drops_deterministic_and_in_range():
    a, b = random_drops(200, seed=3), random_drops(200, seed=3)
    assert a == b and a != random_drops(200, seed=4)
    for d in a:
        for v in (d.roll_deg, d.pitch_deg, d.yaw_deg):
            assert -180.0 <= v < 180.0
        assert d.height_m == 1.0
    # the full circle is covered, upside-down included
    assert min(d.roll_deg for d in a) < -150 and max(d.roll_deg for d in a) > 150
    assert min(d.pitch_deg for d in a) < -80 and max(d.pitch_deg for d in a) > 80
    assert [d.height_m for d in random_drops(5, 0, heights=(1.0, 3.0))] == [1.0, 3.0, 1.0, 3.0, 1.0]
    assert {d.height_m for d in random_drops(5, 0, heights=2.5)} == {2.5}
    assert drops_from("random:7", 1, 3.0) == random_drops(7, 1, 3.0)
    assert drops_from("random:7", 1) == random_drops(7, 1)


def test_random_drops_are_uniform_over_rotations():
    """Haar-uniform rotations: the start tilt θ has CDF (1 − cos θ)/2 (Kolmogorov–Smirnov), and the yaw about
    the vertical is uniform; the Euler draw is kept as euler:N and is not uniform (too many near upright)."""
    from scipy.stats import kstest

    from felis.rotations import euler_quat, tilt_deg
    from felis.scenarios.drop import euler_drops

    def tilts(drops):
        return np.array([tilt_deg(euler_quat(d.roll_deg, d.pitch_deg, d.yaw_deg)) for d in drops])

    cdf = lambda t: (1 - np.cos(np.radians(t))) / 2  # noqa: E731
    assert kstest(tilts(random_drops(2000, seed=5)), cdf).pvalue > 0.01
    assert kstest(tilts(euler_drops(2000, seed=5)), cdf).pvalue < 1e-6
    assert drops_from("euler:4", 2, 3.0) == euler_drops(4, 2, 3.0)


@pytest.mark.parametrize("arg, height", [("random:0", None), ("random:x", None), ("random:3", -1.0),
                                         ("random:3", 21.0), ("random:3", math.nan)])
def test_random_bad(arg, height):
    with pytest.raises(ParameterError) as e:
        drops_from(arg, 0, height)
    assert "\n" not in str(e.value)


def test_height_only_with_random(tmp_path):
    p = _write(tmp_path, [GOOD])
    with pytest.raises(ParameterError, match="--height is for --drops random:N"):
        drops_from(str(p), 0, 2.0)


def test_policies(tmp_path):
    assert check_policy("passive") == "passive" and check_policy("stand") == "stand"
    with pytest.raises(ParameterError, match="no such policy file"):
        check_policy(str(tmp_path / "nope.npz"))
    f = tmp_path / "policy.npz"
    f.write_bytes(b"x")
    with pytest.raises(ParameterError, match="not a landing policy file") as e:
        check_policy(str(f))
    assert "\n" not in str(e.value)
    assert check_policy("rules") == "rules"


# ----------------------------------------------------------------------------------- real MuJoCo drops
@pytest.fixture(scope="module")
def sim():
    s = LandingSim()
    yield s
    s.close()


def test_standing_waist_measured(sim):
    """The cat at rest in its stand pose: waist a little under the MJCF's 0.117 m (legs splayed, contacts)."""
    assert 0.10 < sim.standing_waist_m < 0.117


def test_upright_low_drop_with_stand_lands(sim):
    o = sim.run(Drop(0.0, 0.0, 0.0, 0.3), "stand")
    assert o.landed and o.foot_only and o.why == "" and o.reasons == ()
    assert o.first_body.endswith("_foot")
    assert o.touchdown_s == pytest.approx(math.sqrt(2 * 0.3 / 9.81), abs=0.01)
    assert o.tilt_deg < 10 and o.waist_m > 0.9 * sim.standing_waist_m and o.final_tilt_deg < 10
    assert o.peak_impact > 1.0


def test_upside_down_passive_does_not_land(sim):
    o = sim.run(Drop(180.0, 0.0, 0.0, 1.0), "passive")
    assert not o.landed and not o.foot_only
    assert o.touch_body in ("upper_body", "lower_body", "head", "tail")
    assert "touched the ground" in o.why and "tilt" in o.why
    assert o.tilt_deg > 150 and o.final_tilt_deg > 150


def test_lands_on_feet_then_topples_within_window(sim):
    """Rolled 40° (past the tipping angle, atan(0.04/0.117) ≈ 19°) from 10 cm: the feet touch down first,
    a leg hits the ground later but within 0.5 s: not landed."""
    o = sim.run(Drop(40.0, 0.0, 0.0, 0.1), "passive")
    assert o.first_body.endswith("_foot")
    assert not o.landed and not o.foot_only
    assert o.touch_body is not None and not o.touch_body.endswith("_foot")
    assert 0.02 < o.touch_s <= WINDOW_S
    assert f"{o.touch_body} touched the ground" in o.why
    assert summarise([o])["reasons"][f"{o.touch_body} touched the ground"] == 1


def test_summarise_and_run_drops_in_order():
    drops = [Drop(0.0, 0.0, 0.0, 0.3), Drop(180.0, 0.0, 0.0, 0.3)]
    out = run_drops(drops, "stand", workers=1)
    s = summarise(out)
    assert list(s)[0] == "success_rate" and s["success_rate"] == 0.5 and s["landed"] == 1 and s["total"] == 2
    first, second = s["drops"]
    assert first["landed"] and first["why"] is None and not second["landed"] and second["why"]
    for k in ("roll_deg", "pitch_deg", "yaw_deg", "height_m", "landed", "peak_impact", "final_tilt_deg",
              "touchdown_s", "why", "foot_only"):
        assert k in first
    assert second["roll_deg"] == 180.0


def test_shipped_policies_right_the_demo_drop_that_passive_does_not():
    """The default (``caps+library``: at 1 m and 3 m a vote by attitude between the cap policy made for that height
    and the motion library), the library and the shipped nets (learning/weights/landing.npz) against holding still,
    on the demo's drop (1 m, tilted 56°) and upside down from 1 m and 3 m: only the default lands upside down, by
    the closed loop its votes choose there."""
    from felis.cli.demo import DEMO_DROP
    from felis.learning.landing.evaluate import default_policy, shipped_policy
    from felis.learning.landing.library import DEFAULT_LIBRARY, load_library
    from felis.learning.landing.policy import load_policy

    assert default_policy() == "caps+library" and check_policy("caps+library") == "caps+library"
    assert check_policy("library") == "library" and check_policy("shipped") == "shipped"
    load_policy(shipped_policy())  # a valid policy file
    assert [s.height_m for s in load_library(DEFAULT_LIBRARY).shelves] == [1.0, 3.0]
    h, r, p, y = DEMO_DROP
    drops = [Drop(r, p, y, h), Drop(180.0, 0.0, 0.0, 1.0), Drop(180.0, 0.0, 0.0, 3.0)]
    default, library, shipped, passive = (run_drops(drops, pol, workers=1)
                                          for pol in ("caps+library", "library", "shipped", "passive"))
    assert default[0].landed and library[0].landed and shipped[0].landed and not passive[0].landed
    assert default[1].landed and not any(o[1].landed for o in (library, shipped, passive)), default[1].why
    assert default[2].landed and not any(o[2].landed for o in (library, shipped, passive)), default[2].why


# ----------------------------------------------------------------------------------- the CLI
def _args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command")
    train = sub.add_parser("train").add_subparsers(dest="train_command")
    evl = sub.add_parser("eval").add_subparsers(dest="eval_command")
    register_train(train)
    register_eval(evl)
    assert "landing" in train.choices
    return p.parse_args(["eval", "landing", *argv])


def test_cli_json_three_drops_same_with_1_and_2_workers(tmp_path, capsys):
    drops = _write(tmp_path, [{"roll_deg": 0, "pitch_deg": 0, "yaw_deg": 0, "height_m": 0.3},
                              {"roll_deg": 180, "pitch_deg": 0, "yaw_deg": 30, "height_m": 0.5},
                              {"roll_deg": 40, "pitch_deg": 10, "yaw_deg": 0, "height_m": 0.1}])
    results = []
    for w in (1, 2):
        out = tmp_path / f"res{w}.json"
        args = _args(["--drops", str(drops), "--policy", "stand", "--workers", str(w), "--json", "--out", str(out)])
        assert args.policy == "stand" and args.func is cmd_eval_landing
        assert cmd_eval_landing(args) == 0
        printed = json.loads(capsys.readouterr().out)
        assert json.loads(out.read_text()) == printed
        results.append(printed)
    a, b = results
    assert a == b
    assert list(a)[:2] == ["success_rate", "policy"] and list(a)[-1] == "drops"
    assert a["policy"] == "stand" and len(a["drops"]) == 3
    assert [d["landed"] for d in a["drops"]] == [True, False, False]
    assert a["success_rate"] == pytest.approx(1 / 3, abs=1e-4)


def test_cli_default_policy_and_text(capsys):
    from felis.learning.landing.evaluate import default_policy

    args = _args(["--drops", "random:2", "--workers", "1"])
    assert args.policy is None and args.height is None  # the shipped library if any, else the nets, else passive
    assert cmd_eval_landing(args) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"2 drops from 1 m (random:2, seed 0), policy {default_policy()}:")


@pytest.mark.parametrize("argv, what", [
    (["--drops", "random:0"], "random:N"),
    (["--drops", "random:2", "--height", "-1"], "height"),
    (["--drops", "random:2", "--height", "25"], "height"),
    (["--drops", "NOFILE.json"], "no such drops file"),
    (["--drops", "random:2", "--policy", "nope.npz"], "no such policy file"),
    (["--drops", "random:2", "--workers", "0"], "--workers"),
    (["--drops", "random:2", "--out", "result.txt"], ".json"),
])
def test_cli_bad_input_is_one_line(tmp_path, monkeypatch, argv, what):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ParameterError) as e:
        cmd_eval_landing(_args(argv))
    assert what in str(e.value) and "\n" not in str(e.value)


def test_cli_bad_drops_file(tmp_path):
    p = _write(tmp_path, [GOOD, {**GOOD, "height_m": "high"}])
    with pytest.raises(ParameterError, match=r"drop 1: height_m must be a finite number") as e:
        cmd_eval_landing(_args(["--drops", str(p)]))
    assert "\n" not in str(e.value) and str(p) in str(e.value)
