"""Smoke test of ``bench/landing_holes.py``: the shipped 1 m shelf's holes and misses on the described cat (the
figures docs/landing.md gives), a few drops' losses, and the lost drops written as a drops file that the library
indeed loses."""

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_holes.py"


def test_holes_bench_counts_the_shelfs_holes_and_writes_the_lost_drops(tmp_path):
    from felis.learning.landing.evaluate import run_drops
    from felis.scenarios.drop import load_drops

    lost = tmp_path / "lost.json"
    r = subprocess.run([sys.executable, str(BENCH), "--n", "8", "--seeds", "12", "--radius", "10", "--json",
                        "--lost", str(lost)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["probes"] == 2958 and res["holes"] == 308 and res["misses"] == 107  # docs/landing.md
    assert sum(v[0] for v in res["holes_by_tilt"].values()) == res["holes"]
    assert sum(v[1] for v in res["holes_by_tilt"].values()) == res["probes"]
    (s,) = res["seeds"]
    assert s["seed"] == 12 and s["landed"] + s["lost"] == 8 and len(s["lost_tilts"]) == s["lost"]
    assert s["a_candidate_lands"] == len(s["rescued_tilts"]) <= s["lost"]
    drops = load_drops(lost)
    assert len(drops) == s["lost"] >= 1
    assert not any(o.landed for o in run_drops(drops, "library"))
