"""``bench/landing_roughness.py``: the share of a neighbour's landing motions that land a probe, by distance."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import load_bench

ROOT = Path(__file__).resolve().parents[2]


def test_carry_over_counts_the_candidates_tried_on_both_and_landing_the_neighbour():
    bench = load_bench("landing_roughness")
    up = np.array([[0.0, 0.0, 1.0], [np.sin(np.radians(0.5)), 0.0, np.cos(np.radians(0.5))],
                   [np.sin(np.radians(4.0)), 0.0, np.cos(np.radians(4.0))]])
    cand = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # the third: 90° away, never tried
    lands = np.array([[1, 0, 1], [1, 1, 0], [0, 1, 0]], dtype=bool)
    rows = {r["from_deg"]: r for r in bench.carry_over(up, lands, cand, 15.0, bins=((0.0, 1.0), (3.0, 5.0)))}
    # 0.5° apart, (p, q) = (0, 1) and (1, 0); candidate 2 is tried on neither. Landing q: {0, 1} and {0}; of those
    # landing p too: {0} and {0}: 2 of 3
    assert rows[0.0]["pairs"] == 2 and rows[0.0]["candidates"] == 3 and rows[0.0]["lands_too"] == round(2 / 3, 3)
    # 4° and 3.5° apart, (p, q) = (0, 2), (2, 0), (1, 2), (2, 1): landing q {1}, {0}, {1}, {0, 1}; landing p
    # too: none, none, {1}, {1}: 2 of 5
    assert rows[3.0]["pairs"] == 4 and rows[3.0]["candidates"] == 5 and rows[3.0]["lands_too"] == round(2 / 5, 3)


def test_the_shipped_library_at_3_m():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "landing_roughness.py"), "--json"], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    bins = json.loads(r.stdout)["bins"]
    near, far = bins[0]["lands_too"], bins[-1]["lands_too"]
    assert 0.0 < far < near < 1.0  # docs/landing.md: 0.79 within 1°, 0.52 at 5–8°
