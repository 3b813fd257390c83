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
    ``getattr(data, field).ravel()``) in the order of the result. `slices` gives each part's place in it.
    ``order`` (optional) permutes the result: ``take()[k]`` is element ``order[k]`` of the parts laid end to end
    (to interleave fields, e.g. each body's position then its rotation, at no cost per take)."""

    def __init__(self, data, parts: Sequence[tuple[str, Iterable[int]]], order: np.ndarray | None = None):
        self.data = data
        self._parts = [(f, np.asarray(ix if isinstance(ix, np.ndarray) else list(ix), dtype=np.intp).reshape(-1))
                       for f, ix in parts]
        arrays, address = {}, {}
        for f, ix in self._parts:
            a = arrays.get(f)
            if a is None:
                a = arrays[f] = getattr(data, f)
                if a.dtype != np.float64 or not a.flags["C_CONTIGUOUS"]:
                    raise TypeError(f"MjData.{f} is not a contiguous float64 array")
                address[f] = _address(a)
            if ix.size and (ix.min() < 0 or ix.max() >= a.size):
                raise IndexError(f"MjData.{f} has {a.size} elements; asked for index {int(ix.max())}")
        sizes = np.cumsum([0] + [ix.size for _, ix in self._parts])
        self.slices = [slice(int(a), int(b)) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
        self.size = int(sizes[-1])
        self._order = None if order is None else np.asarray(order, dtype=np.intp).reshape(-1)
        if self._order is not None and not np.array_equal(np.sort(self._order), np.arange(self.size)):
            raise ValueError(f"order must be a permutation of 0…{self.size - 1}")
        self._flat = self._index = None
        if arrays:
            lo = min(address.values())
            hi = max(address[f] + a.nbytes for f, a in arrays.items())
            if hi - lo <= getattr(data, "nbuffer", 0) and all((x - lo) % 8 == 0 for x in address.values()):
                first = next(a for f, a in arrays.items() if address[f] == lo)
                self._flat = np.lib.stride_tricks.as_strided(first, shape=((hi - lo) // 8,), strides=(8,),
                                                             writeable=False)
                offset = {f: (x - lo) // 8 for f, x in address.items()}
                self._index = np.concatenate([ix + offset[f] for f, ix in self._parts])
                if self._order is not None:
                    self._index = self._index[self._order]

    @property
    def one_buffer(self) -> bool:
        """True when `take` is a single gather from one view (the arrays share MuJoCo's buffer)."""
        return self._flat is not None

    def take(self) -> np.ndarray:
        """A new array of the listed elements, as they are now."""
        if self._flat is not None:
            return self._flat.take(self._index)
        d = self.data
        v = np.concatenate([getattr(d, f).ravel().take(ix) for f, ix in self._parts]) if self._parts else np.zeros(0)
        return v if self._order is None else v[self._order]
