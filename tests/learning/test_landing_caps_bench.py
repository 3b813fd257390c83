"""``bench/landing_caps.py``: a cap policy built from the library and evaluated against it."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_caps.py"


def test_build_then_resume_then_evaluate(tmp_path):
    """A one-centre build (a generation of two on three starts), resumed (nothing left to do: the same file), a
    resume with other settings refused in one line, one more generation (`--more`: kept only if it scores higher;
    recorded), then the evaluation of it and the library on six drops."""
    out = tmp_path / "caps.json"
    cmd = [sys.executable, str(BENCH), "--out", str(out), "--centres", "6", "--max-tilt", "60", "--train", "3",
           "--generations", "1", "--popsize", "2", "--steps", "50"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    (c,) = d["caps"]
    assert d["format"] == "felis-landing-caps" and d["settings"]["train"] == 3 and c["rollouts"] == 3 + 2 * 3
    assert 0 <= c["evolved_lands_train"] <= 3 and len(c["best_after_generation"]) == 1 and c["tilt_deg"] <= 60
    before = out.read_bytes()
    r = subprocess.run([*cmd, "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and out.read_bytes() == before and "1 behaviours" in r.stdout
    r = subprocess.run([*cmd[:-2], "--steps", "60", "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "built with other settings" in r.stderr and r.stderr.strip().count("\n") == 0
    r = subprocess.run([*cmd, "--more", "1"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d2 = json.loads(out.read_text())
    (c2,) = d2["caps"]
    assert c2["score"] >= c["score"] and len(c2["more"]) == 1 and c2["more"][0]["rollouts"] == 3 + 2 * 3
    assert d2["more_by"] == [" ".join(cmd[2:] + ["--more", "1"])] and d2["made_by"] == d["made_by"]
    r = subprocess.run([*cmd[:3], str(tmp_path / "none.json"), *cmd[4:], "--more", "1"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1 and "--more continues a built file" in r.stderr
    r = subprocess.run([sys.executable, str(BENCH), "--policy", str(out), "--drops", "random:6", "--seeds", "0",
                        "--late", "1", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    row = res["seeds"]["0"]
    assert res["behaviours"] == 1 and set(row) == {"caps", "library"}
    for v in row.values():
        assert len(v["landed"]) == 2 and all(0 <= n <= 6 for n in v["landed"])
        assert sum(b["landed"] for b in v["by_tilt"].values()) == v["landed"][0]


@pytest.mark.parametrize("text, says", [("{", "Expecting"), ('{"format": "x"}', "not a felis-landing-caps file"),
                                        ('{"format": "felis-landing-caps", "settings": {"hidden": 8}, "caps": []}',
                                         "holds no behaviour")])
def test_a_bad_caps_file_is_one_line(tmp_path, text, says):
    from felis.errors import ParameterError

    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(ParameterError, match=says):
        load_bench("landing_caps").load_caps(p)
    r = subprocess.run([sys.executable, str(BENCH), "--policy", str(p)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and str(p) in r.stderr and r.stderr.strip().count("\n") == 0


def test_a_genome_of_the_wrong_length_is_refused(tmp_path):
    from felis.errors import ParameterError

    bench = load_bench("landing_caps")
    g = np.zeros(len(bench.genome(bench.template(8))) - 1).tolist()
    p = tmp_path / "short.json"
    p.write_text(json.dumps({"format": "felis-landing-caps", "settings": {"hidden": 8},
                             "caps": [{"centre": [0, 0, 1], "genome": g}]}))
    with pytest.raises(ParameterError, match="a genome of"):
        bench.load_caps(p)
    bad = subprocess.run([sys.executable, str(BENCH)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "give --out FILE (build) or --policy FILE (evaluate)" in bad.stderr
