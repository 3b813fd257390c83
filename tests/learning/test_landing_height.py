"""``bench/landing_height.py``: the ceiling's and the library's landings at the drop height and a few mm either way."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import load_bench

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
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--design", "rubber-paw",
                        "--drops", "4", "--mm", "1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["design"] == "rubber-paw" and "library" not in out and out["drops"] == 4
    o = out["optimum"]
    assert o["landed_at_height"] == o["by_offset_mm"]["0"] <= 4 and o["landed_at_every_height"] <= o["landed_at_height"]
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_height.py"), "--design", "nope"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "unknown design 'nope'" in r.stderr
