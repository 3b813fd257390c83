"""``felis log export LOG --csv DIR``: a run log's numbers as CSV files, for a spreadsheet.

One file per kind of data, each with a time column ``t`` (s of run time) and a header row:

- ``joint_states.csv``: ``<joint>.position``, ``<joint>.velocity`` (and ``<joint>.effort`` when logged) per joint;
- ``joint_commands.csv``: ``<joint>.position`` sent;
- ``imu.csv``: the IMU's orientation ``qw, qx, qy, qz`` and ``tilt_deg`` (when the robot has one);
- ``base.csv``: ``height`` (when known); ``contacts.csv``: one 0/1 column per foot (when fitted);
- ``events.csv``: ``t, kind, detail`` (the details as JSON);
- one file per other channel that carries numbers each tick (``balance.csv`` for ``/balance``, ``phase.csv`` for
  ``/phase``, ``timing.csv`` for ``/timing``, …): a column per number or flag, nested fields joined with dots
  (``xcom.x``); a field a message lacks is an empty cell. Once-only channels (``/meta``, ``/summary``, the
  verdicts) stay in the log.

Files are written whole to temporary names and moved into place (`felis.files.write_atomic`); NaN is an empty
cell.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from felis.errors import LogError
from felis.files import prepare_parent, write_atomic
from felis.logs.reader import channel_messages, read_log
from felis.rotations import tilt_deg


def _table(t: np.ndarray, columns: dict[str, np.ndarray]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t", *columns])
    cols = [np.asarray(c) for c in columns.values()]
    for i in range(len(t)):
        w.writerow([f"{t[i]:.6f}", *("" if (isinstance(v, float) and v != v) else (repr(v) if isinstance(v, float)
                                                                                     else v)
                                      for v in (c[i].item() for c in cols))])
    return buf.getvalue()


def _flat(msg: dict, prefix: str = "") -> dict:
    """Numbers and flags (as 0.0/1.0) of a message, nested objects joined with dots; strings and lists left out."""
    out = {}
    for k, v in msg.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        elif isinstance(v, bool | int | float):
            out[prefix + k] = float(v)
    return out


def export_csv(path: str | Path, out_dir: str | Path) -> list[Path]:
    """Write the CSV files of the log at ``path`` into ``out_dir`` (created); returns the files written."""
    data = read_log(path)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LogError(f"cannot export to {out}: it is a file, not a directory")
    prepare_parent(out / "x.csv", "CSV export", LogError)
    files: dict[str, str] = {}
    cols = {}
    for i, j in enumerate(data.joints):
        cols[f"{j}.position"] = data.q[:, i]
        cols[f"{j}.velocity"] = data.dq[:, i]
        if data.effort is not None:
            cols[f"{j}.effort"] = data.effort[:, i]
    files["joint_states.csv"] = _table(data.t, cols)
    files["joint_commands.csv"] = _table(data.cmd_t, {f"{j}.position": data.cmd_q[:, i]
                                                      for i, j in enumerate(data.joints)})
    if data.quat is not None:
        q = data.quat
        files["imu.csv"] = _table(data.t, {"qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
                                           "tilt_deg": np.asarray(tilt_deg(q), dtype=float)})
    if data.height is not None:
        files["base.csv"] = _table(data.t, {"height": data.height})
    if data.contacts is not None:
        files["contacts.csv"] = _table(data.t, {f: data.contacts[:, k].astype(int) for k, f in enumerate(data.feet)})
    done = {"/meta", "/summary", "/imu", "/contacts", "/base"}  # written above (or once-only)
    for topic, items in channel_messages(path).items():
        if topic in done or len(items) < 2:
            continue
        rows = [(t, _flat(m)) for t, m in items]
        names = list(dict.fromkeys(k for _, r in rows for k in r))
        if names:
            files[topic.strip("/").replace("/", "_") + ".csv"] = _table(
                np.array([t for t, _ in rows]), {k: np.array([r.get(k, np.nan) for _, r in rows], dtype=float)
                                                 for k in names})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["t", "kind", "detail"])
    for e in data.events:
        w.writerow([f"{e['t']:.6f}", e["kind"], json.dumps(e["detail"], separators=(",", ":"))])
    files["events.csv"] = buf.getvalue()
    written = []
    for name, text in files.items():
        write_atomic(out / name, text, "CSV export", LogError)
        written.append(out / name)
    return written
