"""Smoke test of ``bench/landing_design.py`` (the design study): one drop, two designs, written as JSON lines, and
the table printed again from the file with ``--resume`` without searching anything."""

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_design.py"


def _bench(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCH), *argv], capture_output=True, text=True, timeout=600)


def test_design_bench_writes_each_drop_and_resumes(tmp_path):
    out = tmp_path / "jobs.jsonl"
    r = _bench("--drops", "1", "--designs", "6V,4ms-paw", "--heights", "1", "--workers", "2", "--out", str(out),
               "--json")
    assert r.returncode == 0, r.stderr
    table = json.loads(r.stdout)
    assert list(table["designs"]) == ["4ms-paw", "6V"]  # the anchor first
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert sorted((x["design"], x["height"], x["i"]) for x in rows) == [("4ms-paw", "1m", 0), ("6V", "1m", 0)]
    cat = next(x for x in rows if x["design"] == "4ms-paw")
    shipped = json.loads((BENCH.parents[1] / "learning" / "weights" / "landing_optimum_4ms-paw-1m.json").read_text())
    assert cat["landed"] == shipped["drops"][0]["landed"]  # the anchor: the shipped search, drop by drop
    assert table["designs"]["4ms-paw"]["1m"] == {"landed": int(cat["landed"]), "of": 1}
    again = _bench("--drops", "1", "--designs", "6V,4ms-paw", "--heights", "1", "--out", str(out), "--resume")
    assert again.returncode == 0, again.stderr
    assert "drop 0:" not in again.stderr  # nothing searched again
    assert "6V" in again.stdout and "(shipped results, 4ms-paw)" in again.stdout
    assert len(out.read_text().splitlines()) == 2
    bad = _bench("--designs", "cat-x")
    assert bad.returncode != 0 and "unknown design 'cat-x'" in bad.stderr
