"""Assertions on a run log (`felis.logs.reader.LogData`, or a `felis.testing.runner.RunResult` holding one).

Each fails with an `AssertionError` whose message says what an engineer needs to act on: which joint or
event, when (run time, s), the value and by how much it missed, and what the log held instead. Misuse (a
joint the log does not have, an empty band, a window that ends before it starts) is a
`felis.errors.ParameterError`, so a typo is not mistaken for a robot that misbehaved.

Times are run times: seconds since the log's first record (its first state or event), so ``t=(1.0, None)`` means
"from one second into the run" on every backend. (The log itself keeps the robot's clock: a simulation's time, or
a servo robot's time since it connected, which may be long before the run; `run_start` is the difference.)
Windows: ``t=(t0, t1)`` keeps samples with t0 ≤ t ≤ t1 (None leaves that end open); ``t=None`` is the whole run.

What counts as a fault (`assert_no_fault`): an event of a kind in `FAULT_EVENTS` (the loop's and the safety
layer's: a watchdog trip, a lost port, a servo's hardware error, torque lost, the Bus Watchdog, the IMU gone
quiet, a failed read, a non-finite command held), torque not read back off at the end, a joint with hardware
error bits or a stale reading on ``/faults``, failed bus transactions beyond a tolerance, and a summary whose run
is not ``ok``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from felis.errors import ParameterError

if TYPE_CHECKING:
    from felis.logs.reader import LogData

FAULT_EVENTS = ("watchdog", "comm_lost", "hardware_error", "torque_lost", "bus_watchdog", "imu_lost", "read_failed",
                "nonfinite_held")
MAX_LINES = 10  # lines of evidence in one failure message


def _data(log: Any) -> LogData:
    """The `LogData` of ``log`` (a `LogData`, or a result with ``.log``)."""
    data = getattr(log, "log", log) if hasattr(log, "report") else log
    if data is None:
        raise ParameterError("this run kept no log: run it with log=True to assert on its log")
    if not (hasattr(data, "events") and hasattr(data, "joints")):
        raise ParameterError(f"expected a run log (LogData, from read_log or run(...).log), got {type(log).__name__}")
    return data


def run_start(log: Any) -> float:
    """The robot-clock time (s) of the log's first record, state or event: run time 0 of the assertions."""
    data = _data(log)
    first = [float(data.t[0])] if len(data.t) else []
    first += [float(data.cmd_t[0])] if len(data.cmd_t) else []
    first += [min(e["t"] for e in data.events)] if data.events else []
    return min(first, default=0.0)


def _events(data: LogData) -> list[dict]:
    """The log's events with run times (module doc)."""
    t0 = run_start(data)
    return [{**e, "t": e["t"] - t0} for e in data.events]


def _window(t: tuple[float | None, float | None] | None) -> tuple[float, float]:
    if t is None:
        return -math.inf, math.inf
    try:
        t0, t1 = t
        lo = -math.inf if t0 is None else float(t0)
        hi = math.inf if t1 is None else float(t1)
    except (TypeError, ValueError):
        raise ParameterError(f"t must be a window (t0, t1) in seconds, got {t!r}") from None
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        raise ParameterError(f"t window {t!r} must have t0 ≤ t1")
    return lo, hi


def _where(window: tuple[float, float]) -> str:
    lo, hi = window
    if math.isinf(lo) and math.isinf(hi):
        return "over the whole run"
    return f"in t ∈ [{'…' if math.isinf(lo) else f'{lo:.3f}'}, {'…' if math.isinf(hi) else f'{hi:.3f}'}] s"


def _span(times: np.ndarray) -> str:
    return f"{times[0]:.3f}…{times[-1]:.3f} s" if len(times) else "no samples"


def assert_joint_within(log: Any, joint: str, low: float, high: float, *,
                        t: tuple[float | None, float | None] | None = None, commanded: bool = False) -> None:
    """Joint ``joint`` stayed within [low, high] (rad; m for a prismatic joint) at every logged state in the window
    ``t`` (``commanded=True``: every command sent). A missing value (NaN) counts as outside; a window without
    samples fails too (nothing was shown to hold)."""
    data = _data(log)
    if joint not in data.joints:
        raise ParameterError(f"no joint {joint!r} in the log of {data.robot}; its joints: {', '.join(data.joints)}")
    low, high = float(low), float(high)
    if not low <= high:
        raise ParameterError(f"band [{low}, {high}] for {joint} is empty: low must be ≤ high")
    window = _window(t)
    what = "command" if commanded else "state"
    times, values = (data.cmd_t, data.cmd_q) if commanded else (data.t, data.q)
    times = times - run_start(data)
    keep = (times >= window[0]) & (times <= window[1])
    if not keep.any():
        raise AssertionError(f"no {what} samples of {joint} {_where(window)} (the log has {_span(times)})")
    tt, v = times[keep], values[keep, data.joints.index(joint)]
    outside = ~((v >= low) & (v <= high))
    if not outside.any():
        return
    miss = np.where(np.isnan(v), np.inf, np.maximum(low - v, v - high))
    first, worst = int(np.flatnonzero(outside)[0]), int(np.argmax(miss))

    def at(k: int) -> str:
        if np.isnan(v[k]):
            return f"t={tt[k]:.3f} s (missing)"
        side = "below" if v[k] < low else "above"
        return f"t={tt[k]:.3f} s ({v[k]:.4f}, {miss[k]:.4f} {side} the band)"

    raise AssertionError(f"{joint} left [{low:.4f}, {high:.4f}] {_where(window)}: {int(outside.sum())} of "
                         f"{len(v)} {what} samples outside; first at {at(first)}, worst at {at(worst)}")


def _matches(event: dict, kind: str, window: tuple[float, float], detail: dict) -> bool:
    d = event.get("detail") or {}
    return (event["kind"] == kind and window[0] <= event["t"] <= window[1]
            and all(k in d and d[k] == v for k, v in detail.items()))


def _describe(event: dict) -> str:
    d = event.get("detail") or {}
    extra = " " + ", ".join(f"{k}={v!r}" for k, v in d.items()) if d else ""
    return f"{event['kind']} at t={event['t']:.3f} s{extra}"


def _listing(events: list[dict]) -> str:
    if not events:
        return "no events"
    lines = [_describe(e) for e in events[:MAX_LINES]]
    more = f"; … and {len(events) - MAX_LINES} more" if len(events) > MAX_LINES else ""
    return "; ".join(lines) + more


def assert_event(log: Any, kind: str, *, t: tuple[float | None, float | None] | None = None,
                 count: int | None = None, **detail) -> list[dict]:
    """An event of ``kind`` (``"armed"``, ``"stopped"``, ``"limit_clamp"``, ``"hardware_error"``, …) happened in the
    window ``t``, with ``detail`` among its details (``reason="duration"``); ``count``: exactly that many times.
    Returns the matching events (``{"t", "kind", "detail"}``)."""
    data = _data(log)
    window = _window(t)
    events = _events(data)
    found = [e for e in events if _matches(e, kind, window, detail)]
    if (count is None and found) or (count is not None and len(found) == count):
        return found
    want = f"{kind!r} event" + (f" with {', '.join(f'{k}={v!r}' for k, v in detail.items())}" if detail else "")
    times = "at least once" if count is None else f"{count} time(s), found {len(found)}"
    same = [e for e in events if e["kind"] == kind]
    seen = f"the {kind!r} events logged: {_listing(same)}" if same else f"the log's events: {_listing(events)}"
    raise AssertionError(f"expected a {want} {_where(window)} {times}; {seen}")


def assert_no_event(log: Any, kind: str, *, t: tuple[float | None, float | None] | None = None) -> None:
    """No event of ``kind`` happened in the window ``t``."""
    data = _data(log)
    window = _window(t)
    found = [e for e in _events(data) if _matches(e, kind, window, {})]
    if found:
        raise AssertionError(f"{len(found)} {kind!r} event(s) {_where(window)}: {_listing(found)}")


def faults_in(log: Any, *, comm_errors: int | None = 0) -> list[str]:
    """Every fault the log records (module doc), one line each, in time order. ``comm_errors``: failed bus
    transactions tolerated (None: any number); the failed reads and stale readings they cause are faults only
    beyond it."""
    data = _data(log)
    found: list[tuple[float, str]] = []
    comm: list[tuple[float, str]] = []
    events = _events(data)
    for e in events:
        if e["kind"] in FAULT_EVENTS:
            d = e.get("detail") or {}
            extra = " " + ", ".join(f"{k}={v!r}" for k, v in d.items()) if d else ""
            (comm if e["kind"] == "read_failed" else found).append((e["t"], f"t={e['t']:.3f} s: {e['kind']}{extra}"))
        elif e["kind"] == "torque_off" and not (e.get("detail") or {}).get("verified", True):
            found.append((e["t"], f"t={e['t']:.3f} s: torque was not read back off at the end"))
    hardware, stale, counts = _channel_faults(data, run_start(data))
    found += hardware
    comm += stale
    n_failed = max([n for _, n in counts] + [sum(e["kind"] == "read_failed" for e in events)])
    if comm_errors is not None and (n_failed > comm_errors or (comm and comm_errors == 0)):
        past = [t for t, n in counts if n > comm_errors]
        t_fail = past[0] if past else min(t for t, _ in comm)
        found += comm + [(t_fail, f"t={t_fail:.3f} s: {n_failed} failed bus transactions in all (allowed "
                                  f"{comm_errors}: assert_no_fault(..., comm_errors=N) tolerates N)")]
    end = max([float(t) - run_start(data) for t in data.t[-1:]] + [e["t"] for e in events] + [0.0])  # summary: last
    summary = data.summary or {}
    run = summary.get("run")
    if isinstance(run, dict) and run.get("ok") is False:
        found.append((end, f"the run stopped: {run.get('stopped')}"))
    if "error" in summary:
        found.append((end, f"the run was aborted: {summary['error']}"))
    return [line for _, line in sorted(found, key=lambda x: x[0])]


def _channel_faults(data: LogData, t0: float) -> tuple[list, list, list[tuple[float, int]]]:
    """From ``/faults`` (JSON, written when they change): each joint's first hardware error and each joint's first
    stale reading, as (t, line), and the count of failed transactions, as (t, count) where it changed; t in run
    time (robot clock − ``t0``)."""
    from felis.logs.reader import channel_messages  # late: the log reader
    from felis.servos import hardware_error_names

    hardware: list[tuple[float, str]] = []
    stale: list[tuple[float, str]] = []
    counts: list[tuple[float, int]] = []
    hw_seen: set[int] = set()
    stale_seen: set[int] = set()
    for t_log, m in channel_messages(data.path, {"/faults"}).get("/faults", []):
        t = t_log - t0
        for i, bits in enumerate(m.get("hardware") or []):
            if bits and i not in hw_seen and i < len(data.joints):
                hw_seen.add(i)
                names = "+".join(hardware_error_names(int(bits)))
                hardware.append((t, f"t={t:.3f} s: {data.joints[i]} reports hardware error {names} "
                                    f"(0x{int(bits):02x})"))
        for i, is_stale in enumerate(m.get("stale") or []):
            if is_stale and i not in stale_seen and i < len(data.joints):
                stale_seen.add(i)
                stale.append((t, f"t={t:.3f} s: {data.joints[i]} did not answer (stale reading)"))
        counts.append((t, int(m.get("comm_errors") or 0)))
    return hardware, stale, counts


def assert_no_fault(log: Any, *, comm_errors: int | None = 0) -> None:
    """The run recorded no fault (module doc); ``comm_errors``: failed bus transactions tolerated (None: any
    number, for a test that injects lost replies on purpose)."""
    data = _data(log)
    found = faults_in(data, comm_errors=comm_errors)
    if found:
        more = f"\n  … and {len(found) - MAX_LINES} more" if len(found) > MAX_LINES else ""
        raise AssertionError(f"{len(found)} fault(s) in {data.path.name}:\n  " + "\n  ".join(found[:MAX_LINES])
                             + more)
