"""Robot descriptions: the shipped ones load as robots.md says; bad ones fail with one clear line."""

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from felis.errors import DescriptionError, UnknownRobotError
from felis.spec import ROBOTS_DIR, available_robots, load_spec, parse_spec

CAT_JOINTS = ["spine_pitch", "spine_yaw", "tail_pitch", "tail_yaw", "fl_pitch", "fl_roll", "fr_pitch",
              "fr_roll", "hl_pitch", "hl_roll", "hr_pitch", "hr_roll"]
CAT_TEXT = (ROBOTS_DIR / "cat.toml").read_text()


def test_cat_description_matches_robots_md():
    cat = load_spec("cat")
    assert list(cat.names) == CAT_JOINTS
    assert [j.servo_id for j in cat.joints] == list(range(1, 13))
    assert all(j.servo == "XL330-M288-T" for j in cat.joints)
    for j in cat.joints:
        limit = math.radians(90 if j.group == "legs" else 60)
        assert (j.lower, j.upper) == pytest.approx((-limit, limit))
    assert cat.groups == {"spine": ("spine_pitch", "spine_yaw"), "tail": ("tail_pitch", "tail_yaw"),
                          "legs": tuple(CAT_JOINTS[4:])}
    assert cat.sensors.imu == "imu" and cat.sensors.height == "waist"
    assert cat.sensors.contacts == ("fl_foot", "fr_foot", "hl_foot", "hr_foot")
    assert 0.8 <= sum(cat.links.values()) <= 1.5
    assert cat.max_velocity == pytest.approx(np.full(12, 103 * 2 * math.pi / 60))
    assert {"stand", "sit", "zero"} <= set(cat.poses)


def test_arm_description_matches_robots_md():
    arm = load_spec("arm")
    assert list(arm.names) == ["joint1", "joint2", "joint3", "joint4", "gripper"]
    assert [j.servo_id for j in arm.joints] == [11, 12, 13, 14, 15]
    assert arm.lower == pytest.approx([-math.pi, -1.5, -1.5, -1.7, -0.010])
    assert arm.upper == pytest.approx([math.pi, 1.5, 1.4, 1.97, 0.019])
    assert arm.joints[4].kind == "prismatic"
    assert arm.indices("arm").tolist() == [0, 1, 2, 3]


def test_available_and_unknown_robot():
    assert {"cat", "arm"} <= set(available_robots())
    with pytest.raises(UnknownRobotError, match="unknown robot 'dog'.*arm, arm-leader, cat"):
        load_spec("dog")


def test_missing_file(tmp_path):
    with pytest.raises(DescriptionError, match="no such description file"):
        load_spec(tmp_path / "nope.toml")


def _edit(pattern: str, repl: str, count: int = 1) -> str:
    text, n = re.subn(pattern, repl, CAT_TEXT, count=count, flags=re.S)
    assert n, f"pattern {pattern!r} not in cat.toml"
    return text


BAD = {
    "unknown top-level key": ('colour = "ginger"\n' + CAT_TEXT, "colour", "unknown key"),
    "unknown joint key": (_edit(r"(\[joint.spine_yaw\]\n)", r"\1speed = 3\n"), "joint.spine_yaw.speed",
                          "unknown key"),
    "missing joint table": (_edit(r"\[joint.tail_yaw\]\n.*?\n\n", ""), "joint.tail_yaw", "missing"),
    "joint not listed": (_edit(r'"hr_roll",\n', "\n"), "joint.hr_roll", "not listed"),
    "limits beyond the servo": (_edit(r"(\[joint.fl_pitch\].*?range_deg = )\[-90, 90\]", r"\1[-200, 200]"),
                                "joint.fl_pitch.range_deg", "XL330-M288-T"),
    "duplicate servo id": (_edit(r"(\[joint.fr_roll\]\n)id = 8", r"\1id = 3"), "joint.fr_roll.id",
                           "already used by tail_pitch"),
    "empty range": (_edit(r"(\[joint.spine_pitch\].*?range_deg = )\[-60, 60\]", r"\1[10, 10]"),
                    "joint.spine_pitch.range_deg", "must be below"),
    "unknown servo": (_edit(r'(\[joint.tail_pitch\]\nid = 3\nservo = )"XL330-M288-T"', r'\1"XL999"'),
                      "joint.tail_pitch.servo", "unknown servo model"),
    "id out of range": (_edit(r"(\[joint.fl_roll\]\n)id = 6", r"\1id = 300"), "joint.fl_roll.id", "outside"),
    "bad direction": (_edit(r"(\[joint.fl_roll\]\n)", r"\1direction = 0\n"), "joint.fl_roll.direction",
                      "must be 1 or -1"),
    "too fast": (_edit(r"(\[joint.fl_roll\]\n)", r"\1max_velocity = 50.0\n"), "joint.fl_roll.max_velocity",
                 "no-load speed"),
    "wrong type": (_edit(r"(\[joint.fl_roll\]\n)id = 6", r'\1id = "six"'), "joint.fl_roll.id", "expected int"),
    "pose misses a joint": (_edit(r"(\[poses.sit\].*?)hr_roll = 0.0\n", r"\1"), "poses.sit.hr_roll", "missing"),
    "pose out of range": (_edit(r"(\[poses.sit\].*?hl_pitch = )-1.2", r"\g<1>-3.0"), "poses.sit.hl_pitch",
                          "outside"),
    "pose names unknown joint": (_edit(r"(\[poses.sit\][^\n]*\n)", r"\1neck = 0.1\n"), "poses.sit.neck",
                                 "unknown key"),
    "schema version": (_edit(r"schema = 1", "schema = 7"), "schema", "not supported"),
    "missing name": (_edit(r'name = "cat"\n', ""), "name", "missing"),
    "not TOML": ("this is [not toml", "toml", "not valid TOML"),
    "sensor typo": (_edit(r"(\[sensors\]\n)", r'\1lidar = "x"\n'), "sensors.lidar", "unknown key"),
    "negative mass": (_edit(r"head = 0.06", "head = -0.06"), "links.head", "positive"),
}


@pytest.mark.parametrize("case", BAD, ids=list(BAD))
def test_bad_description_one_line_naming_file_and_key(case, tmp_path):
    text, key, problem = BAD[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(DescriptionError) as err:
        load_spec(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: {key}:"), msg
    assert problem in msg


def test_prismatic_range_checked_through_transmission():
    arm_text = (ROBOTS_DIR / "arm.toml").read_text()
    bad = arm_text.replace("m_per_rad = 0.015", "m_per_rad = 0.001")  # 0.019 m would need 19 rad of horn
    with pytest.raises(DescriptionError, match="joint.gripper.range: maps to servo angles"):
        parse_spec(bad, "arm.toml")


@settings(max_examples=150, deadline=None)
@given(st.text(max_size=300))
def test_garbage_never_crashes_with_anything_but_description_error(text):
    try:
        parse_spec(text, "fuzz.toml")
    except DescriptionError as e:
        assert str(e).startswith("fuzz.toml: ") and "\n" not in str(e)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 11), st.sampled_from(["id", "range_deg", "group", "servo"]),
       st.one_of(st.integers(-1000, 1000), st.floats(allow_nan=True), st.text(max_size=5), st.booleans(),
                 st.lists(st.integers(-400, 400), max_size=3)))
def test_mutated_joint_values_fail_cleanly(i, key, value):
    import tomllib

    doc = tomllib.loads(CAT_TEXT)
    doc["joint"][CAT_JOINTS[i]][key] = value
    text = _dump(doc)
    try:
        spec = parse_spec(text, "m.toml")
    except DescriptionError as e:
        assert "\n" not in str(e) and str(e).startswith("m.toml: ")
    else:  # accepted: then it must be a valid description
        assert len({j.servo_id for j in spec.joints}) == 12
        assert np.all(spec.lower < spec.upper)


def _dump(doc: dict) -> str:
    """Minimal TOML writer for the description's shape (tests only)."""
    import json

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return "nan" if v != v else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return json.dumps(v) if isinstance(v, str) else str(v)

    lines = [f"{k} = {val(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            scal = {kk: vv for kk, vv in v.items() if not isinstance(vv, dict)}
            if scal or not v:
                lines.append(f"[{k}]")
                lines += [f"{kk} = {val(vv)}" for kk, vv in scal.items()]
            for kk, vv in v.items():
                if isinstance(vv, dict):
                    lines.append(f"[{k}.{kk}]")
                    lines += [f"{a} = {val(b)}" for a, b in vv.items()]
    return "\n".join(lines) + "\n"


def test_dump_roundtrip():
    import tomllib

    assert parse_spec(_dump(tomllib.loads(CAT_TEXT))).names == load_spec("cat").names


def test_shipped_files_are_in_package():
    assert Path(str(ROBOTS_DIR / "cat.toml")).is_file()
