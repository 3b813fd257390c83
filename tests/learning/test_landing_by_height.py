"""Landing policies by drop height (`felis.learning.landing.by_height`): the default ``caps+library``."""

from __future__ import annotations

import numpy as np
import pytest

from felis.errors import ParameterError
from felis.learning.landing import by_height


def test_nearest_height_is_by_the_ratio():
    """argmin |ln(h_k / h)|: between 1 m and 3 m the boundary is √3 m; a height at or below 0 is the lowest part's."""
    got = by_height.nearest_height([1.0, 3.0], [-1.0, 0.0, 0.5, 1.0, 1.73, 1.74, 2.0, 3.0, 30.0])
    assert list(got) == [0, 0, 0, 0, 0, 1, 1, 1, 1]
    assert list(by_height.nearest_height([3.0, 1.0, 0.3], [0.5, 0.6])) == [2, 1]  # √0.3 ≈ 0.548


class _Const:
    """A batch policy that returns ``c`` and records the rows and times it saw."""

    def __init__(self, c: float):
        self.c, self.seen = c, []

    def __call__(self, it, t, rows):
        self.seen.append((rows.copy(), t.copy()))
        return np.full((len(it), 12), self.c)


def test_each_cat_keeps_the_part_of_the_height_it_sensed_at_release():
    """A cat takes its part at its first tick (t < half a tick) from the height input then and keeps it while the
    height falls; each part sees only its own cats' rows; `ByHeightRule` takes for one cat what `ByHeight` takes."""
    low, high = _Const(1.0), _Const(3.0)
    pol = by_height.ByHeight([1.0, 3.0], [low, high])
    it = np.zeros((3, 15))
    it[:, 6] = np.array([1.1, 2.9, 1.8]) / 3.0  # sensed (m) / 3 m, the nets' height input
    rows = np.arange(3)
    v = pol(it, np.zeros(3), rows)
    assert list(v[:, 0]) == [1.0, 3.0, 3.0] and pol.choice == {0: 0, 1: 1, 2: 1}
    it[:, 6] = 0.1 / 3.0  # falling: all near the floor now, each keeps its part
    v = pol(it, np.full(3, 0.3), rows)
    assert list(v[:, 0]) == [1.0, 3.0, 3.0]
    assert [list(r) for r, _ in low.seen] == [[0], [0]] and [list(r) for r, _ in high.seen] == [[1, 2], [1, 2]]
    for h, want in ((1.1, 1.0), (2.9, 3.0), (1.8, 3.0)):
        rule = by_height.ByHeightRule([1.0, 3.0], [lambda it, t: np.full(12, 1.0), lambda it, t: np.full(12, 3.0)])
        x = np.zeros(15)
        x[6] = h / 3.0
        assert rule(x, 0.0)[0] == want
        x[6] = 0.0
        assert rule(x, 0.2)[0] == want


@pytest.mark.parametrize("heights, n, says", [
    ([1.0], 2, "1 heights for 2 policies"),
    ([1.0, 1.0], 2, "distinct positive heights"),
    ([1.0, -3.0], 2, "distinct positive heights"),
    ([1.0, float("nan")], 2, "distinct positive heights"),
    ([], 0, "0 heights for 0 policies"),
])
def test_bad_parts_are_one_line(heights, n, says):
    for cls in (by_height.ByHeight, by_height.ByHeightRule):
        with pytest.raises(ParameterError, match=says):
            cls(heights, [_Const(0.0)] * n)


def test_caps_library_is_the_votes_at_1m_and_3m():
    """The default's heights come from the files: the caps file's height (1 m) and the library's other shelves (3 m),
    where the shipped votes between the cap policies and the library run (`felis.learning.landing.by_attitude`);
    on the simulated cat the batch sends 1 m and 1.5 m drops to the 1 m vote and 2.5 m and 3 m drops to the 3 m one;
    a library with no other height is one line."""
    from felis.learning.landing.by_attitude import ByAttitude
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, CapPolicy
    from felis.learning.landing.designs import design_sim
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ, batch_controller, default_policy
    from felis.learning.landing.library import LibraryBatch, MotionLibrary, load_library
    from felis.scenarios.drop import Drop

    lib = load_library()
    assert by_height.caps_library_heights(SHIPPED_CAPS, lib) == (1.0, [3.0])
    assert default_policy() == by_height.NAME == "caps+library"
    drops = [Drop(30.0, 5.0, 0.0, h) for h in (1.0, 1.5, 2.5, 3.0)]
    sim = design_sim("cat", nthread=1)
    try:
        b = batch_controller(sim.spec, "caps+library", drops)
        sim.batch.run(drops, b, sim.standing_waist_m, rate_hz=RATE_HZ, margin_s=MARGIN_S)
    finally:
        sim.close()
    pol = b.policies[0]
    assert isinstance(pol, by_height.ByHeight) and [type(p) for p in pol.policies] == [ByAttitude, ByAttitude]
    assert [[type(x) for x in p.policies] for p in pol.policies] == [[CapPolicy, LibraryBatch],
                                                                      [LibraryBatch, CapPolicy]]
    assert [pol.choice[i] for i in range(4)] == [0, 0, 1, 1]
    assert sorted(pol.policies[0].choice) == [0, 1] and sorted(pol.policies[1].choice) == [2, 3]
    one = MotionLibrary([s for s in lib.shelves if s.height_m == 1.0], lib.radius_deg, lib.sigma_deg)
    with pytest.raises(ParameterError, match="no shelf at another height than the cap policy's 1 m"):
        by_height.caps_library_heights(SHIPPED_CAPS, one)
