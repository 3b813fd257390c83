"""``bench/landing_clone.py``: a simple behaviour of the paper's nets fitted by regression to a library motion."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_clone.py"


def test_fit_recovers_a_behaviour_it_can_represent():
    """The known-good case: velocities made by a simple behaviour with every input (h = 4) are fitted by one of the
    same shape to a small fraction of their spread, and the fit is a valid `SimpleBehaviour` that runs as the
    controller runs it."""
    import torch

    from felis.errors import ParameterError
    from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour

    rng = np.random.default_rng(1)
    units = []
    for p in PARTS:
        k = KINDS[p]
        w1, w2 = rng.normal(0, 0.5, size=(4, k.n_available + 1)), rng.normal(0, 0.5, size=(len(k.outputs), 5))
        units.append(GeneUnit(p, tuple(range(k.n_available)), 4, w1, w2, MAX_SPEED))
    teacher = SimpleBehaviour(*units).check()
    it = rng.uniform(-1, 1, size=(300, 15))
    v = teacher.velocities_many(it)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the bench runs it: a small net, and the other test worker on the other core
    try:
        policy, rms, behaviour = load_bench("landing_clone").fit(it, v, hidden=4, steps=800)
    finally:
        torch.set_num_threads(threads)
    assert isinstance(behaviour, SimpleBehaviour) and behaviour.check() is behaviour
    assert rms < 0.1 * float(np.std(v)), (rms, float(np.std(v)))
    assert np.allclose(policy(it[:5]), behaviour.velocities_many(it[:5]))
    with pytest.raises(ParameterError, match="hidden ≥ 1"):
        load_bench("landing_clone").fit(it, v, hidden=0, steps=1)


def test_clone_bench_runs_one_motion():
    r = subprocess.run([sys.executable, str(BENCH), "--n", "1", "--steps", "50", "--json"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    (m,) = res["motions"]
    assert m["open_loop_landed"] is True and m["ticks"] == 145 and np.isfinite(m["rms_rad_s"])
    assert res["clone_landed"] == int(m["clone_landed"]) and res["motions_tried"] == 1 + len(res["skipped_not_landing"])
    bad = subprocess.run([sys.executable, str(BENCH), "--n", "0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--n and --hidden must be ≥ 1" in bad.stderr


def test_the_shipped_clone_runs_are_what_the_docs_say():
    """docs/landing.md "Whether a net holds one" and the README: of 24 motions that land their start, the paper-size
    fit lands 12, with DAgger 14, 64 neurons and a clock 6; median velocity error 0.69, 0.79, 0.61 rad/s."""
    root = BENCH.parents[1]
    runs = json.loads((root / "learning" / "weights" / "landing_clone-1m.json").read_text())["runs"]
    got = {k: (len(r["motions"]), r["clone_landed"], round(float(np.median([m["rms_rad_s"] for m in r["motions"]])), 2))
           for k, r in runs.items()}
    assert got == {"paper-size": (24, 12, 0.69), "dagger-3": (24, 14, 0.79), "64-hidden-clock": (24, 6, 0.61)}
    for r in runs.values():
        assert all(m["open_loop_landed"] for m in r["motions"]) and len(r["skipped_not_landing"]) == 4
        assert r["clone_landed"] == sum(m["clone_landed"] for m in r["motions"])
    assert runs["paper-size"]["hidden"] == 8 and runs["dagger-3"]["rounds"] == 3 and runs["64-hidden-clock"]["clock"]
    assert [m["entry"] for m in runs["paper-size"]["motions"]] == [m["entry"] for m in runs["dagger-3"]["motions"]]
    text = " ".join((root / "docs" / "landing.md").read_text().split())
    assert "| 12 of 24 | 0.69 rad/s |" in text and "| 14 of 24 |" in text and "| 6 of 24 | 0.61 rad/s |" in text
    assert "drop 12 times of 24" in " ".join((root / "README.md").read_text().split())


def test_clone_bench_evolves_one_motion_over_its_cap():
    r = subprocess.run([sys.executable, str(BENCH), "--n", "1", "--steps", "50", "--evolve", "1", "--popsize", "2",
                        "--train", "2", "--test", "2", "--late", "1", "--json"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    (m,) = res["motions"]
    p = m["patch"]
    assert (p["train"], p["test"], p["evolution_rollouts"]) == (2, 2, 2 + 2 * 2)
    assert all(0 <= p[k] <= 2 for k in p if k.endswith(("_train", "_test")) and k != "late_test")
    assert p["evolved_lands_own"] in (True, False) and len(p["best_after_generation"]) == 1
    assert res["evolution"]["generations"] == 1 and res["evolution"]["evolved_lands_test"] == p["evolved_lands_test"]
    assert list(p["late_test"]) == ["1"] and all(0 <= c <= 2 for c in p["late_test"]["1"].values())
    assert res["evolution"]["late_test"] == p["late_test"]
    for bad in (["--evolve", "-1"], ["--evolve", "2", "--clock"], ["--evolve", "2", "--patch", "0"],
                ["--evolve", "2", "--late", "-1"]):
        out = subprocess.run([sys.executable, str(BENCH), *bad], capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and "--evolve must be ≥ 0" in out.stderr, (bad, out.stderr)
