"""The landing motion library (`felis.learning.landing.library`, `library_build`): the attitude the IMU gives,
mirror images that land as their originals, the probes' vote, files read back and refused in one line, batched
equal to sequential, a build that resumes to the same library, and the CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from felis.errors import ParameterError
from felis.learning.landing.library import (
    DEFAULT_LIBRARY,
    MotionLibrary,
    Shelf,
    drop_up,
    is_library_file,
    library_from_dict,
    load_library,
    mirror_motion,
    mirror_up,
    up_axis,
)
from felis.learning.landing.motion import DIMS, N_WAYPOINTS
from felis.rotations import roll_pitch
from felis.scenarios.drop import Drop, random_drops


def _felis(*argv: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "felis", *argv], capture_output=True, text=True, timeout=timeout)


def test_the_up_axis_is_what_the_imu_roll_and_pitch_give_and_ignores_yaw():
    for d in random_drops(50, seed=4):
        R = Rotation.from_euler("ZYX", [d.yaw_deg, d.pitch_deg, d.roll_deg], degrees=True)
        want = R.inv().apply([0.0, 0.0, 1.0])
        x, y, z, w = R.as_quat()
        roll, pitch = roll_pitch((w, x, y, z))
        assert np.allclose(up_axis(roll, pitch), want, atol=1e-12)
        assert np.allclose(drop_up(d), want, atol=1e-12)
        assert np.allclose(drop_up(Drop(d.roll_deg, d.pitch_deg, d.yaw_deg + 77.0, d.height_m)), want, atol=1e-12)


def test_mirroring_flips_the_yaw_and_roll_angles_and_is_its_own_inverse():
    x = np.random.default_rng(0).uniform(-1, 1, DIMS)
    m = mirror_motion(x)
    w, mw = x[:N_WAYPOINTS * 8].reshape(-1, 8), m[:N_WAYPOINTS * 8].reshape(-1, 8)
    assert np.array_equal(mw[:, [0, 2, 4, 6]], w[:, [0, 2, 4, 6]]) and np.array_equal(mw[:, [1, 3, 5, 7]],
                                                                                        -w[:, [1, 3, 5, 7]])
    n = N_WAYPOINTS * 8
    assert m[n] == x[n] and m[n + 2] == -x[n + 2] and m[n + 5] == -x[n + 5] and m[n + 3] == x[n + 3]
    assert np.array_equal(mirror_motion(m), x)
    assert np.array_equal(mirror_motion(np.stack([x, x]))[1], m)


def test_a_mirrored_drop_with_the_mirrored_motion_lands_as_the_original():
    """The cat is left-right symmetric: the shipped optimum's first landed 1 m drop and its mirror image."""
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.optimum import evaluate

    doc = json.loads((DEFAULT_LIBRARY.parent / "landing_optimum_4ms-paw-1m.json").read_text())
    e = next(e for e in doc["drops"] if e["landed"] and abs(e["roll_deg"]) > 10)
    d = Drop(e["roll_deg"], e["pitch_deg"], e["yaw_deg"], e["height_m"])
    md = Drop(-d.roll_deg, d.pitch_deg, -d.yaw_deg, d.height_m)
    assert np.allclose(drop_up(md), mirror_up(drop_up(d)))
    sim = BatchLandingSim(nthread=1)
    try:
        (s0, v0), (s1, v1) = evaluate(sim, [d, md], np.array([e["motion_x"], mirror_motion(e["motion_x"])]))
    finally:
        sim.close()
    assert v0.landed and v1.landed
    assert abs(v0.tilt_deg - v1.tilt_deg) < 0.5 and abs(s0 - s1) < 0.01


def _unit(deg_from_up: float, toward_y: float = 1.0) -> np.ndarray:
    a = math.radians(deg_from_up)
    return np.array([0.0, toward_y * math.sin(a), math.cos(a)])


def _shelf(landed=(True, True), votes=True) -> Shelf:
    x = np.random.default_rng(1).uniform(-1, 1, (2, DIMS))
    probes = np.array([_unit(a) for a in (12.0, 13.0, 14.0)])
    lands = np.zeros((3, 4), dtype=bool)
    if votes:
        lands[:, 0] = True  # entry 0 (at 10°) lands every probe; entry 1 (at 14°) none
    return Shelf(1.0, np.array([_unit(10.0), _unit(14.0)]), x, np.array(landed), probes, lands)


def test_the_probes_vote_for_the_motion_that_lands_near_the_attitude_not_the_nearest_one():
    s = _shelf()
    x, c = s.choose(_unit(13.5))
    assert c == 0 and np.array_equal(x, s.x[0])  # the nearest entry is 1 (at 14°), but 0 lands the probes
    x, c = s.choose(_unit(13.5, -1.0))  # the mirror image of that attitude: the mirror image of that motion
    assert c == 1 and np.array_equal(x, mirror_motion(s.x[0]))  # candidate 1: entry 0's mirror image
    x, c = s.choose(_unit(13.5), radius_deg=0.1)  # no probe near: the nearest entry that landed
    assert c == 2 and np.array_equal(x, s.x[1])
    x, c = _shelf(landed=(True, False)).choose(_unit(13.5), radius_deg=0.1)
    assert c == 0
    x, c = _shelf(votes=False).choose(_unit(13.9))
    assert c == 2


def test_the_fill_targets_holes_first_then_the_probes_whose_neighbours_vote_for_a_motion_that_fails_there():
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.library_build import fill, fill_targets

    s = _shelf()
    s.probe_up = np.array([_unit(a) for a in (11.0, 12.0, 13.0, 14.0, 15.0, 40.0)])  # 40°: nothing lands it
    s.lands = np.zeros((6, 4), dtype=bool)
    s.lands[[0, 1, 3, 4], 2] = True  # entry 1 (at 14°) lands the probes at 11, 12, 14 and 15°
    s.lands[2, 0] = True  # only entry 0 (at 10°) lands the one at 13°: its neighbours vote for entry 1, which fails
    assert fill_targets(s, 1).tolist() == [5] and fill_targets(s, 2).tolist() == [2]
    from felis.learning.landing.library_build import misses

    assert misses(s, among=np.array([0, 1, 2, 5])).tolist() == [2] and misses(s, among=np.array([3, 4])).size == 0
    assert misses(s, sigma_deg=0.3).tolist() == [2]  # a narrow vote too: its neighbours both point to entry 1
    sim = BatchLandingSim(nthread=1)
    try:  # no generations: the start, the nearest candidate that lands the probe (entry 0, not the nearer entry 1)
        x, n, c = fill(sim, s, np.array([2, 5]), generations=0)  # or, for a hole, the nearest (entry 1)
    finally:
        sim.close()
    assert np.array_equal(x[0], s.x[0]) and np.array_equal(x[1], s.x[1]) and n.shape == c.shape == (2,)
    s.lands[:, 2] = False  # now entry 1 lands nothing (nor its own drop), entry 0 the probe at 13°: a hole at 40°
    s.landed = np.array([True, False])  # starts from entry 0, which works, not from the nearer entry 1
    sim = BatchLandingSim(nthread=1)
    try:
        x, _, _ = fill(sim, s, np.array([5]), generations=0)
    finally:
        sim.close()
    assert np.array_equal(x[0], s.x[0])


def test_a_library_reads_back_as_written_and_picks_the_nearer_height():
    lib = MotionLibrary([_shelf(), Shelf(3.0, *[getattr(_shelf(), k) for k in ("up", "x", "landed", "probe_up",
                                                                                "lands")])], meta={"made_by": "t"})
    back = library_from_dict(json.loads(json.dumps(lib.as_dict())))
    for a, b in zip(lib.shelves, back.shelves, strict=True):
        assert a.height_m == b.height_m and np.array_equal(a.lands, b.lands) and np.array_equal(a.landed, b.landed)
        assert np.allclose(a.up, b.up, atol=1e-6) and np.array_equal(a.x, b.x)
    assert back.shelf(1.2).height_m == 1.0 and back.shelf(2.0).height_m == 3.0 and back.shelf(8).height_m == 3.0


def test_a_library_read_again_is_a_copy_and_a_changed_file_is_read_anew(tmp_path):
    """`load_library` keeps the files it has read (a command reads one 2-3 times): each call gets its own copy, and
    a file written since is parsed again."""
    path = tmp_path / "lib.json"
    path.write_text(json.dumps(MotionLibrary([_shelf()]).as_dict()))
    a = load_library(path)
    a.shelves[0].landed[:] = ~a.shelves[0].landed
    a.shelves[0].x[0, 0] = 99.0
    b = load_library(path)
    assert np.array_equal(b.shelves[0].landed, _shelf().landed) and b.shelves[0].x[0, 0] == _shelf().x[0, 0]
    path.write_text(json.dumps(MotionLibrary([_shelf(), Shelf(3.0, *[getattr(_shelf(), k) for k in (
        "up", "x", "landed", "probe_up", "lands")])]).as_dict()) + " ")  # another size: another file
    assert [s.height_m for s in load_library(path).shelves] == [1.0, 3.0]


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(format="x"), "not a landing motion library"),
    (lambda d: d.update(version=9), "library version 9 is not supported"),
    (lambda d: d.update(shelves=[]), "'shelves' must be a non-empty list"),
    (lambda d: d["shelves"][0].update(height_m=-1), "shelf 0: height_m must be a positive number"),
    (lambda d: d["shelves"][0]["entries"][1].update(motion_x=[0.0] * 3), "shelf 0, entry 1: motion_x must be 55"),
    (lambda d: d["shelves"][0]["entries"][0].update(up=[0.0, 0.0, 2.0]), "every 'up' must be a unit vector"),
    (lambda d: d["shelves"][0]["probes"][2].update(lands=[7]), "shelf 0, probe 2: lands must be candidate ids 0…3"),
    (lambda d: d["shelves"][0]["probes"][1].update(lands=[True]), "shelf 0, probe 1: lands must be candidate ids"),
    (lambda d: d["shelves"][0]["probes"][0].update(up=[0.0, "z", 1.0]), "shelf 0, probe 0: up must be numbers"),
    (lambda d: d["shelves"][0]["entries"][1].update(up=[0.0, float("nan"), 1.0]), "entry 1: up must be 3 finite"),
    (lambda d: d.update(sigma_deg=0), "radius_deg and sigma_deg must be positive"),
])
def test_bad_library_files_are_one_line_naming_the_file(tmp_path, edit, message):
    doc = MotionLibrary([_shelf()]).as_dict()
    edit(doc)
    path = tmp_path / "lib.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ParameterError, match=message) as e:
        load_library(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)
    path.write_text("{")
    with pytest.raises(ParameterError, match="lib.json"):
        load_library(path)


def _two_shelves() -> MotionLibrary:
    return MotionLibrary([_shelf(), Shelf(3.0, *[getattr(_shelf(), k) for k in ("up", "x", "landed", "probe_up",
                                                                                "lands")])], meta={"made_by": "t"})


def test_a_votes_file_gives_its_library_other_votes_on_the_shelves_it_lists_and_keeps_the_rest(tmp_path):
    """A votes file (`bench/landing_revote.py`'s output) names its library by path and SHA-256: loaded, it is that
    library with the listed shelves' lands replaced; a votes file written elsewhere names it relative to itself."""
    from felis.learning.landing.library import votes_dict

    base = tmp_path / "lib.json"
    base.write_text(json.dumps(_two_shelves().as_dict()))
    voted = load_library(base)
    voted.shelf(3.0).lands[:] = False
    voted.shelf(3.0).lands[1, 3] = True  # the 14° entry's mirror image lands probe 1 there; nothing else
    (tmp_path / "v").mkdir()
    out = tmp_path / "v" / "votes.json"
    out.write_text(json.dumps(votes_dict(voted, base, out, [3.0], {"revoted": {"3m": {"design": "d"}}})))
    doc = json.loads(out.read_text())
    assert doc["votes_of"]["file"] == "../lib.json" and [s["height_m"] for s in doc["shelves"]] == [3.0]
    back = load_library(out)
    assert np.array_equal(back.shelf(3.0).lands, voted.shelf(3.0).lands)
    assert np.array_equal(back.shelf(1.0).lands, _shelf().lands)  # not listed: the library's own vote
    assert back.shelf(3.0).choose(_unit(13.0))[1] == 3 and back.shelf(1.0).choose(_unit(13.0))[1] == 0
    assert np.array_equal(back.shelf(3.0).x, _shelf().x) and back.meta["revoted"] == {"3m": {"design": "d"}}
    assert is_library_file(out)


@pytest.mark.parametrize("edit, message", [
    (lambda d, b: b.write_text(b.read_text() + " "), "has changed since"),
    (lambda d, b: b.unlink(), "no such library file"),
    (lambda d, b: d["votes_of"].pop("sha256"), "'votes_of' must hold the library's 'file' and its 'sha256'"),
    (lambda d, b: d["shelves"][0].update(height_m=2.0), "shelf 0: lib.json has no shelf of height 2.0 m"),
    (lambda d, b: d["shelves"][0]["lands"].pop(), "'lands' must be one list per probe \\(3\\)"),
    (lambda d, b: d["shelves"][0]["lands"][2].append(4), "probe 2: lands must be candidate ids 0…3"),
])
def test_bad_votes_files_are_one_line_naming_the_file(tmp_path, edit, message):
    from felis.learning.landing.library import votes_dict

    base, out = tmp_path / "lib.json", tmp_path / "votes.json"
    base.write_text(json.dumps(_two_shelves().as_dict()))
    doc = votes_dict(load_library(base), base, out, [1.0])
    edit(doc, base)
    out.write_text(json.dumps(doc))
    with pytest.raises(ParameterError, match=message) as e:
        load_library(out)
    assert str(out) in str(e.value) and "\n" not in str(e.value)


def test_the_shipped_library_batched_equals_sequential():
    """The same drops through `felis.loop` one at a time (`LibraryRule` in the landing controller) and batched
    (`LibraryBatch`): the same verdicts, the same motion chosen from the IMU."""
    from felis.learning.landing.evaluate import run_drops, run_drops_sequential

    drops = [*random_drops(3, seed=1, heights=1.0), Drop(30.0, -20.0, 45.0, 3.0)]
    a = run_drops(drops, "library", workers=1)
    b = run_drops_sequential(drops, "library", workers=1)
    for x, y in zip(a, b, strict=True):
        assert x.landed == y.landed and x.why == y.why
        assert abs(x.touchdown_s - y.touchdown_s) < 1e-9 and abs(x.tilt_deg - y.tilt_deg) < 1e-3


def test_robustify_judges_each_entry_on_its_own_attitudes_when_others_are_done():
    """Entry 0 of the shipped 1 m shelf lands its attitude and four 6° round it already, so it leaves the search
    at once; entries 6 and 10 do not. Whatever robustify returns for each must land as many of that entry's own
    five drops (and its centre) as it says. (It once judged the entries still searching on the drops of the
    first ones by position, so a twin's verdict belonged to another attitude.)"""
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.library_build import neighbours, robustify, up_drop
    from felis.learning.landing.optimum import evaluate

    shelf = load_library().shelf(1.0)
    rows = [0, 6, 10]
    sim = design_sim("4ms-paw", nthread=1)  # the cat the shelf was searched on
    try:
        x, n, centre = robustify(sim, shelf.up[rows], shelf.x[rows], 1.0, generations=2, population=4)
        drops = [up_drop(v, 1.0) for r in rows for v in neighbours(shelf.up[r], 6.0)]
        landed = np.array([v.landed for _, v in evaluate(sim, drops, np.repeat(x, 5, axis=0))]).reshape(3, 5)
    finally:
        sim.close()
    assert n[0] == 5 and n[1] < 5  # entry 0 done at once, entry 6 still searching after it
    assert landed.sum(axis=1).tolist() == n.tolist()
    assert landed[:, 0].tolist() == centre.tolist()


def test_a_build_resumed_from_its_checkpoints_equals_one_run(tmp_path):
    from felis.learning.landing.library_build import build_library, fibonacci_ups

    # on the 4 ms-paw cat (its 1 ms step: half the physics of the described cat's, the same machinery)
    kw = dict(heights=(1.0,), grid=20, probes=36, max_tilt_deg=60.0, generations=1, population=2, restarts=0,
              workers=1, robust_generations=1, fill_generations=1, design="4ms-paw")
    assert len(fibonacci_ups(20, 60.0)) >= 2
    one = build_library(**kw, workdir=tmp_path / "a")
    where = tmp_path / "a" / "1m"
    assert {p.name for p in where.iterdir()} == {"optimum.jsonl", "robust.npz", "probes.npy", "fill.npz",
                                                "fill2.npz"}
    with np.load(where / "fill.npz") as f:
        assert len(f["holes"]) > 0  # so the fill stage ran on something
    res = np.load(where / "probes.npy")  # (probes, candidates): 1 lands, 0 does not, -1 not tried (too far apart)
    tried = np.argwhere(res >= 0)
    assert len(tried) > 8 and res.shape[1] > 2 * len(fibonacci_ups(20, 60.0))  # the fills' columns too
    res[tuple(tried[len(tried) // 2:].T)] = -1  # as if killed halfway through the probes
    np.save(where / "probes.npy", res)
    again = build_library(**kw, workdir=tmp_path / "a", resume=True)
    s, t = one.shelves[0], again.shelves[0]
    assert np.array_equal(s.x, t.x) and np.array_equal(s.lands, t.lands) and np.array_equal(s.landed, t.landed)
    assert s.lands.shape == (len(fibonacci_ups(36, 60.0)), 2 * len(s.up))
    assert len(s.up) > len(fibonacci_ups(20, 60.0))  # twins or fills beside the grid's entries
    fresh = build_library(**kw)  # no checkpoints at all: the same library
    assert np.array_equal(fresh.shelves[0].x, s.x) and np.array_equal(fresh.shelves[0].lands, s.lands)
    assert one.meta["design"] == "4ms-paw"


def test_cli_builds_a_library_that_eval_runs(tmp_path):
    out = tmp_path / "lib.json"
    r = _felis("train", "landing-library", "--out", str(out), "--heights", "1", "--grid", "12", "--probes", "20",
               "--max-tilt", "60", "--generations", "1", "--population", "2", "--restarts", "0", "--workers", "1",
               "--fill-generations", "1", "--design", "4ms-paw")
    assert r.returncode == 0, r.stderr
    assert f"library: {out}" in r.stdout and "1 m:" in r.stdout
    doc = json.loads(out.read_text())
    assert doc["made_by"].startswith("felis train landing-library") and doc["design"] == "4ms-paw"
    r = _felis("eval", "landing", "--drops", "random:2", "--policy", str(out), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["total"] == 2
    r = _felis("train", "landing-library", "--out", str(tmp_path / "x.npz"))
    assert r.returncode != 0 and "must end in .json" in r.stderr


def _without_far_entries(lib: MotionLibrary, max_tilt_deg: float, probe_every: int = 1) -> MotionLibrary:
    """``lib`` without the entries tilted beyond ``max_tilt_deg`` (those `--add` puts there), every ``probe_every``-th
    probe kept (fewer probes: fewer rollouts for `--add`)."""
    shelves = [_shelf_with(s, np.flatnonzero(np.degrees(np.arccos(np.clip(s.up[:, 2], -1, 1))) <= max_tilt_deg + 0.5),
                           np.arange(0, len(s.probe_up), probe_every), sigma_deg=None) for s in lib.shelves]
    return MotionLibrary(shelves, lib.radius_deg, lib.sigma_deg, meta={"made_by": "test"})


def _shelf_with(s: Shelf, rows, probes=None, *, sigma_deg: float | None) -> Shelf:
    """Shelf ``s`` with only its entries ``rows`` (and probes ``probes``; default all), their verdicts kept."""
    rows = np.asarray(rows)
    probes = np.arange(len(s.probe_up)) if probes is None else np.asarray(probes)
    cols = np.stack([2 * rows, 2 * rows + 1], axis=1).ravel()
    return Shelf(s.height_m, s.up[rows], s.x[rows], s.landed[rows], s.probe_up[probes], s.lands[np.ix_(probes, cols)],
                 None if s.drops is None else [s.drops[i] for i in rows], sigma_deg)


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_add_puts_a_hard_drop_motion_on_its_shelf_and_the_library_then_lands_that_drop(tmp_path):
    """`felis train landing-library --add`: the motion the optimum found for (120, 0, 0) from 3 m joins the 3 m
    shelf; the library, which landed nothing tilted beyond 100° before, now lands that drop (the same policy as
    every other start); any other start gets the new motion or what the base chose."""
    from felis.learning.landing.motion import load_motion

    hard = DEFAULT_LIBRARY.parent / "landing_hard_drop.json"
    base = _without_far_entries(load_library(), 100.0, probe_every=16)  # 1 probe in 16: 16× fewer rollouts
    base_path = tmp_path / "base.json"
    base_path.write_text(json.dumps(base.as_dict()))
    drops = tmp_path / "hard.json"
    drops.write_text(json.dumps([{"roll_deg": 120, "pitch_deg": 0, "yaw_deg": 0, "height_m": 3.0}]))
    r = _felis("eval", "landing", "--drops", str(drops), "--policy", str(base_path), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["landed"] == 0  # what the library did before
    out = tmp_path / "ext.json"
    r = _felis("train", "landing-library", "--add", str(hard), "--base", str(base_path), "--out", str(out),
               "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "landing_hard_drop.json: 3 m shelf, drop (120, 0, 0) lands its own attitude" in r.stdout
    ext = load_library(out)
    s0, s1 = base.shelf(3.0), ext.shelf(3.0)
    assert len(s1.up) == len(s0.up) + 1 and np.array_equal(s1.lands[:, :-2], s0.lands)
    assert np.allclose(s1.x[-1], load_motion(hard)[0].x) and s1.landed[-1]
    doc = json.loads(out.read_text())
    assert doc["added"][-1]["motion"] == "landing_hard_drop.json" and doc["extended_by"][-1].startswith(
        "felis train landing-library --add")
    assert len(ext.shelf(1.0).up) == len(base.shelf(1.0).up)
    r = _felis("eval", "landing", "--drops", str(drops), "--policy", str(out), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["landed"] == 1
    new = {2 * len(s0.up), 2 * len(s0.up) + 1}
    for u in (drop_up(d) for d in random_drops(100, seed=5, heights=3.0)):  # the new motion, or the same choice
        assert s1.choose(u)[1] in {s0.choose(u)[1]} | new


def test_add_refuses_a_motion_for_another_height_or_without_its_drop_in_one_line(tmp_path):
    hard = json.loads((DEFAULT_LIBRARY.parent / "landing_hard_drop.json").read_text())
    two = tmp_path / "two.json"
    two.write_text(json.dumps({**hard, "height_m": 2.0, "drop": {**hard["drop"], "height_m": 2.0}}))
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({k: v for k, v in hard.items() if k != "drop"}))
    for path, words in ((two, "a motion for a 2 m drop; the library has shelves at 1, 3 m only"),
                        (bare, "without its 'drop' cannot join a library")):
        r = _felis("train", "landing-library", "--add", str(path), "--out", str(tmp_path / "o.json"))
        assert r.returncode != 0 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "o.json").exists()


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_a_search_with_base_rebuilds_its_heights_shelves_and_keeps_the_others(tmp_path):
    """`felis train landing-library --base LIB --heights 3 …`: the 3 m shelf is the new search's, the 1 m shelf
    and the vote are LIB's; the records of what was added to the old 3 m shelf go with it, the rebuild is
    recorded; eval runs the result. A bad --base is one line before any search."""
    from felis.learning.landing.library_build import fibonacci_ups

    out = tmp_path / "re.json"
    r = _felis("train", "landing-library", "--base", str(DEFAULT_LIBRARY), "--heights", "3", "--grid", "12",
               "--probes", "20", "--max-tilt", "60", "--generations", "1", "--population", "2", "--restarts", "0",
               "--fill-generations", "1", "--fill-rounds", "1", "--workers", "2", "--out", str(out),
               "--workdir", str(tmp_path / "ck"))
    assert r.returncode == 0, r.stderr
    assert f"1 m: kept from {DEFAULT_LIBRARY}" in r.stdout and "3 m: " in r.stdout
    base, new = load_library(), load_library(out)
    assert new.heights == [1.0, 3.0] and (new.radius_deg, new.sigma_deg) == (base.radius_deg, base.sigma_deg)
    b1, n1 = base.shelf(1.0), new.shelf(1.0)
    assert np.array_equal(b1.x, n1.x) and np.array_equal(b1.lands, n1.lands) and np.array_equal(b1.probe_up,
                                                                                                 n1.probe_up)
    n3 = new.shelf(3.0)
    assert len(n3.probe_up) == len(fibonacci_ups(20, 60.0)) and n3.sigma_deg is None
    assert len(n3.up) >= len(fibonacci_ups(12, 60.0)) and n3.lands.shape == (len(n3.probe_up), 2 * len(n3.up))
    doc = json.loads(out.read_text())
    assert doc["made_by"] == base.meta["made_by"] and doc["extended_by"][-1].startswith(
        "felis train landing-library --base")
    assert doc["rebuilt"] == [{"heights": [3.0], "grid": {"sphere_points": 12, "probe_points": 20,
                                                          "max_tilt_deg": 60.0}, "search": doc["rebuilt"][0]["search"]}]
    assert doc["rebuilt"][0]["search"]["generations"] == 1
    assert all(a["height_m"] != 3.0 for a in doc.get("added", []) + doc.get("probes_added", []))
    r = _felis("eval", "landing", "--drops", "random:2", "--height", "3", "--policy", str(out), "--json")
    assert r.returncode == 0, r.stderr
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    r = _felis("train", "landing-library", "--base", str(bad), "--heights", "3", "--out", str(tmp_path / "o.json"))
    assert r.returncode != 0 and str(bad) in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "o.json").exists() and not (tmp_path / "o.ckpt").exists()


def test_a_shelf_with_its_own_narrow_sigma_follows_its_nearest_probes_and_keeps_it_in_the_file():
    """Probe 14.0° is landed by entry B only, probes 17.5–18.5° by entry A only; at 14.2° a wide vote (σ 6°) sums
    A's three farther probes, a narrow one (the shelf's σ 1°, as `--add-probes --sigma` writes) follows the nearest."""
    x = np.random.default_rng(2).uniform(-1, 1, (2, DIMS))
    probes = np.array([_unit(a) for a in (14.0, 17.5, 18.0, 18.5)])
    lands = np.zeros((4, 4), dtype=bool)
    lands[0, 2] = True  # entry B (candidate 2)
    lands[1:, 0] = True  # entry A (candidate 0)
    shelf = Shelf(3.0, np.array([_unit(10.0), _unit(20.0)]), x, np.array([True, True]), probes, lands)
    wide = MotionLibrary([shelf], sigma_deg=6.0)
    assert np.array_equal(wide.choose(_unit(14.2), 3.0), x[0])
    narrow = MotionLibrary([Shelf(**{**shelf.__dict__, "sigma_deg": 1.0})], sigma_deg=6.0)
    assert np.array_equal(narrow.choose(_unit(14.2), 3.0), x[1])
    doc = json.loads(json.dumps(narrow.as_dict()))
    assert doc["shelves"][0]["sigma_deg"] == 1.0 and doc["sigma_deg"] == 6.0
    back = library_from_dict(doc)
    assert back.shelves[0].sigma_deg == 1.0 and np.array_equal(back.choose(_unit(14.2), 3.0), x[1])
    for bad in (0, -1, "2", True, float("nan")):
        doc["shelves"][0]["sigma_deg"] = bad
        with pytest.raises(ParameterError, match="shelf 0: sigma_deg must be a positive number"):
            library_from_dict(doc)


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_join_puts_another_librarys_motions_on_the_shelf_with_their_verdicts_and_refuses_other_probes(tmp_path):
    """`felis train landing-library --join OTHER --heights 3`: OTHER's 3 m entries not already there are appended
    with their verdicts on the (same) probes, so the vote can pick them; the 1 m shelf and the vote are kept; a
    shelf with other probes, or --join with --add, is one line."""
    base = load_library()
    b3 = base.shelf(3.0)
    x_new = b3.x[5] + 0.01
    lands = np.zeros((len(b3.probe_up), 4), dtype=bool)
    p = int(np.flatnonzero(~b3.lands.any(axis=1))[0])  # a probe no motion of the base lands
    lands[p, 2] = True  # the new motion lands it
    other = MotionLibrary([Shelf(3.0, b3.up[[5, 5]], np.stack([b3.x[5], x_new]), np.array([True, True]),
                                 b3.probe_up, lands)], meta={"made_by": "test other"})
    other_path, out = tmp_path / "other.json", tmp_path / "joined.json"
    other_path.write_text(json.dumps(other.as_dict()))
    r = _felis("train", "landing-library", "--join", str(other_path), "--heights", "3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"3 m: 1 entries joined from {other_path}, {len(b3.up) + 1} in all" in r.stdout
    r = _felis("train", "landing-library", "--join", str(other_path), "--heights", "3", "--sigma", "0.8", "--out",
               str(tmp_path / "narrow.json"))
    assert r.returncode == 0 and r.stdout.splitlines()[0].endswith("; vote σ 0.8°"), r.stderr
    narrow = load_library(tmp_path / "narrow.json")
    assert narrow.shelf(3.0).sigma_deg == 0.8 and narrow.shelf(1.0).sigma_deg == base.shelf(1.0).sigma_deg
    j = load_library(out)
    j3 = j.shelf(3.0)
    assert np.array_equal(j3.x[:-1], b3.x) and np.allclose(j3.x[-1], x_new)  # the duplicate of entry 5 skipped
    assert np.array_equal(j3.lands[:, :-2], b3.lands) and np.array_equal(j3.lands[:, -2:], lands[:, 2:])
    assert j3.sigma_deg == b3.sigma_deg and np.array_equal(j.shelf(1.0).lands, base.shelf(1.0).lands)
    doc = json.loads(out.read_text())
    assert doc["joined"][-1] == {"height_m": 3.0, "entries": 1, "made_by": "test other"}
    assert j3.choose(j3.probe_up[p], j.radius_deg, j3.sigma_deg)[1] == 2 * len(b3.up)  # the vote picks it there
    fewer = MotionLibrary([Shelf(3.0, b3.up[:1], b3.x[:1] + 0.02, b3.landed[:1], b3.probe_up[:-1],
                                 np.zeros((len(b3.probe_up) - 1, 2), dtype=bool))])
    fewer_path = tmp_path / "fewer.json"
    fewer_path.write_text(json.dumps(fewer.as_dict()))
    for argv, words in ((("--join", str(fewer_path), "--heights", "3"), "3 m: the two shelves have different probes"),
                        (("--join", str(other_path), "--heights", "1"), "the --join library has no shelf"),
                        (("--join", str(other_path), "--add-probes", "10"), "one at a time"),
                        (("--join", str(other_path), "--heights", "3", "--sigma", "-1"), "--sigma must be a positive")):
        r = _felis("train", "landing-library", *argv, "--out", str(tmp_path / "o.json"))
        assert r.returncode != 0 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "o.json").exists()


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_add_probes_tries_a_denser_grid_on_a_shelf_keeps_what_it_had_and_resumes(tmp_path):
    """`felis train landing-library --add-probes N --heights 3`: the new probes (an N-point sphere's attitudes)
    are tried with the 3 m motions near them; the old probes' results and the 1 m shelf are unchanged; a resumed
    run reads the checkpoint and writes the same library; eval runs it."""
    out, ck = tmp_path / "dense.json", tmp_path / "ck"
    argv = ("train", "landing-library", "--add-probes", "40", "--heights", "3", "--probe-radius", "8", "--sigma",
            "2", "--out", str(out), "--workdir", str(ck), "--workers", "2")
    r = _felis(*argv)
    assert r.returncode == 0, r.stderr
    assert "3 m: " in r.stdout and "probes added (40-point sphere, motions within 8°)" in r.stdout
    base, dense = load_library(), load_library(out)
    b3, d3 = base.shelf(3.0), dense.shelf(3.0)
    n_new = len(d3.probe_up) - len(b3.probe_up)
    assert n_new > 0 and d3.sigma_deg == 2.0 and dense.sigma_deg == base.sigma_deg
    assert np.array_equal(d3.probe_up[:len(b3.probe_up)], b3.probe_up) and np.array_equal(d3.lands[:len(b3.lands)],
                                                                                           b3.lands)
    cand_up = d3.candidates()[0]
    new_up, new_lands = d3.probe_up[len(b3.probe_up):], d3.lands[len(b3.lands):]
    ang = np.degrees(np.arccos(np.clip(new_up @ cand_up.T, -1, 1)))
    assert not np.any(new_lands & (ang > 8.0 + 1e-9))  # tried only within the radius
    assert np.all(np.degrees(np.arccos(np.clip(new_up[:, 2], -1, 1))) <= 100.0 + 1e-9) and np.all(new_up[:, 1] >= 0)
    kept = dense.shelf(1.0)  # the other shelf as it was, its own vote width too
    assert kept.sigma_deg == base.shelf(1.0).sigma_deg and np.array_equal(kept.lands, base.shelf(1.0).lands)
    doc = json.loads(out.read_text())
    assert doc["probes_added"][-1]["probes"] == n_new and doc["extended_by"][-1].startswith(
        "felis train landing-library --add-probes 40")
    assert (ck / "3m" / "probes_added.npy").exists()
    out2 = tmp_path / "again.json"
    r = _felis(*[a if a != str(out) else str(out2) for a in argv], "--resume")
    assert r.returncode == 0, r.stderr
    doc2 = json.loads(out2.read_text())
    assert doc2["shelves"] == doc["shelves"]
    r = _felis("eval", "landing", "--drops", "random:2", "--height", "3", "--policy", str(out), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["total"] == 2


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_add_probes_near_misses_refines_only_where_the_vote_is_wrong(tmp_path):
    """`--add-probes N --near-misses`: of the N-point sphere's new attitudes only those whose nearest probe is a
    miss of the shelf's own vote (`misses`); the rest of the grid is left out."""
    from felis.learning.landing.library_build import fibonacci_ups, misses

    out = tmp_path / "refined.json"
    r = _felis("train", "landing-library", "--add-probes", "1000", "--heights", "3", "--probe-radius", "2",
               "--near-misses", "--out", str(out), "--workdir", str(tmp_path / "ck"), "--workers", "2")
    assert r.returncode == 0, r.stderr
    base, refined = load_library(), load_library(out)
    b3, r3 = base.shelf(3.0), refined.shelf(3.0)
    wrong = misses(b3, base.radius_deg, b3.sigma_deg or base.sigma_deg)
    assert f"only near the {len(wrong)} probes where the vote missed" in r.stdout
    new_up = r3.probe_up[len(b3.probe_up):]
    grid = fibonacci_ups(1000, 100.0)
    grid = grid[np.degrees(np.arccos(np.clip(grid @ b3.probe_up.T, -1, 1))).min(axis=1) > 1e-3]
    nearest = np.argmax(grid @ b3.probe_up.T, axis=1)
    want = grid[np.isin(nearest, wrong)]
    assert 0 < len(new_up) == len(want) < len(grid) and np.allclose(new_up, want, atol=1e-6)
    assert json.loads(out.read_text())["probes_added"][-1]["near_misses"] == len(wrong)
    r = _felis("train", "landing-library", "--near-misses", "--out", str(tmp_path / "o.json"))
    assert r.returncode != 0 and "--near-misses refines --add-probes N" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "o.json").exists()


def test_add_probes_refuses_a_height_without_a_shelf_and_bad_numbers_in_one_line(tmp_path):
    o = tmp_path / "o.json"
    for argv, words in ((("--add-probes", "10", "--heights", "2"), "the library has shelves at 1, 3 m only"),
                        (("--add-probes", "10", "--sigma", "0"), "--sigma must be a positive number"),
                        (("--add-probes", "0"), "points ≥ 1"),
                        (("--add-probes", "10", "--add", str(DEFAULT_LIBRARY.parent / "landing_hard_drop.json")),
                         "--add, --add-probes, --join, --recheck, --extend and --fill: one at a time")):
        r = _felis("train", "landing-library", *argv, "--out", str(o))
        assert r.returncode != 0 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not o.exists()


# docs/landing.md, on random:100: the shipped library (the default until 2026-11-30) and the ceiling (the per-drop
# optimum warm-started from it) on the described cat, seeds 0 and 1 (1 m, 3 m)
LIBRARY = {(1.0, 1): 75, (3.0, 1): 81}  # seed 0's (89, 92) are the share test's: 100 % and 94 % of 89 and 98
DEFAULT = {(1.0, 0): 96, (3.0, 0): 95, (1.0, 1): 93, (3.0, 1): 95}  # caps+library: the votes by attitude
CEILING = {(1.0, 0): 89, (1.0, 1): 82, (3.0, 0): 98, (3.0, 1): 87}


def _ceiling(design: str, height: float, seed: int = 0, step: float | None = None) -> dict:
    """`learning/weights/landing_optimum_warm[_<design>]-<h>m[-<step>ms][-seed<s>].json`: the design's name unless it
    is the described cat, the step unless it is the design's own."""
    name = ("" if design == "cat" else f"_{design}") + f"-{height:g}m" + ("" if step is None else f"-{step:g}ms")
    return json.loads((DEFAULT_LIBRARY.parent / f"landing_optimum_warm{name}{'' if seed == 0 else f'-seed{seed}'}.json")
                      .read_text())


@pytest.mark.parametrize("height, policy, seed", [(1.0, None, 0), (3.0, None, 0), (1.0, None, 1), (3.0, None, 1),
                                                  (1.0, "library", 1)])
def test_the_default_lands_what_the_docs_say_on_random_100_and_90_percent_of_the_ceiling(height, policy, seed):
    """README and docs/landing.md: the default policy (``caps+library``: from 1 m and from 3 m a vote by attitude
    between the cap policy made for that height and the motion library) on `random:100` seeds 0 and 1, and the
    library alone from 1 m on seed 1 (held out; its seed 0 figures are the share test's below, in process), through
    the command, land what the docs say, ≥ 75 % from 1 m and ≥ 50 % from 3 m, and ≥ 90 % of the shipped ceiling of
    the same drops (the issue's goals). The rollouts are deterministic on a machine; ±1 allows for another CPU's
    floating point at a drop on the edge."""
    r = _felis("eval", "landing", "--drops", "random:100", "--seed", str(seed), "--height", f"{height:g}", "--json",
               *([] if policy is None else ["--policy", policy]))
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    got, want = res["landed"], (DEFAULT if policy is None else LIBRARY)[height, seed]
    assert res["policy"] == (policy or "caps+library") and res.get("timestep_ms") is None  # the model's 0.5 ms step
    assert abs(got - want) <= 1, f"{height:g} m seed {seed}: {got} landed, the docs say {want}"
    assert got >= (75 if height == 1.0 else 50) and got >= 0.9 * CEILING[height, seed]
    if policy is None:  # docs/landing.md's table of the default against the ceiling, by start tilt
        doc = " ".join((Path(__file__).parents[2] / "docs" / "landing.md").read_text().split())
        row = " | ".join(f"{b['landed']}/{b['total']}" for b in res["by_tilt"].values())
        assert f"| default, {height:g} m, seed {seed} | **{got}** | {row} |" in doc


@pytest.mark.parametrize("height, seed", [(1.0, 0), (3.0, 0), (1.0, 1), (3.0, 1)])
def test_the_cats_shipped_ceilings_are_of_the_drops_and_step_they_name(height, seed):
    """`felis eval landing --policy optimum --warm-start learning/weights/landing_library_4ms-paw.json --restarts 1
    --drops random:100 --seed S --height H` (the library as it was voted when these were searched; seed 0 23–29
    min, seed 1 33 and 40 min on 2 cores): each file's drops are that seed's, its step the model's 0.5 ms, and it
    lands what the docs say."""
    doc = _ceiling("cat", height, seed)
    assert doc["design"] == "cat" and doc["timestep_ms"] == 0.5 and doc["seed"] == seed
    assert doc["search"]["warm_start"] == "library" and doc["landed"] == CEILING[height, seed]
    assert sum(o["landed"] for o in doc["drops"]) == CEILING[height, seed]
    want = random_drops(100, seed=seed, heights=height)
    got = [(o["roll_deg"], o["pitch_deg"], o["yaw_deg"], o["height_m"]) for o in doc["drops"]]
    assert np.allclose(got, [(d.roll_deg, d.pitch_deg, d.yaw_deg, d.height_m) for d in want], atol=1e-3)


@pytest.mark.parametrize("design, height, step, policy, want, share", [
    ("cat", 1.0, None, "library", 89, 100), ("cat", 3.0, None, "library", 98, 94),
    # the cats before 2026-11-29 (their figures reproduce; `make test-slow`, keeping the default run under 10 min)
    pytest.param("4ms-paw", 1.0, None, "library", 89, 96, marks=pytest.mark.slow),
    pytest.param("4ms-paw", 3.0, None, "library", 94, 89, marks=pytest.mark.slow),
    pytest.param("soft-rubber-paw", 1.0, None, "library", 88, 94, marks=pytest.mark.slow),
    pytest.param("soft-rubber-paw", 3.0, None, "library", 96, 91, marks=pytest.mark.slow),
    pytest.param("cat", 1.0, 1.0, "4ms-vote", 90, 84, marks=pytest.mark.slow),  # the step that does not resolve
    pytest.param("cat", 3.0, 1.0, "4ms-vote", 97, 61, marks=pytest.mark.slow),  # the 2 ms paw, and the old vote
    pytest.param("cat", 1.0, None, "4ms-vote", 89, 93, marks=pytest.mark.slow),
    pytest.param("cat", 3.0, None, "4ms-vote", 98, 78, marks=pytest.mark.slow),
    pytest.param("cat", 3.0, 0.25, "4ms-vote", 96, 80, marks=pytest.mark.slow)])  # 17 s
def test_the_library_lands_every_drop_of_a_cats_ceiling_it_lands_and_its_share(design, height, step, policy, want,
                                                                                 share):
    """The ceiling of a cat (the described one; ``4ms-paw``, the cat as described until 2026-11-29; the design
    study's 3 ms paw) on `random:100 --seed 0` at its step or another, searched from the shipped library's motions:
    the library (that cat's vote of its motions, or the vote taken on the 4 ms-paw cat: ``4ms-vote``) on that cat
    at that step lands every drop of it that it lands, and the share the docs report: on the described cat 100 %
    and 94 % (the goal is 90 %); on the 4 ms-paw cat 96 % and 89 %; with the old vote on the described cat 93 % and
    78 %, and at 1 ms, which does not resolve its paw, 84 % and 61 %."""
    from felis.learning.landing.designs import design_library
    from felis.learning.landing.evaluate import run_drops

    own = {"cat": 0.5, "4ms-paw": None, "soft-rubber-paw": None}[design]
    doc = _ceiling(design, height, step=step)
    assert doc["design"] == design and doc["search"]["warm_start"] == "library" and doc["landed"] == want
    assert doc.get("timestep_ms") == (own if step is None else step)
    # what `felis eval landing --design D --drops random:100 --seed 0 --height H [--timestep STEP]` runs, in process
    drops = random_drops(100, seed=0, heights=height)
    # the library as that cat votes it: what `felis eval landing --design D` runs by default
    run = str(design_library(design) or "library") if policy == "library" else str(design_library("4ms-paw"))
    lib = [o.landed for o in run_drops(drops, run, design=design, timestep=None if step is None else step / 1000.0)]
    assert all(o["landed"] for o, landed in zip(doc["drops"], lib, strict=True) if landed)
    assert round(100 * sum(lib) / want) == share


def test_the_shipped_librarys_vote_was_taken_on_the_described_cat_and_the_old_one_is_kept():
    """`learning/weights/landing_library.json` holds the motions and the vote taken on the described cat at its
    0.5 ms step over every probe of both shelves (`bench/landing_revote.py --near-deg 0`; nothing chosen on the
    evaluated drops); `landing_library_4ms-paw.json`, the 4 ms-paw cat's, is a votes file over it: the same
    motions and probes, another vote."""
    from felis.learning.landing.designs import design_library

    lib, old = load_library(), load_library(design_library("4ms-paw"))
    assert old.meta["votes_of"]["file"] == DEFAULT_LIBRARY.name and "revoted" not in old.meta
    assert all(v["near_deg"] == 0 and v["timestep_ms"] == 0.5 for v in lib.meta["revoted"]["shelves"].values())
    assert set(lib.meta["revoted"]["shelves"]) == {"1m", "3m"}
    for a, b in zip(lib.shelves, old.shelves, strict=True):
        assert np.array_equal(a.x, b.x) and np.array_equal(a.probe_up, b.probe_up) and a.sigma_deg == b.sigma_deg
        assert not np.array_equal(a.lands, b.lands)


def test_eval_landing_on_a_design_with_its_own_vote_runs_it_by_default(tmp_path, capsys):
    """Another design's default is the library with that cat's own vote; the described cat's is ``caps+library``
    (the cap policy was evolved on it)."""
    from felis.cli.main import main
    from felis.learning.landing.designs import design_library

    drops = tmp_path / "d.json"
    drops.write_text(json.dumps([{"roll_deg": 150.0, "pitch_deg": 10.0, "yaw_deg": 0.0, "height_m": 1.0}]))
    for design, policy in (("4ms-paw", str(design_library("4ms-paw"))), ("cat", "caps+library")):
        assert main(["eval", "landing", "--drops", str(drops), "--design", design, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["policy"] == policy
    assert design_library("cat") is None


def _with_entries(lib: MotionLibrary, height_m: float, rows) -> MotionLibrary:
    """``lib`` with only the entries ``rows`` on its ``height_m`` shelf (their probe verdicts kept), in that order."""
    shelves = [s if s.height_m != height_m else _shelf_with(s, rows, sigma_deg=s.sigma_deg) for s in lib.shelves]
    return MotionLibrary(shelves, lib.radius_deg, lib.sigma_deg, meta=dict(lib.meta))


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_recheck_sets_each_entrys_flag_to_whether_it_lands_its_own_attitude(tmp_path):
    """``--recheck`` tries every entry of a shelf on its own drop again and keeps the probes' verdicts; entry 72 of
    the shipped 1 m shelf, a twin searched (before robustify's fix) on another entry's attitudes, does not land
    its own, entry 0 does. On 27 of the shelf's 698 entries (``--base``; the whole shelf is 20 s of rollouts)."""
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.optimum import evaluate

    picked = [0, 72, 160, 300, *range(5, 698, 31)]
    base = tmp_path / "base.json"
    base.write_text(json.dumps(_with_entries(load_library(), 1.0, picked).as_dict()))
    out = tmp_path / "rechecked.json"
    r = _felis("train", "landing-library", "--recheck", "--heights", "1", "--base", str(base), "--out", str(out))
    assert r.returncode == 0, r.stderr
    before, after = load_library(base).shelf(1.0), load_library(out).shelf(1.0)
    assert len(after.up) == len(picked)
    assert np.array_equal(before.lands, after.lands) and np.array_equal(before.x, after.x)
    sim = BatchLandingSim(nthread=1)
    try:
        rows = list(range(len(picked)))
        drops = [Drop(*(after.drops[i][k] for k in ("roll_deg", "pitch_deg", "yaw_deg")), 1.0) for i in rows]
        now = [v.landed for _, v in evaluate(sim, drops, after.x[rows])]
    finally:
        sim.close()
    assert now == after.landed.tolist() and now[:2] == [True, False]
    changed = int((before.landed != after.landed).sum())
    assert f"1 m: {int(after.landed.sum())} of {len(after.landed)} entries land their own attitude" in r.stdout
    assert f"{changed} flags changed" in r.stdout and load_library(out).meta["rechecked"][-1]["changed"] == changed
    assert load_library(out).shelf(3.0).landed.tolist() == load_library().shelf(3.0).landed.tolist()


def _edge_library(tmp_path):
    """A small 3 m library: the shipped shelf's entries tilted 75–100° that land their own drop, probed on a
    40-point sphere up to 90°; written to a file for the CLI."""
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.library_build import fibonacci_ups, tilts_deg, try_probes

    s = load_library().shelf(3.0)
    rows = np.flatnonzero((tilts_deg(s.up) > 75) & (tilts_deg(s.up) <= 100) & s.landed)[:8]
    probe_up = fibonacci_ups(40, 90.0)
    sim = BatchLandingSim(nthread=2)
    try:
        lands = try_probes(sim, s.up[rows], s.x[rows], probe_up, 3.0)
    finally:
        sim.close()
    lib = MotionLibrary([Shelf(3.0, s.up[rows], s.x[rows], s.landed[rows], probe_up, lands,
                               [s.drops[i] for i in rows])], sigma_deg=3.0)
    path = tmp_path / "edge.json"
    path.write_text(json.dumps(lib.as_dict()))
    return lib, path


# slow (11-22 s): a tool that built the shipped library; the default suite keeps the build, its resume and the CLI
@pytest.mark.slow
def test_extend_takes_a_shelf_beyond_its_farthest_probe_from_the_motions_at_its_edge_and_resumes(tmp_path):
    """``--extend 120``: probes of the ``--probes`` sphere tilted beyond the shelf's farthest (90°) up to 120°,
    tried with the motions within the radius; a fill round for those no motion lands, each from the nearest motion
    that lands something; the new entries' flags are what they do on their probe; the old probes' results and
    entries kept; a run resumed from its checkpoints writes the same library; eval runs it."""
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.library_build import tilts_deg, up_drop
    from felis.learning.landing.optimum import evaluate

    _, path = _edge_library(tmp_path)
    old = load_library(path).shelf(3.0)  # as the file has it (attitudes to 6 decimals)
    out, ck = tmp_path / "out.json", tmp_path / "ck"
    argv = ("train", "landing-library", "--base", str(path), "--extend", "120", "--heights", "3", "--probes", "40",
            "--fill-generations", "1", "--fill-rounds", "1", "--out", str(out), "--workdir", str(ck),
            "--workers", "2")
    r = _felis(*argv)
    assert r.returncode == 0, r.stderr
    ext = load_library(out)
    s = ext.shelf(3.0)
    P, E = len(old.probe_up), len(old.up)
    new = s.probe_up[P:]
    assert len(new) >= 3 and np.all((tilts_deg(new) > tilts_deg(old.probe_up).max()) & (tilts_deg(new) <= 120 + 1e-6))
    assert np.all(new[:, 1] >= 0)
    assert np.array_equal(s.probe_up[:P], old.probe_up) and np.array_equal(s.lands[:P, :2 * E], old.lands)
    assert np.array_equal(s.x[:E], old.x) and np.array_equal(s.landed[:E], old.landed)
    cand_up = s.candidates()[0]
    ang = np.degrees(np.arccos(np.clip(s.probe_up @ cand_up.T, -1, 1)))
    assert not np.any(s.lands & (ang > 30.0 + 1e-9))
    a = ext.meta["extended"][-1]
    assert a["probes"] == len(new) and a["from_deg"] == pytest.approx(float(tilts_deg(old.probe_up).max()), abs=1e-3)
    rnd = a["fill"]["rounds"][0]
    assert rnd["targets"] >= 1 and len(s.up) == E + rnd["entries"]
    reach = float(tilts_deg(old.probe_up).max())  # the 40-point sphere's farthest within 90°
    assert f"3 m: {len(new)} probes added from {reach:.0f}° to 120°" in r.stdout, r.stdout
    # none of the new probes is landed by the shelf's motions; the fill (from the edge) finds one that is
    assert a["landed_by_some_before"] == 0 and a["landed_by_some"] >= 1 and rnd["entries"] >= 1
    assert angles_min(s.up[E:], new) < 1e-3  # each new entry sits on one of the new probes
    sim = BatchLandingSim(nthread=2)
    try:  # its flag is what it does there
        now = [v.landed for _, v in evaluate(sim, [up_drop(u, 3.0) for u in s.up[E:]], s.x[E:])]
    finally:
        sim.close()
    assert now == s.landed[E:].tolist() and any(now)
    assert {p.name for p in (ck / "3m").iterdir()} == {"extend_probes.npy", "extend_fill1.npz",
                                                       "extend_probes1.npy"}
    out2 = tmp_path / "again.json"
    r = _felis(*[a if a != str(out) else str(out2) for a in argv], "--resume")
    assert r.returncode == 0, r.stderr
    assert json.loads(out2.read_text())["shelves"] == json.loads(out.read_text())["shelves"]
    r = _felis("train", "landing-library", "--base", str(out), "--extend", "110", "--heights", "3", "--out",
               str(tmp_path / "no.json"))
    assert r.returncode != 0 and len(r.stderr.splitlines()) == 1
    assert f"the 3 m shelf's probes reach {tilts_deg(new).max():.1f}° already" in r.stderr
    r = _felis("eval", "landing", "--drops", "random:2", "--height", "3", "--policy", str(out), "--json")
    assert r.returncode == 0, r.stderr


# slow (~30 s): a tool for the shipped library's shelves on the described cat (docs/landing.md)
@pytest.mark.slow
def test_fill_searches_a_motion_for_each_hole_of_a_shelf_on_the_cat_it_names_and_resumes(tmp_path):
    """``--fill``: no new probes; a fill round over the shelf's own probes that no motion lands (and the vote's
    misses), each motion searched on the described cat from the nearest that lands something; the shelf's entries
    and results kept; each new entry sits on its probe and its flag is what it does there; resumed from its
    checkpoints it writes the same library; a bad tilt or another mode beside it is one line."""
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.library_build import up_drop
    from felis.learning.landing.optimum import evaluate

    _, path = _edge_library(tmp_path)
    old = load_library(path).shelf(3.0)
    out, ck = tmp_path / "out.json", tmp_path / "ck"
    argv = ("train", "landing-library", "--base", str(path), "--fill", "--heights", "3", "--fill-generations", "1",
            "--fill-rounds", "1", "--out", str(out), "--workdir", str(ck), "--workers", "2")
    r = _felis(*argv)
    assert r.returncode == 0, r.stderr
    lib = load_library(out)
    s = lib.shelf(3.0)
    P, E = len(old.probe_up), len(old.up)
    holes = int((~old.lands.any(axis=1)).sum())
    assert holes >= 1 and np.array_equal(s.probe_up, old.probe_up)
    assert np.array_equal(s.x[:E], old.x) and np.array_equal(s.lands[:, :2 * E], old.lands)
    a = lib.meta["filled"][-1]
    rnd = a["fill"]["rounds"][0]
    assert a["design"] == "cat" and a["probes"] == P and a["landed_by_some_before"] == P - holes
    assert rnd["targets"] >= holes and rnd["entries"] >= 1 and len(s.up) == E + rnd["entries"]
    assert a["landed_by_some"] > a["landed_by_some_before"]  # the fill lands some hole
    assert f"3 m: of {P} probes tilted at most 180°, {P - holes} landed by some motion before the fill" in r.stdout
    assert angles_min(s.up[E:], s.probe_up) < 1e-3
    sim = BatchLandingSim(nthread=2)
    try:
        now = [v.landed for _, v in evaluate(sim, [up_drop(u, 3.0) for u in s.up[E:]], s.x[E:])]
    finally:
        sim.close()
    assert now == s.landed[E:].tolist()
    assert {p.name for p in (ck / "3m").iterdir()} == {"fill_fill1.npz", "fill_probes1.npy"}
    out2 = tmp_path / "again.json"
    r = _felis(*[a if a != str(out) else str(out2) for a in argv], "--resume")
    assert r.returncode == 0, r.stderr
    assert json.loads(out2.read_text())["shelves"] == json.loads(out.read_text())["shelves"]
    for extra, says in ((("--fill", "0"), "--fill DEG and --probe-radius must be within (0, 180]"),
                        (("--fill", "--extend", "120"), "one at a time")):
        r = _felis("train", "landing-library", "--base", str(path), *extra, "--out", str(tmp_path / "no.json"))
        assert r.returncode != 0 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "no.json").exists()


def angles_min(a: np.ndarray, b: np.ndarray) -> float:
    """The largest, over the rows of a, of the angle (deg) to the nearest row of b (rows normalised first, and the
    angle from the chord, 2·asin(|a − b|/2): exact near 0, where arccos of a dot product of vectors written to 6
    decimals reads up to ~0.01°)."""
    a, b = (v / np.linalg.norm(v, axis=1, keepdims=True) for v in (np.asarray(a, float), np.asarray(b, float)))
    chord = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return float(np.degrees(2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))).min(axis=1).max())


def test_nearest_in_chunks_is_the_whole_matrix_argmax():
    from felis.learning.landing.library_build import _nearest, fibonacci_ups

    a, b = fibonacci_ups(500), fibonacci_ups(37, 120.0)
    idx, cos = _nearest(a, b, chunk=7)
    d = a @ b.T
    assert np.array_equal(idx, np.argmax(d, axis=1)) and np.allclose(cos, d.max(axis=1))
