"""Pose files (`felis.calib.poses`): location, round trip with backup, the description's poses as defaults, checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from felis.calib.poses import DESCRIPTION, FILE, PoseFile, known_poses, load, poses_path, resolve, save
from felis.errors import CalibrationError, ParameterError
from felis.spec import load_spec


@pytest.fixture(autouse=True)
def config_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    return tmp_path / "config"


def test_round_trip_backup_and_location_beside_the_calibration(config_home):
    spec = load_spec("arm")
    path = poses_path("arm", "a1")
    assert path == config_home / "felis" / "calibration" / "arm" / "a1.poses.json"
    q = np.array([0.1, -0.2, 0.3, -0.4, 0.005])
    pf = PoseFile("arm", "a1").with_pose(spec, "reach", q)
    save(pf, path)
    save(pf.with_pose(spec, "stand", 0.5 * q), path)
    back = load(path, spec, robot_id="a1")
    assert list(back.poses) == ["reach", "stand"] and back.pose(spec, "reach").q.tolist() == q.tolist()
    assert list(load(path.with_name("a1.poses.json.bak"), spec).poses) == ["reach"]
    data = json.loads(path.read_text())
    assert data["schema"] == 1 and data["poses"]["reach"]["created"].endswith("Z")
    known = known_poses(spec, back)  # taught first; a taught 'stand' overrides the description's
    assert [(n, p.source) for n, p in known.items()] == [("reach", FILE), ("stand", FILE), ("zero", DESCRIPTION),
                                                         ("sit", DESCRIPTION)]
    assert [p.name for p in resolve(spec, back, ["sit", "reach"])] == ["sit", "reach"]
    with pytest.raises(ParameterError, match=r"no pose 'x' for the arm 'a1'; known: reach, stand \(taught\); zero, "
                                             r"sit \(description\)"):
        resolve(spec, back, ["x"])


@pytest.mark.parametrize("edit, expect", [
    (lambda d: d["poses"]["reach"]["joints"].update(joint9=0.0), "joint 'joint9' is not in the arm description"),
    (lambda d: d["poses"]["reach"]["joints"].update(joint2=2.0), "joint2 = 2.0000 is outside its limits"),
    (lambda d: d["poses"]["reach"]["joints"].update(joint2="1"), "joints.joint2: must be a finite number"),
    (lambda d: d.update(robot="cat"), "holds poses of a 'cat', not of a 'arm'"),
    (lambda d: d.update(schema=2), "schema 2 is not supported"),
    (lambda d: d["poses"].update({"bad name": {"joints": {}}}), "poses.bad name: pose name"),
    (lambda d: d.pop("poses"), "poses: missing"),
])
def test_bad_files_are_one_line_naming_the_backup(edit, expect):
    spec = load_spec("arm")
    path = poses_path("arm", "a1")
    pf = PoseFile("arm", "a1").with_pose(spec, "reach", np.zeros(5))
    save(pf, path)
    save(pf, path)  # a backup exists
    data = pf.to_dict()
    edit(data)
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=expect) as e:
        load(path, spec)
    assert "\n" not in str(e.value) and str(e.value).endswith("a1.poses.json.bak")


def test_a_missing_file_is_no_taught_poses_only_when_allowed():
    spec = load_spec("arm")
    assert load(poses_path("arm", "new"), spec, missing_ok=True) is None
    with pytest.raises(CalibrationError, match="no pose file at"):
        load(poses_path("arm", "new"), spec)
