"""``bench/landing_height.py``: the ceiling's and the library's landings at the drop height and a few mm either way."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

from felis.errors import ParameterError

ROOT = Path(__file__).resolve().parents[2]


def test_summary_counts_landings_per_height_on_average_and_at_every_height():
    bench = load_bench("landing_height")
    R = np.array([[1, 1, 1], [0, 1, 1], [0, 0, 0], [1, 0, 1]], dtype=bool)
    s = bench.summary(R, [-1, 0, 1])
    assert s["landed_at_height"] == 2 and s["landed_at_every_height"] == 1
    assert s["mean_over_heights"] == round(3 / 3 + 2 / 3 + 0 + 2 / 3, 1)
    assert s["by_offset_mm"] == {"-1": 2, "0": 2, "1": 3}


def test_the_shipped_ceiling_reproduces_its_file_at_the_drop_height():
    # the first drops of the shipped seed-0 ceiling from 3 m, each run again from 3 m and ±1 mm; at 3 m itself the
    # ceiling's motions must land exactly the drops its results file says they land
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--height", "3", "--drops", "6",
                        "--mm", "1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["drops"] == 6 and out["offsets_mm"] == [-1, 0, 1]
    c, b = out["ceiling"], out["library"]
    assert c["landed_at_height"] == c["file_says_landed"] > 0
    for s in (c, b):
        assert s["landed_at_every_height"] <= s["landed_at_height"] <= 6
        assert s["by_offset_mm"]["0"] == s["landed_at_height"]


def test_a_file_that_is_not_an_optimum_results_file_is_one_line(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"drops": [{"roll_deg": 0}]}))
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--ceiling", str(bad)],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0
    assert r.stderr.strip().count("\n") == 0 and "not a per-drop optimum's results" in r.stderr


def test_a_design_of_the_study_runs_its_own_optimum_on_its_own_cat():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--design", "soft-rubber-paw",
                        "--drops", "4", "--mm", "1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["design"] == "soft-rubber-paw" and "library" not in out and out["drops"] == 4
    o = out["optimum"]
    assert o["landed_at_height"] == o["by_offset_mm"]["0"] <= 4 and o["landed_at_every_height"] <= o["landed_at_height"]
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--design", "nope"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "unknown design 'nope'" in r.stderr


def test_the_band_ceiling_is_the_candidate_that_lands_the_most_heights_as_if_each_were_tried_at_every_one():
    # the branch and bound skips rollouts, never the best: against every candidate run at every height (on 4ms-paw,
    # whose 1 ms step costs half the described cat's physics: the bound is the same on every cat)
    from felis.learning.landing.designs import design_library
    from felis.learning.landing.library import drop_up, load_library
    from felis.learning.landing.optimum import _worker_sim
    from felis.scenarios.drop import random_drops

    bench = load_bench("landing_height")
    lib = load_library(design_library("4ms-paw"))
    drops = random_drops(3, seed=0, heights=1.0)
    cands = [lib.near(drop_up(d), 1.0)[:5] for d in drops]
    offsets = [-2, -1, 0, 1, 2]
    sim = _worker_sim("4ms-paw")
    calls = []
    share, best, at_h = bench.band_ceiling(sim, drops, cands, offsets, chunk=7,
                                           progress=lambda done, total: calls.append((done, total)))
    full = [bench.landed_at(sim, [d] * len(c), c, offsets) for d, c in zip(drops, cands, strict=True)]
    for i, R in enumerate(full):
        assert share[i] == R.sum(axis=1).max() / len(offsets)
        assert R[best[i]].sum() == R.sum(axis=1).max()
        assert at_h[i] == R[:, offsets.index(0)].any()
    assert calls and calls[-1][0] == calls[-1][1] <= sum(len(c) for c in cands) * len(offsets)
    assert any(0 < s for s in share)  # a case where something lands
    with pytest.raises(ParameterError, match="must include the drop height"):
        bench.band_ceiling(sim, drops, cands, [-1, 1])


@pytest.mark.slow  # 14-21 s: the bench's figures, checked by `make test-slow`
def test_band_reads_the_ceiling_over_the_heights_and_the_library_is_at_most_level_with_it():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--band", "--height", "1",
                        "--drops", "3", "--mm", "1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    b = out["band_ceiling"]
    assert b["candidates"] > 3 and b["landed_at_every_height"] <= 3
    # the library's choice is one of the band's candidates: it can tie, never beat it
    assert out["library"]["mean_over_heights"] <= b["mean_over_heights"] <= 3
    assert b["some_candidate_lands_at_height"] >= out["ceiling"]["landed_at_height"]
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--band", "--design",
                        "soft-rubber-paw"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "not with --design" in r.stderr


def test_period_is_the_shift_at_which_a_pattern_agrees_with_itself_most():
    bench = load_bench("landing_height")
    p = np.array(([1] * 11 + [0] * 4) * 4, dtype=bool)  # period 15 samples
    assert bench.period_mm(p, 0.5) == 7.5
    assert bench.period_mm(np.ones(20, dtype=bool), 0.5) is None


def test_from_3_m_landings_repeat_with_the_fall_of_one_physics_step_a_discretisation_not_physics():
    # on the 4 ms-paw cat at its 1 ms step (the cat as described until 2026-11-29), the library's choice for seed 0's
    # first drop, every 0.5 mm of ±12 mm: it lands and misses with the period of the 7.7 mm the cat falls in one
    # 1 ms step at 7.7 m/s
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--scan", "1", "--on", "4ms-paw",
                        "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert abs(out["fall_per_step_mm"] - 7.67) < 0.01
    (row,) = out["drops"]
    assert 0 < sum(row["landed"]) < len(out["offsets_mm"])
    assert abs(row["period_mm"] - out["fall_per_step_mm"]) <= 1.0


@pytest.mark.slow  # 14-21 s: the bench's figures, checked by `make test-slow`
def test_a_level_drops_paw_penetration_depends_on_the_step_phase_at_the_model_step_not_at_a_quarter_of_it():
    # the 4 ms paw at its 1 ms step (the cat as described until 2026-11-29)
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--penetration", "--on", "4ms-paw",
                        "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    by = json.loads(r.stdout)["by_timestep_ms"]
    coarse, fine = ([row["deepest_mm"] for row in by[k]] for k in ("1", "0.25"))
    assert max(coarse) - min(coarse) > 2 * (max(fine) - min(fine))
    assert min(fine) > 5.0  # the paw sinks deeper than a 5 mm pad is thick
    assert any(row["link_after_ms"] is not None for row in by["1"])  # in some phases a leg link reaches the floor
    # the described cat's rubber paw (τ = 2 ms, the contact's own: the feet take priority over the floor's 4 ms)
    # sinks about a 5 mm pad's thickness at a quarter of its 0.5 ms step, half the 4 ms paw's; at its step the depth
    # still moves with the phase (3.5–5.6 mm), far less than the 4 ms paw's at its 1 ms; no leg link reaches the floor
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--penetration", "--json"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    step, quarter = ([row["deepest_mm"] for row in out["by_timestep_ms"][k]] for k in ("0.5", "0.125"))
    assert out["on"] == "cat" and 4.0 < min(quarter) <= max(quarter) < 6.0 and max(quarter) < 0.6 * min(fine)
    assert 3.0 < min(step) <= max(step) < 6.5 and max(step) - min(step) < 0.5 * (max(coarse) - min(coarse))
    assert all(row["link_after_ms"] is None for rows in out["by_timestep_ms"].values() for row in rows)


@pytest.mark.slow  # 14-21 s: the bench's figures, checked by `make test-slow`
def test_from_3_m_the_4ms_paw_cats_landings_go_as_the_physics_step_shrinks():
    # on the 4 ms-paw cat (the cat as described until 2026-11-29), the library's choice and the ceiling's motions on
    # seed 0's first 20 drops from 3 m, at its 1 ms step and at 0.25 ms: at 1 ms the ceiling lands what its file
    # says; at 0.25 ms both lose more than half of it
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--timesteps", "1", "0.25",
                        "--on", "4ms-paw", "--drops", "20", "--json"], capture_output=True, text=True, cwd=ROOT,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    coarse, fine = out["by_timestep"]
    assert coarse["timestep_ms"] == 1 and coarse["ceiling"] == out["file_says_landed"] > 10
    assert 2 * fine["library"] < coarse["library"] and 2 * fine["ceiling"] < coarse["ceiling"]
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--timesteps", "0.3"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "must divide the 10 ms control tick" in r.stderr
