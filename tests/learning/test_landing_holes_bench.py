"""Smoke test of ``bench/landing_holes.py``: the shipped 1 m shelf's holes and misses on the described cat (the
figures docs/landing.md gives), a few drops' losses, and the lost drops written as a drops file that the library
indeed loses."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


CEILING_LOST = BENCH.parents[1] / "learning" / "weights" / "landing_ceiling_lost-1m-seeds10-12.json"


def _ceiling_by_seed() -> dict[int, tuple[int, int]]:
    """{seed: (library landed, ceiling landed)} from the shipped ceiling of the library's lost drops."""
    doc = json.loads(CEILING_LOST.read_text())
    out = {}
    for s in doc["seeds"]:
        more = sum(o["landed"] for part in ("under130", "from130")
                   for o, w in zip(doc[part]["results"]["drops"], doc[part]["drop_seeds"], strict=True) if w == s)
        out[s] = (doc["library_landed"][str(s)], doc["library_landed"][str(s)] + more)
    return out


def test_the_held_out_1m_ceiling_is_what_the_docs_say():
    """docs/landing.md "Where held-out 1 m drops are lost" and the README: the library lands 78, 75, 62 of seeds
    10–12 from 1 m; the warm-started optimum of its lost drops lands 8 of the 36 under 130° and 10 of the 49 from
    130°, so the ceiling is 82, 80, 71 and the library 95, 94, 87 % (92 % in all) of it."""
    doc = json.loads(CEILING_LOST.read_text())
    under, beyond = doc["under130"]["results"], doc["from130"]["results"]
    assert (under["landed"], under["total"], beyond["landed"], beyond["total"]) == (8, 36, 10, 49)
    assert under["design"] == beyond["design"] == "cat" and under["search"]["warm_start"] == "library"
    assert under["search"]["restarts"] == beyond["search"]["restarts"] == 1
    by_seed = _ceiling_by_seed()
    assert by_seed == {10: (78, 82), 11: (75, 80), 12: (62, 71)}
    assert [round(100 * a / b) for a, b in by_seed.values()] == [95, 94, 87]
    lib, ceil = (sum(v[i] for v in by_seed.values()) for i in (0, 1))
    assert (lib, ceil, round(100 * lib / ceil)) == (215, 233, 92)
    for text in ((BENCH.parents[1] / "docs" / "landing.md").read_text(), (BENCH.parents[1] / "README.md").read_text()):
        assert "82, 80 and 71" in " ".join(text.split())


@pytest.mark.slow
def test_the_shipped_held_out_ceiling_searched_exactly_the_drops_the_library_loses():
    """The file's drops are the library's lost drops of random:100 seeds 10–12 from 1 m, under 130° then from 130°,
    and the library lands what the file says (~1 min)."""
    from felis.learning.landing.evaluate import run_drops
    from felis.learning.landing.library import drop_up
    from felis.learning.landing.library_build import tilts_deg
    from felis.scenarios.drop import random_drops

    doc = json.loads(CEILING_LOST.read_text())
    want = {"under130": [], "from130": []}
    for s in doc["seeds"]:
        drops = random_drops(100, seed=s, heights=(1.0,))
        outs = run_drops(drops, "library")
        assert sum(o.landed for o in outs) == doc["library_landed"][str(s)]
        for d, o in zip(drops, outs, strict=True):
            if not o.landed:
                want["under130" if tilts_deg(drop_up(d)[None])[0] < 130 else "from130"].append((s, d))
    for part, rows in want.items():
        got = doc[part]["results"]["drops"]
        assert [s for s, _ in rows] == doc[part]["drop_seeds"]
        assert len(got) == len(rows)
        for o, (_, d) in zip(got, rows, strict=True):
            assert abs(o["roll_deg"] - d.roll_deg) < 1e-3 and abs(o["pitch_deg"] - d.pitch_deg) < 1e-3
