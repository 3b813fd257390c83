"""The skills' own channels in a run log: ``/balance`` (the XCoM balance monitor's verdict each tick) and
``/phase`` (the gait phase its gait gate reads: the learned phase estimator's, or the gait's own clock), so a
viewer plots the margin of stability beside the joints and sees when the alarm and the warning came.

==============  ====================  ===========================================================================
``/balance``    JSON (felis.Balance)  margin (m, + inside the base of support; left out when unknown), alarm,
                                      warning, class (standing, moving, unbalanced, falling, unknown), xcom {x, y},
                                      com {x, y, z}, com_velocity {x, y, z}, cop {x, y} (where the feet's forces
                                      are known), omega0 (1/s), clearance (m)
``/phase``      JSON (felis.Phase)    phase [0, 1), frequency_hz, amplitude, stepping, source (``estimator``: the
                                      learned phase estimator, seed 003; ``clock``: the gait's own clock); only
                                      while the gate has a gait (the estimator needs a full window first)
==============  ====================  ===========================================================================

Both follow Foxglove's JSON-schema rules (one type per field, ``properties`` on every object); a value that is
not known is left out rather than written as null. `skill_channels` finds the sources by duck typing (this
package imports nothing above `felis`): a controller with an ``assessment`` (`felis.controllers.reactions.
ReactiveController`, or a wrapper that forwards it) or a loop monitor with ``last`` and ``assess`` (a
`felis.controllers.balance.BalanceMonitor` run as a monitor); the gait from that monitor's ``gait`` gate.
Cost: about 5 µs a tick for both.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

_NUM = {"type": "number"}
_XY = {"type": "object", "properties": {"x": _NUM, "y": _NUM}}
_XYZ = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}

BALANCE_SCHEMA = {"type": "object", "title": "felis.Balance", "properties": {
    "margin": {**_NUM, "description": "margin of stability b (m): distance from the XCoM to the edge of the base of "
                                      "support, positive inside"},
    "alarm": {"type": "boolean", "description": "a fall is predicted (hysteresis over ticks)"},
    "warning": {"type": "boolean", "description": "the margin is below the warning threshold: time to react"},
    "class": {"type": "string", "description": "standing, moving, unbalanced, falling or unknown (seed 004 §1.3)"},
    "xcom": {**_XY, "description": "extrapolated centre of mass ξ = x + v/ω0 (m, world frame)"},
    "com": {**_XYZ, "description": "centre of mass (m, world frame)"},
    "com_velocity": {**_XYZ, "description": "CoM velocity relative to the stance feet (m/s)"},
    "cop": {**_XY, "description": "centre of pressure (m), where the feet's forces are known"},
    "omega0": {**_NUM, "description": "√(g/l) (1/s), l the CoM's height above the stance feet"},
    "clearance": {**_NUM, "description": "lowest point other than the feet above the ground (m)"}}}

PHASE_SCHEMA = {"type": "object", "title": "felis.Phase", "properties": {
    "phase": {**_NUM, "description": "gait phase now, [0, 1)"},
    "frequency_hz": {**_NUM, "description": "gait frequency (Hz)"},
    "amplitude": {**_NUM, "description": "gait amplitude (the estimator's channel amplitude, or the clock's ramp)"},
    "stepping": {"type": "boolean", "description": "a periodic gait runs"},
    "source": {"type": "string", "description": "estimator (learned, seed 003) or clock (the gait's own)"}}}


def _num(v) -> str | None:
    """A finite number as JSON text, else None (left out)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f"{f:.9g}" if math.isfinite(f) else None  # 9 digits, as felis.logs.runlog's per-tick JSON


def _point(v, keys: str) -> str | None:
    if v is None or len(v) < len(keys):
        return None
    parts = [_num(x) for x in v[:len(keys)]]
    if any(p is None for p in parts):
        return None
    return "{" + ",".join(f'"{k}":{p}' for k, p in zip(keys, parts, strict=True)) + "}"


def balance_text(a) -> bytes:
    """An assessment (`felis.controllers.balance.Assessment`, duck-typed) as a ``/balance`` message."""
    parts = [f'"alarm":{"true" if a.alarm else "false"}', f'"warning":{"true" if a.warning else "false"}',
             f'"class":"{a.cls}"']
    for key, text in (("margin", _num(a.margin)), ("xcom", _point(a.xi, "xy")), ("com", _point(a.com, "xyz")),
                      ("com_velocity", _point(a.com_vel, "xyz")), ("cop", _point(a.cop, "xy")),
                      ("omega0", _num(a.omega0)), ("clearance", _num(getattr(a, "clearance", None)))):
        if text is not None:
            parts.append(f'"{key}":{text}')
    return ("{" + ",".join(parts) + "}").encode()


def phase_text(g, source: str) -> bytes:
    """A gait (``phase``, ``frequency_hz``, ``amplitude``, ``stepping``; duck-typed) as a ``/phase`` message."""
    parts = [f'"stepping":{"true" if getattr(g, "stepping", False) else "false"}', f'"source":"{source}"']
    for key in ("phase", "frequency_hz", "amplitude"):
        text = _num(getattr(g, key, None))
        if text is not None:
            parts.append(f'"{key}":{text}')
    return ("{" + ",".join(parts) + "}").encode()


class SkillChannels:
    """Loop monitor: each tick, ``/balance`` from ``assessment()`` (None: nothing this tick) and ``/phase`` from
    ``gate()`` (the gait gate, t → gait or None; itself None when there is none) into ``log``
    (`felis.logs.mcap.McapLog`)."""

    def __init__(self, log, assessment: Callable[[], object] | None, gate: Callable[[], object] | None):
        self.log, self._assessment, self._gate = log, assessment, gate
        self._put_balance = self._put_phase = None
        self._source: str | None = None

    def reset(self, spec=None, state=None) -> None:
        self._source = None  # the gate may be wired at the controller's reset

    def __call__(self, state, command=None) -> None:
        a = self._assessment() if self._assessment is not None else None
        gate = self._gate() if self._gate is not None else None
        g = gate(state.t) if callable(gate) else None
        if g is not None and self._source is None:
            est = getattr(gate, "__self__", None)  # a bound method: the estimator's, or the gait clock's
            self._source = "estimator" if hasattr(est, "pae") else "clock"
        if a is not None or g is not None:  # both are snapshots (frozen): formatted with the tick's other messages
            self.log.defer(self._write, self.log.ns(state.t), a, g)

    def _write(self, ns: int, a, g) -> None:
        if a is not None:
            if self._put_balance is None:
                self._put_balance = self.log.channel("/balance", BALANCE_SCHEMA)
            self._put_balance(ns, balance_text(a))
        if g is not None:
            if self._put_phase is None:
                self._put_phase = self.log.channel("/phase", PHASE_SCHEMA)
            self._put_phase(ns, phase_text(g, self._source))


def skill_channels(log, controller, monitors: Sequence = ()) -> SkillChannels | None:
    """The `SkillChannels` monitor for a run of ``controller`` with ``monitors``, or None when neither runs a
    balance monitor (module doc)."""
    if log is None:
        return None
    if _has(controller, "monitor") and _has(_get(controller, "monitor"), "assess"):
        mon = _get(controller, "monitor")

        def assessment():
            return _get(controller, "assessment")
    else:
        found = [m for m in monitors if _has(m, "assess") and _has(m, "last")]
        if not found:
            return None
        mon = found[0]

        def assessment():
            return mon.last

    return SkillChannels(log, assessment, lambda: getattr(mon, "gait", None))


def _has(obj, name: str) -> bool:
    try:
        getattr(obj, name)
    except AttributeError:
        return False
    return True


def _get(obj, name: str):
    return getattr(obj, name, None)
