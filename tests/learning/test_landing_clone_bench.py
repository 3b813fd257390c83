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


def test_the_shipped_evolution_runs_are_what_the_docs_say():
    """docs/landing.md "Closed-loop behaviours: imitated, then evolved over their starts": every count of its table
    and readings recounted from `learning/weights/landing_clone_evolve-1m.json`."""
    root = BENCH.parents[1]
    runs = json.loads((root / "learning" / "weights" / "landing_clone_evolve-1m.json").read_text())["runs"]
    text = " ".join((root / "docs" / "landing.md").read_text().split())
    want = {"cap-15": (12, 16, 15.0, 1173), "cap-30": (8, 24, 30.0, 1518)}
    for name, r in runs.items():
        ps = [m["patch"] for m in r["motions"]]
        n, test, deg, secs = want[name]
        assert (len(ps), r["evolution"]["test"], r["evolution"]["patch_deg"], r["seconds"]) == (n, test, deg, secs)
        tot = {k: sum(p[f"{k}_lands_test"] for p in ps) for k in ("motion", "fitted", "evolved")}
        late = {k: [sum(p["late_test"][t][k] for p in ps) for t in ("1", "2")] for k in ("motion", "fitted", "evolved")}
        assert tot == {k: r["evolution"][f"{k}_lands_test"] for k in tot} and late["evolved"] == [
            r["evolution"]["late_test"][t]["evolved"] for t in ("1", "2")]
        row = (f"| cap of {deg:g}°: {n} motions × {test} starts")
        assert row in text and f"{secs:,}".replace(",", " ") + " s) | " + f"{tot['motion']} | {tot['fitted']} | " \
            f"**{tot['evolved']}** |" in text
        assert (f"| … started 1 / 2 ticks late | {late['motion'][0]} / {late['motion'][1]} | {late['fitted'][0]} / "
                f"{late['fitted'][1]} | **{late['evolved'][0]} / {late['evolved'][1]}** |") in text
        assert all(p["evolution_rollouts"] == r["motions"][0]["patch"]["evolution_rollouts"] for p in ps)
    p15, p30 = ([m["patch"] for m in runs[k]["motions"]] for k in ("cap-15", "cap-30"))

    def ahead(ps):
        return (sum(p["evolved_lands_test"] > p["motion_lands_test"] for p in ps),
                sum(p["evolved_lands_test"] < p["motion_lands_test"] for p in ps))

    assert ahead(p15) == (8, 3) and ahead(p30) == (5, 3)
    won = [p for p in p30 if p["evolved_lands_test"] > p["motion_lands_test"]]
    assert (min(p["evolved_lands_test"] for p in won), max(p["evolved_lands_test"] for p in won)) == (11, 21)
    assert (min(p["motion_lands_test"] for p in won), max(p["motion_lands_test"] for p in won)) == (1, 10)
    assert [p15[0]["evolution_rollouts"], p30[0]["evolution_rollouts"]] == [3848, 7696]
    assert sum(p["evolved_lands_train"] == 0 or p["evolved_lands_test"] == 0 for p in p30) == 3
    assert sum(p["evolved_lands_test"] == 0 for p in p15) == 2
    assert all(p["fitted_lands_train"] <= 2 for p in p30 if p["evolved_lands_test"] == 0)
    assert all(p["fitted_lands_train"] <= 2 for p in p15 if p["evolved_lands_test"] == 0)
    assert [sum(p["evolved_lands_own"] for p in ps) for ps in (p15, p30)] == [10, 5]
    assert [sum(m["clone_landed"] for m in runs[k]["motions"]) for k in ("cap-15", "cap-30")] == [4, 3]
    assert [len(runs[k]["skipped_not_landing"]) for k in runs] == [3, 3]
    for s in ("more held-out starts than its motion for 8 of the 12 motions and fewer for 3",
              "5 more and 3 fewer, and the 5 land 11–21 of their 24 starts where their motions land 1–10",
              "3 848 rollouts a motion (98 s)", "7 696 (190 s)", "land 62 and 23 of the held-out starts",
              "land 110 and 84", "3 of the 8 motions with 30° caps and 2 of the 12 with 15° caps",
              "10 of 12 motions with 15° caps and 5 of 8 with 30° caps", "The fitted behaviour lands 4 and 3"):
        assert s in text, s
    readme = " ".join((root / "README.md").read_text().split())
    kinds = ("motion", "fitted", "evolved")
    t15, t30 = ({k: sum(p[f"{k}_lands_test"] for p in ps) for k in kinds} for ps in (p15, p30))
    assert (f"within 15° of 12 motions the evolved behaviours land {t15['evolved']} of 192, the open-loop motions "
            f"{t15['motion']} and the fitted behaviours {t15['fitted']}. Within 30° of 8 motions they land "
            f"{t30['evolved']}, {t30['motion']} and {t30['fitted']}. Started 2 ticks late the motions land 62 and 23, "
            "the evolved behaviours 110 and 84.") in readme
