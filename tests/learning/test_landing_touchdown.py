"""``bench/landing_touchdown.py``: the library with the legs' touchdown offsets closed on the IMU."""

import math

import numpy as np
import pytest
from conftest import load_bench

from felis.errors import ParameterError
from felis.learning.landing.library import LibraryBatch, load_library
from felis.learning.landing.policy import DROP_HEIGHT_M


def _it(roll_deg, pitch_deg, h):
    it = np.zeros((1, 15))
    it[0, 4] = math.radians(roll_deg) / math.pi
    it[0, 5] = math.radians(pitch_deg) / (math.pi / 2)
    it[0, 6] = h / DROP_HEIGHT_M
    return it


def test_the_offsets_follow_the_imu_below_on_and_are_held_from_freeze():
    bench = load_bench("landing_touchdown")
    lib = load_library()
    args = (lib, [3.0], 120, 10.0)
    fb = bench.TouchdownFeedback(LibraryBatch(*args), 1, k=0.5, on_m=0.6, freeze_m=0.2)
    plain = LibraryBatch(*args)
    rows = np.array([0])
    steps = [(0.0, 20.0, -10.0, 2.9), (0.01, 20.0, -10.0, 0.5), (0.02, 80.0, 0.0, 0.4), (0.03, 30.0, -10.0, 0.3),
             (0.04, 10.0, 5.0, 0.15), (0.05, -10.0, -5.0, 0.1)]
    offset, held = np.zeros(12), None
    for t, roll, pitch, h in steps:
        it = _it(roll, pitch, h)
        v = fb(it, np.array([t]), rows)[0] - plain(it, np.array([t]), rows)[0]
        offset = offset + v * 0.01
        want = np.zeros(12)
        if 0.2 <= h < 0.6 and abs(roll) < 60:
            want[bench.PITCH], want[bench.ROLL] = -0.5 * math.radians(pitch), -0.5 * math.radians(roll)
        elif h < 0.2:  # held: what it was at the last tick above 0.2 m
            want = held
        np.testing.assert_allclose(offset, want, atol=1e-12, err_msg=f"t={t}")
        held = offset.copy()


def test_gain_zero_is_the_library():
    bench = load_bench("landing_touchdown")
    from felis.learning.landing.evaluate import run_drops
    from felis.scenarios.drop import drops_from

    drops = drops_from("random:4", seed=2, height=1.0)
    assert bench.landed(drops, 0.0, 0.6, 0.2) == sum(o.landed for o in run_drops(drops, "library"))
    assert bench.landed(drops, 1e-12, 0.6, 0.2) == bench.landed(drops, 0.0, 0.6, 0.2)


def test_the_feedback_inside_the_search():
    """`robustness`: the optimum's rollouts run through the wrap (k = 0: none, the open loop's own results), and
    each landing motion is tried from 8 attitudes near its drop."""
    bench = load_bench("landing_touchdown")
    from felis.learning.landing.optimum import optimise
    from felis.scenarios.drop import Drop

    drops = [Drop(20.0, 10.0, 0.0, 1.0), Drop(60.0, 0.0, 0.0, 1.0)]  # within reach of the seeds from 1 m
    plain = optimise(drops, generations=0, population=2)
    r0 = bench.robustness(drops, 0.0, 0.6, 0.2, generations=0, population=2)
    assert r0["landed"] == sum(o.landed for o in plain) > 0
    assert r0["near_tried_per_offset"] == 8 * r0["landed"] and set(r0["near_landed"]) == {"1", "2"}
    assert all(0 <= n <= 8 * r0["landed"] for n in r0["near_landed"].values())
    seen = []

    def wrap(policy, rows):
        seen.append(rows)
        return policy

    same = optimise(drops, generations=0, population=2, wrap=wrap)
    assert seen and [o.score for o in same] == [o.score for o in plain]  # an identity wrap changes nothing


def test_a_patch_scores_the_worst_of_five_attitudes():
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.optimum import evaluate, patch, seeds
    from felis.scenarios.drop import Drop

    d, x = Drop(40.0, 20.0, 0.0, 1.0), seeds()[:3]
    sim = BatchLandingSim()
    try:
        got = evaluate(sim, [d] * 3, x, patch_deg=2.0)
        each = evaluate(sim, [d, *patch(d, 2.0)] * 3, np.repeat(x, 5, axis=0))
    finally:
        sim.close()
    for i in range(3):
        assert got[i][0] == min(s for s, _ in each[5 * i:5 * i + 5])


def test_a_height_patch_scores_the_worst_of_three_heights():
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.optimum import evaluate, seeds
    from felis.scenarios.drop import Drop

    d, x = Drop(40.0, 20.0, 0.0, 3.0), seeds()[:3]
    ups = [Drop(40.0, 20.0, 0.0, 3.0 + mm / 1000) for mm in (0.0, -2.0, 2.0)]
    sim = BatchLandingSim()
    try:
        got = evaluate(sim, [d] * 3, x, patch_mm=2.0)
        each = evaluate(sim, ups * 3, np.repeat(x, 3, axis=0))
        with pytest.raises(ParameterError, match="≥ 0 mm"):
            evaluate(sim, [d], x[:1], patch_mm=-1.0)
    finally:
        sim.close()
    for i in range(3):
        assert got[i][0] == min(s for s, _ in each[3 * i:3 * i + 3])


# slow (12 s): the search's --patch option through a long run; its inside is tested above by default
@pytest.mark.slow
def test_patch_through_the_long_run_and_the_cli(tmp_path):
    """`optimise_all(patch_deg=)` equals `optimise` (chunked, checkpointed: the header records the patch); the
    commands refuse a negative patch in one line."""
    import json
    import subprocess
    import sys

    from felis.learning.landing.optimum import optimise, optimise_all, seeds
    from felis.scenarios.drop import Drop

    drops = [Drop(30.0, 0.0, 0.0, 1.0), Drop(0.0, 50.0, 0.0, 1.0)]
    one = optimise(drops, generations=1, population=4, patch_deg=2.0)
    many = optimise_all(drops, generations=1, population=4, workers=1, chunk=1, workdir=str(tmp_path / "w"),
                        patch_deg=2.0)
    assert [o.as_dict() for o in one] == [o.as_dict() for o in many]
    for o in one:  # every rollout five times: the seeds, then one generation of 4 unless a seed landed the patch
        assert o.rollouts in (5 * len(seeds()), 5 * (len(seeds()) + 4))
    head = json.loads((tmp_path / "w" / "optimum.jsonl").read_text().splitlines()[0])
    assert head["settings"]["patch_deg"] == 2.0
    for argv in (("eval", "landing", "--policy", "optimum", "--drops", "random:1", "--patch", "-1"),
                 ("train", "landing-library", "--patch", "nan", "--out", str(tmp_path / "l.json"))):
        r = subprocess.run([sys.executable, "-m", "felis", *argv], capture_output=True, text=True, timeout=120)
        assert r.returncode != 0 and "--patch must be ≥ 0 degrees" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr
