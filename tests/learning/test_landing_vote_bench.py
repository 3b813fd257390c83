"""`bench/landing_vote.py`: votes between landing policies by attitude, built and evaluated (docs/landing.md,
"Policies by attitude"), and the shipped votes' probes recounted."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).parents[2] / "bench" / "landing_vote.py"


def _bench():
    spec = importlib.util.spec_from_file_location("landing_vote", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_vote_is_built_on_training_seeds_and_runs_as_felis_eval_runs_it(tmp_path, capsys):
    """Built: each part's landings on each training seed's drops, σ the best of the grid left one seed out; evaluated
    on another seed: each part alone, the vote, which `felis eval landing --policy FILE` (the sequential path, one
    cat at a time) lands alike, and the paper's compose net fitted and evolved as the dispatcher (each of its drops
    lands as the part it chose); the evaluation kept in the file."""
    from felis.learning.landing.by_attitude import load_vote
    from felis.learning.landing.cap_policy import SHIPPED_CAPS
    from felis.learning.landing.evaluate import run_drops, run_drops_sequential
    from felis.scenarios.drop import random_drops

    shutil.copy(SHIPPED_CAPS, tmp_path / "caps.json")
    out = tmp_path / "vote.json"
    b = _bench()
    b.main(["--out", str(out), "--height", "1", "--parts", "caps.json", "library", "--train-seeds", "100", "101",
            "--drops", "random:6", "--sigmas", "3", "30"])
    d, v, parts = load_vote(out)
    assert parts == [str(tmp_path / "caps.json"), "library"] and d["height_m"] == 1.0 and len(v.probes) == 12
    cv = d["training"]["leave_one_seed_out"]
    assert set(cv) == {"3", "30"} and v.sigma_deg == float(max(cv, key=cv.get))
    drops = random_drops(6, seed=101, heights=1.0)
    for k, name in enumerate(parts):  # the probes are what each part lands
        assert [o.landed for o in run_drops(drops, name)] == [bool(x) for x in v.landed[6:, k]]
    capsys.readouterr()
    b.main(["--policy", str(out), "--seeds", "3", "--drops", "random:6", "--record", "check", "--json",
            "--compose", "4"])
    got = json.loads(capsys.readouterr().out)
    res = got["seeds"]["3"]
    assert set(res) == {"caps.json", "library", "vote", "compose_fitted", "compose_evolved"}
    assert sum(res["vote"]["chose"].values()) == 6
    drops = random_drops(6, seed=3, heights=1.0)
    alone = [[o.landed for o in run_drops(drops, name)] for name in parts]
    both, either = (sum(f(a, c) for a, c in zip(*alone, strict=True)) for f in (lambda a, c: a and c,
                                                                                   lambda a, c: a or c))
    for k in ("compose_fitted", "compose_evolved"):  # each drop lands as the part the compose net chose
        assert sum(res[k]["chose"].values()) == 6 and both <= res[k]["landed"] <= either
        assert 0 <= got["compose"]["training_landed"][k] <= 12
    seq = run_drops_sequential(drops, str(out), workers=1)
    assert sum(o.landed for o in seq) == res["vote"]["landed"] and sum(o.landed for o in run_drops(drops, str(out))) \
        == res["vote"]["landed"]
    assert json.loads(out.read_text())["evaluated"]["check"]["seeds"]["3"] == res
    with pytest.raises(SystemExit):
        b.main(["--out", str(out), "--compose", "4"])  # --compose evaluates a vote file


def test_bad_builds_are_one_line(tmp_path):
    b = _bench()
    with pytest.raises(SystemExit, match="name a caps file in"):
        b.main(["--out", str(tmp_path / "v.json"), "--parts", "library", "../x.json"])
    with pytest.raises(SystemExit, match="at least two policies"):
        b.main(["--out", str(tmp_path / "v.json"), "--parts", "library"])
    with pytest.raises(SystemExit):
        b.main(["--out", str(tmp_path / "v.json"), "--train-seeds", "100"])  # σ needs two seeds to leave one out
    assert not (tmp_path / "v.json").exists()


@pytest.mark.parametrize("which", [0, 1])
def test_the_shipped_votes_probes_are_what_their_parts_land(which):
    """The first 24 drops of each shipped vote's first training seed, run again with each part: the landings the file
    holds (the rollouts are deterministic on a machine; one drop on the edge may differ on another CPU)."""
    from felis.learning.landing.by_attitude import SHIPPED_VOTES, load_vote
    from felis.learning.landing.evaluate import run_drops
    from felis.scenarios.drop import drops_from

    d, v, parts = load_vote(SHIPPED_VOTES[which])
    drops = drops_from(d["training"]["drops"], d["training"]["seeds"][0], d["height_m"])[:24]
    for k, name in enumerate(parts):
        got = np.array([o.landed for o in run_drops(drops, name)])
        assert (got != v.landed[:24, k].astype(bool)).sum() <= 1, (name, got, v.landed[:24, k])


def _mean(xs) -> str:
    """A mean as the docs write it: exact to two decimals, else to one."""
    m = sum(xs) / len(xs)
    return f"{m:g}" if abs(m * 100 - round(m * 100)) < 1e-9 else f"{round(m, 1):g}"


def test_the_docs_tables_are_the_votes_recorded_evaluations():
    """docs/landing.md, "Policies by attitude": the evaluation table and the compose-net table are the evaluations
    the shipped vote files record (`--record seeds_0_7`, `--record compose_16`), seed by seed and on average; the
    vote's seed 0 and 1 figures are recounted through `felis eval landing` by the default's tests."""
    from felis.learning.landing.by_attitude import SHIPPED_VOTES

    doc = " ".join((BENCH.parents[1] / "docs" / "landing.md").read_text().split())
    cols = {}
    for path in SHIPPED_VOTES:
        d = json.loads(path.read_text())
        h = f"{d['height_m']:g} m"
        ev, comp = d["evaluated"]["seeds_0_7"], d["evaluated"]["compose_16"]
        assert ev["command"].endswith("--seeds 0 1 2 3 4 5 6 7 --record seeds_0_7")
        assert "--compose 16" in comp["command"]
        for name in [*d["parts"], "vote"]:  # the compose run runs the parts and the vote again: the same landings
            assert [comp["seeds"][s][name]["landed"] for s in comp["seeds"]] == \
                [ev["seeds"][s][name]["landed"] for s in ev["seeds"]]
        for name in ("vote", "compose_fitted", "compose_evolved"):
            xs = [comp["seeds"][str(s)][name]["landed"] for s in range(8)]
            cols.setdefault(name, []).append(", ".join(map(str, xs)) + f" ({_mean(xs)})")
        vote = [ev["seeds"][str(s)]["vote"]["landed"] for s in range(8)]
        label = "**1 m, the vote**" if h == "1 m" else "**3 m, the vote**"
        rest = ", ".join(map(str, vote[2:]))
        assert f"| {label} | **{vote[0]}** | **{vote[1]}** | {rest} | **{_mean(vote)}** |" in doc
    for name, label in (("compose_fitted", "compose net, fitted"),
                        ("compose_evolved", "compose net, evolved from random weights")):
        assert f"| {label} | {cols[name][0]} | {cols[name][1]} |" in doc, (label, cols[name])
    # the README's Unreleased entry quotes the same means
    readme = " ".join((BENCH.parents[1] / "README.md").read_text().split())
    mean = {k: [v.rsplit("(", 1)[1].rstrip(")") for v in vs] for k, vs in cols.items()}
    assert (f"fitted to the same drops it lands {mean['compose_fitted'][0]} and {mean['compose_fitted'][1]}, evolved "
            f"from random weights {mean['compose_evolved'][0]} and {mean['compose_evolved'][1]}") in readme
    assert f"({mean['vote'][0]} and {mean['vote'][1]} on average over seeds 0–7" in readme
