"""``bench/landing_revote.py``: the library's vote taken again on another paw and step."""

import numpy as np
import pytest
from conftest import load_bench

from felis.learning.landing.library import Shelf, load_library, mirror_up
from felis.learning.landing.library_build import up_drop


def _tilted(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([np.sin(a), 0.0, np.cos(a)])


def test_candidates_to_try_are_the_best_voted_then_the_nearest_each_once():
    bench = load_bench("landing_revote")
    up = np.array([_tilted(0.0), _tilted(10.0), _tilted(20.0)])  # entries; candidates 2e and 2e + 1 (mirror)
    probes = np.array([_tilted(0.5), _tilted(1.0), _tilted(19.0)])
    lands = np.zeros((3, 6), dtype=bool)
    lands[0, 4] = lands[1, 4] = True  # the 20° entry lands the probes near 0°: the vote picks it there
    lands[1, 2] = True  # the 10° entry lands one
    shelf = Shelf(3.0, up, np.zeros((3, 55)), np.ones(3, bool), probes, lands)
    tries = bench.candidates_to_try(shelf, np.array([0, 2]), top=2, nearest=2, radius_deg=15.0, sigma_deg=1.0)
    # probe 0: voted 4 (two probes), then 2 (one, 0.5° further); then the nearest, 0 and its mirror 1 (equal: the
    # entry first)
    assert tries[0].tolist() == [4, 2, 0, 1]
    # probe 2 (19°): no probe within 15° is landed by anything, so nothing by the vote; the nearest: 4 and 5
    assert tries[1].tolist() == [4, 5]
    assert np.allclose(mirror_up(up)[2], shelf.candidates()[0][5])


def test_revote_gives_each_pairs_verdict_and_resumes_without_a_rollout(tmp_path):
    from felis.learning.landing.evaluate import BatchLandingSim
    from felis.learning.landing.optimum import evaluate

    bench = load_bench("landing_revote")
    lib = load_library()
    shelf = lib.shelf(1.0)
    probes = np.array([0, 7])
    tries = [np.array([0, 3]), np.array([5])]
    state = tmp_path / "r.npz"
    sim = BatchLandingSim()
    try:
        lands = bench.revote(lib, 1.0, probes, tries, sim, state=state)
        _, cand_x, _ = shelf.candidates()
        pairs = [(0, 0), (0, 3), (7, 5)]
        direct = evaluate(sim, [up_drop(shelf.probe_up[p], 1.0) for p, _ in pairs], cand_x[[c for _, c in pairs]])
    finally:
        sim.close()
    want = np.zeros_like(shelf.lands)
    for (p, c), (_, v) in zip(pairs, direct, strict=True):
        want[p, c] = v.landed
    assert np.array_equal(lands, want)
    # every pair is in the checkpoint: resuming runs nothing (no simulation given)
    assert np.array_equal(bench.revote(lib, 1.0, probes, tries, None, state=state, resume=True), want)
    with pytest.raises(SystemExit, match="other pairs"):
        bench.revote(lib, 1.0, probes, [np.array([1]), np.array([5])], None, state=state, resume=True)
