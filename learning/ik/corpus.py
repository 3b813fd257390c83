"""Files of IK demonstrations: corpora as ``.npz`` (no pickle; `save_corpus`, `load_corpus`) and
demonstrations recorded from run logs of the arm (`recorded_demos`)."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from felis import armkin
from felis.controllers.arm_posture import DT
from felis.controllers.trajectories import Trajectory
from felis.errors import TrajectoryError
from felis.files import write_atomic
from felis.logs.reader import read_log

ARM_JOINTS = ("joint1", "joint2", "joint3", "joint4")
_FORMAT = "felis-ik-corpus"


def save_corpus(path: str | Path, corpus: Sequence[Trajectory]) -> Path:
    """Write a corpus as ``.npz`` (atomically, no pickle): arrays ``t`` (N,), ``p`` (N, 3), ``q`` (N, 4)
    (NaN for a trajectory without angles), ``start`` (n + 1,) frame offsets, and ``meta``, a JSON
    string {format, version, kinds, ids, has_q}."""
    path = Path(path)
    start = np.concatenate([[0], np.cumsum([len(tr.t) for tr in corpus])]).astype(np.int64)
    q_rows = [tr.q if tr.q is not None else np.full((len(tr.t), 4), np.nan) for tr in corpus]
    meta = {"format": _FORMAT, "version": 1, "kinds": [tr.kind for tr in corpus],
            "ids": [int(tr.ident) for tr in corpus], "has_q": [tr.q is not None for tr in corpus]}
    buf = io.BytesIO()
    np.savez(buf, t=np.concatenate([tr.t for tr in corpus]) if corpus else np.zeros(0),
             p=np.concatenate([tr.p for tr in corpus]) if corpus else np.zeros((0, 3)),
             q=np.concatenate(q_rows) if corpus else np.zeros((0, 4)), start=start, meta=np.array(json.dumps(meta)))
    return write_atomic(path, buf.getvalue(), "IK corpus", TrajectoryError)


def load_corpus(path: str | Path) -> list[Trajectory]:
    """Read a corpus written by `save_corpus`; TrajectoryError (one line) for a missing, corrupt or
    foreign file."""
    path = Path(path)
    if not path.exists():
        raise TrajectoryError(f"{path}: no such corpus file")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("t", "p", "q", "start", "meta") if k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise TrajectoryError(f"{path}: not a corpus .npz file ({e})") from None
    missing = [k for k in ("t", "p", "q", "start", "meta") if k not in arrays]
    if missing:
        raise TrajectoryError(f"{path}: not an IK corpus: missing array(s) {', '.join(missing)}")
    try:
        meta = json.loads(str(arrays["meta"]))
        kinds, ids, has_q = meta["kinds"], meta["ids"], meta["has_q"]
        if meta.get("format") != _FORMAT:
            raise ValueError(f"format {meta.get('format')!r}")
    except (ValueError, KeyError, TypeError) as e:
        raise TrajectoryError(f"{path}: not an IK corpus: bad meta ({e})") from None
    t, p, q, start = arrays["t"], arrays["p"], arrays["q"], arrays["start"]
    n_all = len(t)
    ok = (t.ndim == 1 and p.shape == (n_all, 3) and q.shape == (n_all, 4) and start.ndim == 1
          and len(start) == len(kinds) + 1 == len(ids) + 1 == len(has_q) + 1
          and start[0] == 0 and start[-1] == n_all and np.all(np.diff(start) >= 0))
    if not ok:
        raise TrajectoryError(f"{path}: IK corpus arrays have inconsistent shapes (t {t.shape}, p {p.shape}, "
                              f"q {q.shape}, start {start.shape}, {len(kinds)} trajectories)")
    return [Trajectory(t=t[a:b].copy(), p=p[a:b].copy(), q=q[a:b].copy() if hq else None, kind=str(k), ident=int(i))
            for a, b, k, i, hq in zip(start[:-1], start[1:], kinds, ids, has_q, strict=True)]



def recorded_demos(log_path: str | Path) -> Trajectory:
    """A demonstration from a run log of the arm: the measured joint angles q (joint1–4) and the tool
    points fk(q); kind ``recorded``, t the log's state times.

    TrajectoryError when the log is not of the arm (no joint1–4), was not recorded at 100 Hz, has
    fewer than 2 states, or has a non-finite angle; LogError when it cannot be read at all.
    """
    data = read_log(log_path)
    missing = [j for j in ARM_JOINTS if j not in data.joints]
    if missing:
        raise TrajectoryError(f"{data.path}: not a run log of the arm (robot {data.robot!r}, no joint(s) "
                              f"{', '.join(missing)})")
    rate = data.meta.get("rate_hz")
    if isinstance(rate, int | float) and abs(rate * DT - 1.0) > 0.1:
        raise TrajectoryError(f"{data.path}: recorded at {rate:g} Hz; IK demonstrations are 100 Hz")
    if len(data.t) < 2:
        raise TrajectoryError(f"{data.path}: {len(data.t)} state(s); a demonstration needs at least 2")
    q = data.q[:, [data.joints.index(j) for j in ARM_JOINTS]]
    bad = ~(np.all(np.isfinite(q), axis=1) & np.isfinite(data.t))
    if bad.any():
        i = int(np.argmax(bad))
        raise TrajectoryError(f"{data.path}: state {i} (t = {data.t[i]:g} s) has a missing or non-finite joint angle")
    return Trajectory(t=data.t.copy(), p=armkin.fk(q), q=q.copy(), kind="recorded", ident=-1)
