"""Whole-body motion samples (`felis.learning.landing.wholebody`) and their motion rule."""

from __future__ import annotations

import json

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing.optimum import DIMS, MotionRule
from felis.learning.landing.samples import STEPS, load_samples
from felis.learning.landing.wholebody import make_wholebody_samples, sphere_orientations
from felis.rotations import euler_quat, up_z


def test_sphere_orientations_cover_the_sphere_evenly():
    o = sphere_orientations(200)
    ups = np.array([up_z(euler_quat(*x)) for x in o])  # cos of the start tilt: uniform on [-1, 1] by area
    assert np.allclose(np.sort(ups), np.linspace(1, -1, 200)[::-1], atol=0.02)
    assert all(x[2] == 0.0 for x in o)


def test_motion_rule_round_trip_and_bad_data():
    x = np.random.default_rng(0).uniform(-1, 1, DIMS)
    r = MotionRule(x, 3.0, STEPS)
    again = MotionRule.from_dict(json.loads(json.dumps(r.as_dict())))
    assert np.allclose(again.table, r.table, atol=1e-4) and again.duration == pytest.approx(STEPS * 0.01)
    for bad in ({"kind": "spine"}, {"kind": "whole-body", "motion_x": [1, 2], "height_m": 3, "steps": 200},
                {"kind": "whole-body", "motion_x": ["a"] * DIMS, "height_m": 3, "steps": 200},
                {"kind": "whole-body", "motion_x": [0] * DIMS, "height_m": -1, "steps": 200}):
        with pytest.raises(ParameterError, match="^whole-body motion"):
            MotionRule.from_dict(bad)


def test_make_and_load_wholebody_samples(tmp_path):
    out = tmp_path / "wb.json"
    made = make_wholebody_samples(out, n=2, generations=1, population=4, restarts=0)
    got = load_samples(out)
    assert len(got) == len(made) == 2
    for a, b in zip(made, got, strict=True):
        assert isinstance(b.rule, MotionRule) and b.orientation == a.orientation
        assert np.array_equal(a.vectors, b.vectors) and b.vectors.shape[0] == STEPS
    doc = json.loads(out.read_text())
    assert doc["kind"] == "whole-body" and "make_wholebody_samples" in doc["command"]
