"""Gait data for a periodic autoencoder (phase learning): joint trajectories of the cat trotting in place
at several frequencies and lifts, with transitions between them and standing in between, recorded in
simulation, or taken from run logs (hardware or the virtual bus).

**Simulation** (`record_sim`): the MuJoCo cat (`felis.sim.MujocoRobot`) in `felis.loop.run_loop` at
``rate_hz`` under `SteppingController.scheduled` (the schedule's phase is the integral of the commanded
frequency, continuous through changes; the lift ramps between segments; see
`felis.controllers.stepping`). Every tick records the state's time, joint positions and foot contacts,
and the gait clock at that time (the clock itself, not the command's 40 ms lead):

* ``clock_phase`` φ ∈ [0, 1) while the gait steps (0 = start of the fl+hr swing), NaN while standing;
* ``frequency_hz`` the commanded step frequency while stepping, 0 while standing;
* ``amplitude`` the commanded lift angle ℓ(t) in rad (`Gait.lift`: ramp level × lift), 0 while standing;
* ``stepping`` whether the periodic gait runs.

MuJoCo is deterministic: the same schedule at the same rate gives bit-identical arrays.

**Default sets** (`TRAIN`, `HELDOUT`): named schedules of (duration_s, frequency_hz, lift) segments, each
starting with ≥ 1 s standing. TRAIN covers 1.5–2.5 Hz (1.5, 1.75, 2.0, 2.25, 2.5) and lifts 0.35–0.65 rad
(0.35, 0.4, 0.5, 0.55, 0.65) with frequency and lift changes and stands in between (≈ 3 min); HELDOUT
uses values TRAIN never holds (1.6, 2.2, 2.4 Hz; lifts 0.45, 0.6 rad) inside those ranges (≈ 1 min),
among them stand → trot → another frequency → stand. The stepping controller is tuned for this range;
every setting here keeps the cat upright (`record_sim` refuses a recording in which it tipped over).

**Step frequency from contacts** (`contact_frequency`): per foot, touchdowns are the rising edges of
the contact signal after closing contact gaps shorter than ``min_gap_s`` (40 ms; a foot that bounces or
flickers is still down) and dropping touches shorter than that (the trotting cat's fore feet brush the
floor for a tick some 60 ms before they land, which would otherwise count twice per cycle); the foot's
cycle frequency is 1 / median interval between touchdowns and the result is the median over the feet.
Each foot lands once per gait cycle, so this is the cycle frequency, the same quantity as the stepping
controller's commanded ``frequency_hz``. At 100 Hz a touchdown time is known to ±10 ms, so a single
interval to ±2 % at 2 Hz; the medians keep the estimate within that (measured: ≤ 2.1 % over every
steady segment of the default sets, most within 1 %).

**Logs** (`from_log`): a felis run log (MCAP, `felis.logs.reader.read_log`); the states' t, q and foot contacts
(when logged; the virtual bus and the servos report none), resampled by linear interpolation (nearest
sample for contacts) onto a uniform grid at the run's rate when the times are irregular (a wall-clock
run). The clock fields are unknown: NaN phase, zero frequency and amplitude, stepping False.

**Files** (`save_recordings`, `load_recordings`): one ``.npz`` (no pickle) with the recordings
concatenated (``t``, ``q``, ``contacts``, ``clock_phase``, ``frequency_hz``, ``amplitude``,
``stepping``, ``start`` offsets) and a JSON ``meta`` member (format, version, joints, and per
recording its name, source, split and rate). Units: seconds, radians, hertz.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from felis.controllers.stepping import SteppingController, check_segments
from felis.errors import LogError, PhaseError

FORMAT = "felis-gait-data"
VERSION = 1
MIN_LOG_S = 2.0  # s: a shorter log holds too few cycles to learn a phase from
MIN_GAP_S = 0.04  # s: contact gaps shorter than this are flicker, not a lift-off
FELL_TILT_DEG = 30.0  # body tilt past which a recording counts as tipped over

Schedule = tuple[tuple[float, float, float], ...]

TRAIN: dict[str, Schedule] = {
    "train-frequencies": ((1.5, 0.0, 0.0), (6.0, 2.0, 0.5), (6.0, 1.5, 0.5), (6.0, 2.5, 0.5), (6.0, 1.75, 0.5),
                          (2.0, 0.0, 0.0)),
    "train-lifts": ((1.5, 0.0, 0.0), (6.0, 2.0, 0.35), (6.0, 2.0, 0.65), (6.0, 2.0, 0.5), (2.0, 0.0, 0.0),
                    (6.0, 2.25, 0.4), (1.5, 0.0, 0.0)),
    "train-corners": ((1.0, 0.0, 0.0), (6.0, 1.5, 0.35), (6.0, 1.5, 0.65), (2.0, 0.0, 0.0), (6.0, 2.5, 0.35),
                      (6.0, 2.5, 0.65), (1.5, 0.0, 0.0)),
    "train-changes": ((1.5, 0.0, 0.0), (5.0, 2.25, 0.55), (5.0, 1.75, 0.4), (5.0, 2.0, 0.65), (5.0, 2.5, 0.4),
                      (5.0, 1.5, 0.55), (2.0, 0.0, 0.0)),
    "train-start-stop": ((1.0, 0.0, 0.0), (4.0, 2.0, 0.5), (2.0, 0.0, 0.0), (4.0, 1.5, 0.4), (2.0, 0.0, 0.0),
                         (4.0, 2.5, 0.55), (2.0, 0.0, 0.0), (4.0, 1.75, 0.65), (2.0, 0.0, 0.0)),
    "train-long": ((1.0, 0.0, 0.0), (12.0, 2.0, 0.5), (10.0, 2.25, 0.35), (10.0, 1.75, 0.55), (2.0, 0.0, 0.0)),
}
HELDOUT: dict[str, Schedule] = {
    "heldout-frequency-change": ((1.5, 0.0, 0.0), (8.0, 1.6, 0.45), (8.0, 2.4, 0.45), (2.0, 0.0, 0.0)),
    "heldout-lift-change": ((1.5, 0.0, 0.0), (8.0, 2.2, 0.6), (8.0, 2.2, 0.45), (2.0, 0.0, 0.0)),
    "heldout-mixed": ((1.0, 0.0, 0.0), (6.0, 2.4, 0.6), (2.0, 0.0, 0.0), (6.0, 1.6, 0.6), (6.0, 2.2, 0.45),
                      (1.5, 0.0, 0.0)),
}
SETS = {"train": TRAIN, "heldout": HELDOUT}


@dataclass
class GaitRecording:
    """One recording on a uniform time grid: T samples of J joints (and C foot contacts, when known)."""

    t: np.ndarray  # (T,) s
    q: np.ndarray  # (T, J) joint positions, rad, in the order of ``joints``
    joints: tuple[str, ...]
    rate_hz: float
    contacts: np.ndarray | None  # (T, C) bool, feet (fl, fr, hl, hr); None when not measured
    clock_phase: np.ndarray  # (T,) gait clock φ ∈ [0, 1) while stepping; NaN standing or unknown
    frequency_hz: np.ndarray  # (T,) commanded step (cycle) frequency; 0 standing or unknown
    amplitude: np.ndarray  # (T,) commanded lift angle, rad; 0 standing or unknown
    stepping: np.ndarray  # (T,) bool: the periodic gait runs
    name: str
    source: str  # "sim" | "log"
    split: str = ""  # "train", "heldout", "log" or "" (which set the recording belongs to)

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0

    def check(self, where: str = "") -> None:
        """PhaseError (one line) if the arrays' shapes or types disagree."""
        n, j = len(self.t), len(self.joints)
        shapes = {"t": (self.t, (n,)), "q": (self.q, (n, j)), "clock_phase": (self.clock_phase, (n,)),
                  "frequency_hz": (self.frequency_hz, (n,)), "amplitude": (self.amplitude, (n,)),
                  "stepping": (self.stepping, (n,))}
        if self.contacts is not None:
            shapes["contacts"] = (self.contacts, (n, self.contacts.shape[-1] if self.contacts.ndim == 2 else -1))
        for key, (a, shape) in shapes.items():
            if np.shape(a) != shape:
                raise PhaseError(f"{where or self.name}: {key} has shape {np.shape(a)}, expected {shape}")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise PhaseError(f"{where or self.name}: rate_hz must be a positive number, got {self.rate_hz}")


# ---------------------------------------------------------------------------------------------- simulation


def record_sim(segments: Sequence[tuple[float, float, float]], name: str = "sim", rate_hz: float = 100.0,
               split: str = "") -> GaitRecording:
    """Run the MuJoCo cat through ``segments`` (duration_s, frequency_hz, lift) of the scheduled stepping
    controller, from the 0.3 s blend into ``stand`` to the end of the last segment, and record every tick.

    PhaseError if the rate is outside 1…1000 Hz, the run stops early, or the cat tips over (body tilt
    > 30°); ParameterError for a bad schedule.
    """
    from felis.loop import run_loop
    from felis.sim import MujocoRobot
    from felis.spec import load_spec

    if not (isinstance(rate_hz, int | float) and 1.0 <= rate_hz <= 1000.0):
        raise PhaseError(f"record rate must be within 1…1000 Hz (a tick of at least 1 ms), got {rate_hz!r}")
    controller = SteppingController.scheduled(check_segments(segments))
    spec = load_spec("cat")
    rows: list[tuple] = []
    qs: list[np.ndarray] = []
    with MujocoRobot(spec) as robot:
        root = robot.root_body

        def record(state, command) -> None:
            g = controller.gait(state.t)
            tilt = math.degrees(math.acos(min(1.0, max(-1.0, float(robot.data.xmat[root][8])))))
            qs.append(np.array(state.q, dtype=float))
            rows.append((state.t, *state.contacts, g.phase if g.stepping else math.nan,
                         g.frequency_hz if g.stepping else 0.0, g.lift, g.stepping, tilt))

        report = run_loop(robot, controller, duration=controller.end_s, rate_hz=rate_hz, clock="sim",
                          monitors=[record]).raise_if_interrupted()
    if not report.ok or report.stopped != "duration":
        raise PhaseError(f"recording {name!r} stopped early: {report.stopped}")
    a = np.array(rows, dtype=float)
    tilt = a[:, 9]
    if tilt.max() > FELL_TILT_DEG:
        k = int(np.argmax(tilt > FELL_TILT_DEG))
        raise PhaseError(f"recording {name!r}: the cat tipped over (tilt {tilt[k]:.0f}° at t = {a[k, 0]:.2f} s); "
                         "use frequencies within 1.5…2.5 Hz and lifts near 0.5 rad")
    return GaitRecording(t=a[:, 0], q=np.array(qs), joints=tuple(spec.names), rate_hz=float(rate_hz),
                         contacts=a[:, 1:5] > 0.5, clock_phase=a[:, 5], frequency_hz=a[:, 6], amplitude=a[:, 7],
                         stepping=a[:, 8] > 0.5, name=name, source="sim", split=split)


def record_set(which: str, rate_hz: float = 100.0, scale: float = 1.0) -> list[GaitRecording]:
    """The recordings of a default set: ``"train"`` (`TRAIN`) or ``"heldout"`` (`HELDOUT`).

    ``scale`` multiplies every segment's duration (e.g. 0.1 for a quick check; 1 = the set as defined).
    """
    if which not in SETS:
        raise PhaseError(f"unknown gait set {which!r}; known: {', '.join(SETS)}")
    if not (isinstance(scale, int | float) and 0 < scale <= 10):
        raise PhaseError(f"scale must be within 0…10, got {scale!r}")
    return [record_sim([(d * scale, f, lift) for d, f, lift in segs], name=name, rate_hz=rate_hz, split=which)
            for name, segs in SETS[which].items()]


def schedule_seconds(schedules: dict[str, Schedule]) -> float:
    """Total scheduled time of a set of schedules, s (each recording adds the 0.3 s blend into stand)."""
    return float(sum(d for segs in schedules.values() for d, _, _ in segs))


# ---------------------------------------------------------------------------------------------- contacts


def contact_frequency(rec: GaitRecording, t0: float | None = None, t1: float | None = None,
                      min_gap_s: float = MIN_GAP_S) -> float:
    """The measured step (cycle) frequency, Hz, over t0 ≤ t ≤ t1 (default: the whole recording).

    Per foot: contact gaps shorter than ``min_gap_s`` are closed (a foot that bounces or flickers stays
    down), then touches shorter than ``min_gap_s`` are dropped (a swinging foot that brushes the floor
    has not landed); touchdowns are the rising edges that remain, f_foot = 1 / median(Δt between
    touchdowns). Returns the median over the feet that have ≥ 3 touchdowns in the window; NaN if none
    has (standing, or no contacts recorded). Each foot lands once per cycle: this is the per-foot cycle
    frequency, the quantity the stepping controller commands.
    """
    if rec.contacts is None:
        return math.nan
    lo = -math.inf if t0 is None else t0
    hi = math.inf if t1 is None else t1
    keep = (rec.t >= lo) & (rec.t <= hi)
    t, contacts = rec.t[keep], rec.contacts[keep]
    rates = []
    for foot in contacts.T:
        down = _debounce(t, foot, min_gap_s)
        touchdowns = t[1:][down[1:] & ~down[:-1]]
        if len(touchdowns) >= 3:
            rates.append(1.0 / float(np.median(np.diff(touchdowns))))
    return float(np.median(rates)) if rates else math.nan


def _debounce(t: np.ndarray, down: np.ndarray, min_s: float) -> np.ndarray:
    """``down`` with short runs removed: first every gap (run of False between two True samples) that
    lasts < ``min_s`` is closed, then every touch (run of True between two False samples) that lasts
    < ``min_s`` is dropped. A run lasts from its first sample to the first sample after it."""
    out = down.astype(bool)
    for value in (False, True):
        edges = np.flatnonzero(out[1:] != out[:-1]) + 1  # first sample of each new run
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if out[a] == value and t[b] - t[a] < min_s:
                out[a:b] = not value
    return out


# ---------------------------------------------------------------------------------------------- logs


def from_log(path: str | Path, rate_hz: float | None = None, name: str | None = None) -> GaitRecording:
    """A recording from a felis run log: t, q and contacts (when logged) of its ``/joint_states`` and
    ``/contacts`` messages, on a
    uniform grid at ``rate_hz`` (default: the run's rate from the log's summary, else its ``/meta``
    rate_hz); resampled (q linear, contacts nearest) only when the logged times are not already on it.

    PhaseError (one line) for a missing file, a file that is not a felis run log, no state messages,
    non-increasing times, less than 2 s of states, or a NaN joint value (naming the joint and time).
    """
    from felis.logs.reader import read_log

    path = Path(path)
    try:
        data = read_log(path)
    except LogError as e:
        raise PhaseError(str(e)) from None
    t = data.t
    if len(t) == 0:
        raise PhaseError(f"{path}: no /joint_states messages: the run logged no joint positions")
    if not np.isfinite(t).all():
        raise PhaseError(f"{path}: /joint_states message {int(np.argmax(~np.isfinite(t)))} has no time")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        raise PhaseError(f"{path}: state times do not increase at message {back[0] + 1} (t = {t[back[0] + 1]:.4f} s)")
    if data.duration < MIN_LOG_S:
        raise PhaseError(f"{path}: only {data.duration:.2f} s of states; a gait recording needs ≥ {MIN_LOG_S:g} s")
    bad = np.argwhere(~np.isfinite(data.q))
    if bad.size:
        k, j = bad[0]
        raise PhaseError(f"{path}: joint {data.joints[j]} has no value (NaN) at t = {t[k]:.3f} s")
    rate = _log_rate(data) if rate_hz is None else rate_hz
    if not (isinstance(rate, int | float) and math.isfinite(rate) and 0 < rate <= 10_000):
        raise PhaseError(f"{path}: rate must be a positive number of Hz, got {rate!r}")
    rate = float(rate)
    contacts = _logged_contacts(data, len(t))
    dt = 1.0 / rate
    q = data.q
    if not np.allclose(np.diff(t), dt, rtol=0.0, atol=1e-3 * dt):
        grid = t[0] + np.arange(int(math.floor((t[-1] - t[0]) * rate + 1e-9)) + 1) * dt
        q = np.stack([np.interp(grid, t, q[:, j]) for j in range(q.shape[1])], axis=1)
        if contacts is not None:
            right = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
            nearest = np.where(grid - t[right - 1] <= t[right] - grid, right - 1, right)
            contacts = contacts[nearest]
        t = grid
    n = len(t)
    return GaitRecording(t=t, q=q, joints=tuple(data.joints), rate_hz=rate, contacts=contacts,
                         clock_phase=np.full(n, np.nan), frequency_hz=np.zeros(n), amplitude=np.zeros(n),
                         stepping=np.zeros(n, dtype=bool), name=name or path.stem, source="log", split="log")


def _log_rate(data) -> float | None:
    """The run's control rate: the summary's (what the loop ran at) if there is one, else /meta's."""
    run = (data.summary or {}).get("run") if isinstance(data.summary, dict) else None
    if isinstance(run, dict) and isinstance(run.get("rate_hz"), int | float):
        return float(run["rate_hz"])
    rate = data.meta.get("rate_hz")
    return float(rate) if isinstance(rate, int | float) else rate


def _logged_contacts(data, n: int) -> np.ndarray | None:
    """(n, C) foot contacts of the log's states (``/contacts``), or None when some state lacks them."""
    if data.contacts is None or data.counts.get("/contacts", 0) != n or data.contacts.shape[1] == 0:
        return None
    return data.contacts


# ---------------------------------------------------------------------------------------------- files


def save_recordings(path: str | Path, recs: Sequence[GaitRecording], set_name: str = "") -> Path:
    """Write ``recs`` to one ``.npz`` (atomically, no pickle); ``set_name`` (e.g. "all") goes into the
    meta. All recordings must have the same joints and the same number of contacts (or none)."""
    from felis.files import write_atomic

    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise PhaseError(f"{path}: a gait-data file must end in .npz")
    recs = list(recs)
    if not recs:
        raise PhaseError(f"{path}: no recordings to save")
    for r in recs:
        r.check()
    joints = recs[0].joints
    other = next((r for r in recs if r.joints != joints), None)
    if other is not None:
        raise PhaseError(f"{path}: recording {other.name!r} has joints {list(other.joints)}, "
                         f"{recs[0].name!r} has {list(joints)}; save them to separate files")
    widths = {r.contacts.shape[1] for r in recs if r.contacts is not None}
    if len(widths) > 1:
        raise PhaseError(f"{path}: recordings have different numbers of foot contacts {sorted(widths)}")
    width = widths.pop() if widths else 0
    start = np.concatenate([[0], np.cumsum([len(r.t) for r in recs])]).astype(np.int64)
    meta = {"format": FORMAT, "version": VERSION, "set": set_name, "joints": list(joints), "contacts": width,
            "recordings": [{"name": r.name, "source": r.source, "split": r.split, "rate_hz": r.rate_hz,
                            "has_contacts": r.contacts is not None} for r in recs]}
    contacts = [r.contacts if r.contacts is not None else np.zeros((len(r.t), width), dtype=bool) for r in recs]
    arrays = {"t": np.concatenate([r.t for r in recs]).astype(float),
              "q": np.concatenate([r.q for r in recs]).astype(float),
              "contacts": np.concatenate(contacts).astype(bool),
              "clock_phase": np.concatenate([r.clock_phase for r in recs]).astype(float),
              "frequency_hz": np.concatenate([r.frequency_hz for r in recs]).astype(float),
              "amplitude": np.concatenate([r.amplitude for r in recs]).astype(float),
              "stepping": np.concatenate([r.stepping for r in recs]).astype(bool),
              "start": start, "meta": np.array(json.dumps(meta, allow_nan=False))}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return write_atomic(path, buf.getvalue(), "gait-data file", PhaseError)


_ARRAYS = ("t", "q", "contacts", "clock_phase", "frequency_hz", "amplitude", "stepping", "start", "meta")


def load_recordings(path: str | Path, split: str | None = None) -> list[GaitRecording]:
    """The recordings of a file written by `save_recordings`; with ``split`` ("train", "heldout", "log")
    only those. PhaseError (one line) for a missing, corrupt, foreign or inconsistent file."""
    from felis.files import read_npz

    path = Path(path)
    data = read_npz(path, "gait-data", PhaseError)
    missing = [k for k in _ARRAYS if k not in data]
    if missing:
        raise PhaseError(f"{path}: not a gait-data file: missing array(s) {', '.join(missing)}")
    raw = data["meta"]
    try:
        if raw.dtype.kind != "U" or raw.shape != ():
            raise ValueError("not a text string")
        meta = json.loads(str(raw))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format') if isinstance(meta, dict) else None!r}")
        if meta.get("version") != VERSION:
            raise ValueError(f"version {meta.get('version')!r} (felis reads {VERSION})")
        joints = tuple(str(j) for j in meta["joints"])
        items = [(str(r["name"]), str(r["source"]), str(r["split"]), float(r["rate_hz"]), bool(r["has_contacts"]))
                 for r in meta["recordings"]]
        width = int(meta["contacts"])
    except (ValueError, KeyError, TypeError) as e:
        raise PhaseError(f"{path}: not a gait-data file: bad meta ({' '.join(str(e).split())[:160]})") from None
    start = data["start"]
    n = len(data["t"])
    ok = (start.ndim == 1 and start.dtype.kind in "iu" and len(start) == len(items) + 1 and len(items) > 0
          and start[0] == 0 and start[-1] == n and bool(np.all(np.diff(start) > 0))
          and data["q"].shape == (n, len(joints)) and data["contacts"].shape == (n, width)
          and all(data[k].shape == (n,) for k in ("t", "clock_phase", "frequency_hz", "amplitude", "stepping"))
          and data["contacts"].dtype == bool and data["stepping"].dtype == bool)
    if not ok:
        raise PhaseError(f"{path}: gait-data arrays are inconsistent (t {data['t'].shape}, q {data['q'].shape}, "
                         f"start {start.shape}, {len(items)} recordings, {len(joints)} joints); corrupt file")
    if not (np.isfinite(data["t"]).all() and np.isfinite(data["q"]).all()):
        raise PhaseError(f"{path}: t or q holds non-finite values; corrupt file")
    splits = sorted({s for _, _, s, _, _ in items})
    if split is not None and split not in splits:
        raise PhaseError(f"{path}: no recordings of split {split!r}; the file holds {', '.join(splits)}")
    out = []
    for (name, source, sp, rate, has_c), a, b in zip(items, start[:-1], start[1:], strict=True):
        if split is not None and sp != split:
            continue
        rec = GaitRecording(t=data["t"][a:b].copy(), q=data["q"][a:b].copy(), joints=joints, rate_hz=rate,
                            contacts=data["contacts"][a:b].copy() if has_c else None,
                            clock_phase=data["clock_phase"][a:b].copy(), frequency_hz=data["frequency_hz"][a:b].copy(),
                            amplitude=data["amplitude"][a:b].copy(), stepping=data["stepping"][a:b].copy(),
                            name=name, source=source, split=sp)
        rec.check(f"{path}: recording {name!r}")
        out.append(rec)
    return out
