"""Landing policies by attitude (`felis.learning.landing.by_attitude`): the vote the default runs from 3 m."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing import by_attitude
from felis.learning.landing.library import up_axis


def _unit(*v):
    v = np.array(v, dtype=float)
    return v / np.linalg.norm(v)


A, B = _unit(0.0, 0.0, 1.0), _unit(0.0, 1.0, 0.0)  # upright; on its right side (u_y > 0)
# part 0 (the fallback) lands round B, part 1 round A; both land at C, neither at D
C, D = _unit(1.0, 0.0, 0.0), _unit(-1.0, 0.0, -1.0)
PROBES = np.array([A, _unit(0.05, 0.0, 1.0), B, _unit(0.05, 1.0, 0.0), C, D])
LANDED = np.array([[0, 1], [0, 1], [1, 0], [1, 0], [1, 1], [0, 0]])


def test_the_vote_takes_the_part_that_landed_most_near_the_attitude():
    """argmax_k Σ w l_k with a Gaussian of the angle; a start and its mirror image (u_y negated) vote alike; a tie
    (both landed, neither, or no probe within many σ) takes the first part, the fallback."""
    v = by_attitude.Vote(PROBES, LANDED, 10.0)
    u = np.array([_unit(0.1, 0.0, 1.0), _unit(0.1, 1.0, 0.1), _unit(0.1, -1.0, 0.1), C, D, _unit(0.0, 1.0, -1.0)])
    assert list(v.choose(u)) == [1, 0, 0, 0, 0, 0]
    assert list(v.choose(np.array([_unit(0.1, -0.2, 1.0)]))) == [1]  # mirrored into u_y ≥ 0, still near A
    # with a narrow σ a start 45° from A and from B has no probe near it: a tie, the fallback
    assert list(by_attitude.Vote(PROBES, LANDED, 2.0).choose(np.array([_unit(0.0, 1.0, 1.0)]))) == [0]
    # from the IT a cat senses: roll r, pitch p as the nets' inputs (r/π, p/(π/2))
    it = np.zeros((2, 15))
    it[:, 4] = np.array([0.05, 0.5])  # roll 9°: near upright; roll 90°: on its side
    assert list(v.choose_it(it)) == [1, 0]
    assert np.allclose(up_axis(0.5 * math.pi, 0.0), B, atol=1e-12)


class _Const:
    def __init__(self, c: float):
        self.c, self.seen = c, []

    def __call__(self, it, t, rows):
        self.seen.append(rows.copy())
        return np.full((len(it), 12), self.c)


def test_each_cat_keeps_the_part_voted_at_release():
    """At its first tick each cat takes its part and keeps it while it turns; each part sees only its own rows; the
    one-cat rule takes what the batch takes."""
    v = by_attitude.Vote(PROBES, LANDED, 10.0)
    fallback, other = _Const(0.0), _Const(1.0)
    pol = by_attitude.ByAttitude(v, [fallback, other])
    it = np.zeros((3, 15))
    it[:, 4] = [0.02, 0.5, -0.5]  # near upright, on its right side, on its left side
    rows = np.arange(3)
    assert list(pol(it, np.zeros(3), rows)[:, 0]) == [1.0, 0.0, 0.0]
    it[:, 4] = [0.5, 0.0, 0.0]  # turned since: each keeps its part
    assert list(pol(it, np.full(3, 0.2), rows)[:, 0]) == [1.0, 0.0, 0.0]
    assert [list(r) for r in other.seen] == [[0], [0]] and [list(r) for r in fallback.seen] == [[1, 2], [1, 2]]
    for roll, want in ((0.02, 1.0), (0.5, 0.0), (-0.5, 0.0)):
        rule = by_attitude.ByAttitudeRule(v, [lambda it, t: np.full(12, 0.0), lambda it, t: np.full(12, 1.0)])
        x = np.zeros(15)
        x[4] = roll
        assert rule(x, 0.0)[0] == want
        x[4] = 0.5 - roll
        assert rule(x, 0.3)[0] == want


@pytest.mark.parametrize("probes, landed, sigma, says", [
    (PROBES, LANDED[:, :1], 10.0, "at least 2 parts"),
    (PROBES[:3], LANDED, 10.0, "3 probes with landings of shape"),
    (PROBES * 2, LANDED, 10.0, "not a unit vector"),
    (PROBES, LANDED * 2, 10.0, "not 0 or 1"),
    (PROBES, LANDED, 0.0, "sigma_deg must be in"),
    (PROBES, LANDED, float("nan"), "sigma_deg must be in"),
])
def test_bad_votes_are_one_line(probes, landed, sigma, says):
    with pytest.raises(ParameterError, match=says):
        by_attitude.Vote(probes, landed, sigma)
    v = by_attitude.Vote(PROBES, LANDED, 10.0)
    with pytest.raises(ParameterError, match="2 parts voted on, 3"):
        by_attitude.ByAttitude(v, [_Const(0.0)] * 3)


def _doc(**kw):
    d = {"format": by_attitude.FORMAT, "version": 1, "height_m": 3.0, "parts": ["library", "caps.json"],
         "sigma_deg": 10.0, "probes": {"up": PROBES.tolist(), "landed": LANDED.tolist()}}
    d.update(kw)
    return d


@pytest.mark.parametrize("doc, says", [
    ("not json", "Expecting value"),
    (json.dumps({"format": "felis-landing-caps"}), "not a felis-landing-vote file"),
    (json.dumps(_doc(parts=["library", "../caps.json"])), "neither 'library' nor a file beside it"),
    (json.dumps(_doc(parts=["library", "missing.json"])), "neither 'library' nor a file beside it"),
    (json.dumps(_doc(parts=["library", "caps.json", "library"])), "3 parts named, landings for 2"),
    (json.dumps(_doc(height_m=-3)), "height_m must be a positive number"),
    (json.dumps(_doc(sigma_deg="wide")), "sigma_deg must be in"),
    (json.dumps(_doc(probes={"up": PROBES.tolist()})), "'landed'"),
])
def test_bad_vote_files_are_one_line_naming_the_file(tmp_path, doc, says):
    (tmp_path / "caps.json").write_text("{}")
    f = tmp_path / "vote.json"
    f.write_text(doc)
    with pytest.raises(ParameterError, match=says) as e:
        by_attitude.load_vote(f)
    assert str(f) in str(e.value) and "\n" not in str(e.value)
    f.write_text(json.dumps(_doc()))
    d, v, parts = by_attitude.load_vote(f)
    assert parts == ["library", str(tmp_path / "caps.json")] and v.parts == 2 and d["height_m"] == 3.0


def test_the_shipped_votes_are_the_defaults_parts():
    """The shipped votes are what ``caps+library`` runs, in a batch and for one cat: from 1 m the cap policy first,
    then the library; from 3 m the library first, then the 3 m cap policy. Each σ was chosen on the file's training
    seeds, none of which an evaluation uses; without the votes the default is the cap policy and the library."""
    from felis.learning.landing.by_height import ByHeight, ByHeightRule, caps_library_batch, caps_library_rule
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, CapPolicy, CapRule
    from felis.learning.landing.library import LibraryBatch, LibraryRule, load_library

    one, three = by_attitude.SHIPPED_VOTES
    for path, height, parts in ((one, 1.0, ["landing_caps48-1m.json", "library"]),
                                (three, 3.0, ["library", "landing_caps48-3m.json"])):
        d, v, _ = by_attitude.load_vote(path)
        assert d["height_m"] == height and d["parts"] == parts
        assert not set(d["training"]["seeds"]) & set(range(13))  # the evaluations' seeds are 0–7 and 10–12
        cv = d["training"]["leave_one_seed_out"]
        assert v.sigma_deg == float(max(cv, key=cv.get)) and len(v.probes) == d["training"]["total"]
    lib = load_library()
    b = caps_library_batch(SHIPPED_CAPS, lib, [3.0], 400, 10.0)
    assert isinstance(b, ByHeight) and all(isinstance(p, by_attitude.ByAttitude) for p in b.policies)
    assert [[type(x) for x in p.policies] for p in b.policies] == [[CapPolicy, LibraryBatch], [LibraryBatch, CapPolicy]]
    assert b.policies[0].policies[1] is b.policies[1].policies[0]  # one library batch
    r = caps_library_rule(SHIPPED_CAPS, lib, 3.0)
    assert isinstance(r, ByHeightRule)
    assert [[type(x) for x in p.rules] for p in r.rules] == [[CapRule, LibraryRule], [LibraryRule, CapRule]]
    b0 = caps_library_batch(SHIPPED_CAPS, lib, [3.0], 400, 10.0, votes=())
    assert [type(p) for p in b0.policies] == [CapPolicy, LibraryBatch]
