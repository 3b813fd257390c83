"""The servo monitor's export (``felis monitor --csv FILE --mcap FILE [--live PORT]``): one sample of every
watched servo per tick.

CSV: one row per servo per sample, columns `FIELDS` (hardware errors joined by ``;``), flushed each sample.
MCAP (and the live view): written by the run logs' writer (`felis.logs.mcap.McapLog`: chunked, indexed,
flushed every ``FLUSH_S``, epoch-ns log times from the monitor's start, the same time base as run logs), with

- ``/meta`` first (kind "monitor", the servo IDs, their joint names, the robot when known), so ``felis log
  info`` reads it like a run log;
- ``/joint_states`` (``foxglove.JointStates``): each servo's position and velocity under its joint name (``id3``
  without a robot description), NaN for a servo that did not answer;
- ``/monitor`` (JSON, felis.Monitor): ``{"servos": [row, …]}``, a row's fields as in `FIELDS` (those a missing
  servo lacks are left out).
"""

from __future__ import annotations

import csv
import json
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from foxglove.messages import JointStates

from felis.errors import ParameterError
from felis.logs.mcap import McapLog
from felis.logs.schemas import jsonable
from felis.logs.wire import JointStatesEncoder

FIELDS = ("t", "id", "stale", "position", "velocity", "current", "load", "temperature", "voltage",
          "status_error", "hardware_errors")

_N = {"type": "number"}
MONITOR_SCHEMA = {"type": "object", "title": "felis.Monitor", "properties": {"servos": {"type": "array", "items": {
    "type": "object", "properties": {
        "id": {"type": "integer"}, "stale": {"type": "boolean"}, "position": _N, "velocity": _N, "current": _N,
        "load": _N, "temperature": _N, "voltage": _N, "status_error": {"type": "integer"},
        "hardware_errors": {"type": "array", "items": {"type": "string"}}}}}}}


class MonitorExport:
    """CSV and/or MCAP export of monitor samples (either path may be None; ``live`` a `felis.logs.live.LiveView`).
    Errors: `ParameterError`."""

    def __init__(self, csv_path: Path | None, mcap_path: Path | None, ids: list[int], robot: str | None = None,
                 joints: list[str] | None = None, live=None):
        self._csv_f = self._csv = self._mcap = None
        try:
            if csv_path is not None:
                self._csv_f = open(csv_path, "w", newline="")  # noqa: SIM115 - closed in close()
                self._csv = csv.DictWriter(self._csv_f, fieldnames=FIELDS, extrasaction="ignore")
                self._csv.writeheader()
        except OSError as e:
            self.close()
            raise ParameterError(f"cannot write monitor export {e.filename}: {e.strerror or e}") from None
        if mcap_path is not None or live is not None:
            import felis  # late: felis/__init__ may one day import felis.logs

            names = list(joints) if joints else [f"id{i}" for i in ids]
            meta = {"kind": "monitor", **({"robot": robot} if robot else {}), "joints": names, "ids": list(ids),
                    "felis_version": felis.__version__,
                    "started_utc": datetime.now(UTC).isoformat(timespec="milliseconds")}
            try:
                self._mcap = McapLog(mcap_path, meta, what="monitor export", error=ParameterError, live=live)
            except ParameterError:
                self.close()
                raise
            self._index = {i: k for k, i in enumerate(ids)}
            self._js = JointStatesEncoder(names, ("position", "velocity"))
            self._put_js = self._mcap.channel("/joint_states", JointStates.get_schema(), "protobuf")
            self._put_mon = self._mcap.channel("/monitor", MONITOR_SCHEMA)
            self._pv = np.full((2, len(ids)), np.nan)

    def write(self, t: float, rows: list[dict]) -> None:
        """One sample: ``rows`` (one dict per servo, `FIELDS` but ``t``) at ``t`` s."""
        if self._csv is not None:
            for r in rows:
                self._csv.writerow({"t": f"{t:.4f}", **{k: (";".join(v) if isinstance(v, list) else v)
                                                       for k, v in r.items()}})
            self._csv_f.flush()
        if self._mcap is not None:
            log = self._mcap
            ns = log.ns(t)
            log._tick(ns)
            pv = self._pv
            pv[:] = np.nan
            for r in rows:
                k = self._index.get(r.get("id"))
                if k is not None and not r.get("stale"):
                    pv[0, k] = r.get("position") if r.get("position") is not None else np.nan
                    pv[1, k] = r.get("velocity") if r.get("velocity") is not None else np.nan
            self._put_js(ns, self._js.encode(ns, pv))
            self._put_mon(ns, json.dumps(jsonable({"servos": rows}), separators=(",", ":")).encode())

    def close(self) -> None:
        if self._csv_f is not None:
            self._csv_f.close()
        if self._mcap is not None:
            self._mcap.close()
