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
    on another seed: each part alone and the vote, which `felis eval landing --policy FILE` (the sequential path, one
    cat at a time) lands alike, drop for drop; the evaluation kept in the file."""
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
    b.main(["--policy", str(out), "--seeds", "3", "--drops", "random:6", "--record", "check", "--json"])
    res = json.loads(capsys.readouterr().out)["seeds"]["3"]
    assert set(res) == {"caps.json", "library", "vote"} and sum(res["vote"]["chose"].values()) == 6
    drops = random_drops(6, seed=3, heights=1.0)
    seq = run_drops_sequential(drops, str(out), workers=1)
    assert sum(o.landed for o in seq) == res["vote"]["landed"] and sum(o.landed for o in run_drops(drops, str(out))) \
        == res["vote"]["landed"]
    assert json.loads(out.read_text())["evaluated"]["check"]["seeds"]["3"] == res


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
