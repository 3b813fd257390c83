"""`Gather`: the numbers a tick reads from MuJoCo's data, in one copy.

``mj_makeData`` lays every array of an ``MjData`` (``qpos``, ``qvel``, ``sensordata``, ``xpos``, ``xquat``,
``subtree_com``, …) out in one buffer. A flat float64 view over the span of the arrays a reader names turns
the elements it wants, from any of them, into one index vector ``i`` into that view, and a tick's reading into
one ``numpy.take``: ``v = flat[i]``. Reading the same values field by field costs a property lookup and a
fancy-indexing copy per field (about a microsecond each, several times that once the physics step has pushed
them out of the CPU caches), which was most of `felis.sim.MujocoRobot.read`.

The view does not own the memory: a `Gather` keeps a reference to the ``MjData`` and is valid while that is
(``mj_resetData`` keeps the buffer; a new ``MjData`` needs a new `Gather`). Where the arrays are not all in
one buffer (checked against ``MjData.nbuffer``, in case a MuJoCo release lays them out otherwise), it reads
field by field and concatenates: the same result, slower.

>>> g = Gather(d, [("qpos", [7, 8]), ("sensordata", range(4))])    # doctest: +SKIP
>>> g.take()                                                        # doctest: +SKIP
array([q7, q8, s0, s1, s2, s3])
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np


def _address(a: np.ndarray) -> int:
    return int(a.__array_interface__["data"][0])


class Gather:
    """One ``take`` of the listed elements of ``data``'s arrays: ``parts`` is (field name, flat indices into
    ``getattr(data, field).ravel()``) in the order of the result. `slices` gives each part's place in it."""

    def __init__(self, data, parts: Sequence[tuple[str, Iterable[int]]]):
        self.data = data
        self._parts = [(f, np.asarray(list(ix), dtype=np.intp).reshape(-1)) for f, ix in parts]
        arrays = {f: getattr(data, f) for f, _ in self._parts}
        for f, a in arrays.items():
            if a.dtype != np.float64 or not a.flags["C_CONTIGUOUS"]:
                raise TypeError(f"MjData.{f} is not a contiguous float64 array")
            for _, ix in (p for p in self._parts if p[0] == f):
                if ix.size and (ix.min() < 0 or ix.max() >= a.size):
                    raise IndexError(f"MjData.{f} has {a.size} elements; asked for index {int(ix.max())}")
        bounds, pos = [], 0
        for _, ix in self._parts:
            bounds.append(slice(pos, pos + ix.size))
            pos += ix.size
        self.slices = bounds
        self.size = pos
        self._flat = self._index = None
        if arrays:
            lo = min(_address(a) for a in arrays.values())
            hi = max(_address(a) + a.nbytes for a in arrays.values())
            nbuffer = getattr(data, "nbuffer", 0)
            if hi - lo <= nbuffer and all((_address(a) - lo) % 8 == 0 for a in arrays.values()):
                first = next(a for a in arrays.values() if _address(a) == lo)
                self._flat = np.lib.stride_tricks.as_strided(first, shape=((hi - lo) // 8,), strides=(8,),
                                                             writeable=False)
                self._index = np.concatenate([ix + (_address(arrays[f]) - lo) // 8 for f, ix in self._parts])

    @property
    def one_buffer(self) -> bool:
        """True when `take` is a single gather from one view (the arrays share MuJoCo's buffer)."""
        return self._flat is not None

    def take(self) -> np.ndarray:
        """A new array of the listed elements, as they are now."""
        if self._flat is not None:
            return self._flat.take(self._index)
        d = self.data
        return np.concatenate([getattr(d, f).ravel().take(ix) for f, ix in self._parts]) if self._parts \
            else np.zeros(0)
