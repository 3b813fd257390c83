"""The servo monitor's export (``felis monitor --csv FILE --mcap FILE``): one sample of every watched servo
per tick.

CSV: one row per servo per sample, columns `FIELDS` (hardware errors joined by ``;``), flushed each
sample. MCAP: written by the run logs' writer (`felis.logs.runlog.JsonMcapWriter`: unchunked, flushed
each message, so a killed monitor leaves a readable file), topic ``/monitor`` with ``{"t", "servos":
[row, …]}`` at log time ``t`` (s since the monitor started, in ns), and a ``/meta`` message first (the
servo IDs, the robot when known) so ``felis log info`` reads it like a run log.
"""

from __future__ import annotations

import csv
from datetime import UTC, datetime
from pathlib import Path

from felis.errors import ParameterError
from felis.logs.runlog import JsonMcapWriter

FIELDS = ("t", "id", "stale", "position", "velocity", "current", "load", "temperature", "voltage",
          "status_error", "hardware_errors")

TOPICS: dict[str, tuple[str, dict]] = {
    "/meta": ("felis.Meta", {"type": "object", "properties": {
        "kind": {"type": "string"}, "ids": {"type": "array", "items": {"type": "integer"}},
        "joints": {"type": "array", "items": {"type": "string"}}, "felis_version": {"type": "string"},
        "started_utc": {"type": "string"}}}),
    "/monitor": ("felis.Monitor", {"type": "object", "properties": {"t": {"type": "number"},
                                                                     "servos": {"type": "array"}}}),
}


class MonitorExport:
    """CSV and/or MCAP export of monitor samples (either path may be None). Errors: `ParameterError`."""

    def __init__(self, csv_path: Path | None, mcap_path: Path | None, ids: list[int], robot: str | None = None):
        self._csv_f = self._csv = self._mcap = None
        try:
            if csv_path is not None:
                self._csv_f = open(csv_path, "w", newline="")  # noqa: SIM115 - closed in close()
                self._csv = csv.DictWriter(self._csv_f, fieldnames=FIELDS, extrasaction="ignore")
                self._csv.writeheader()
        except OSError as e:
            self.close()
            raise ParameterError(f"cannot write monitor export {e.filename}: {e.strerror or e}") from None
        if mcap_path is not None:
            import felis  # late: felis/__init__ may one day import felis.logs

            meta = {"kind": "monitor", **({"robot": robot} if robot else {}), "joints": [], "ids": list(ids),
                    "felis_version": felis.__version__,
                    "started_utc": datetime.now(UTC).isoformat(timespec="milliseconds")}
            try:
                self._mcap = JsonMcapWriter(mcap_path, TOPICS, meta, what="monitor export", error=ParameterError)
            except ParameterError:
                self.close()
                raise

    def write(self, t: float, rows: list[dict]) -> None:
        """One sample: ``rows`` (one dict per servo, `FIELDS` but ``t``) at ``t`` s."""
        if self._csv is not None:
            for r in rows:
                self._csv.writerow({"t": f"{t:.4f}", **{k: (";".join(v) if isinstance(v, list) else v)
                                                       for k, v in r.items()}})
            self._csv_f.flush()
        if self._mcap is not None:
            self._mcap.message("/monitor", t, {"t": t, "servos": rows})

    def close(self) -> None:
        if self._csv_f is not None:
            self._csv_f.close()
        if self._mcap is not None:
            self._mcap.close()
