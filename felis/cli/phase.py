"""``felis phase``: gait data for phase learning (`felis.learning.gait_data`).

::

    felis phase record --out FILE.npz [--set train|heldout|all] [--rate HZ] [--scale F] [--json]
    felis phase record --from-log RUN.mcap [--from-log RUN2.mcap …] --out FILE.npz [--rate HZ] [--json]

The first form records the default schedules in MuJoCo (deterministic; each recording keeps its set,
train or heldout, so a loader can pick one); ``--scale`` multiplies every segment's duration (e.g.
0.1 for a quick check). The second takes the joint trajectories of run logs, e.g. from
``felis run step-in-place --robot cat --backend dxl --port virtual --log run.mcap``, resampled onto a
uniform grid at the run's rate (or ``--rate``). Prints the recordings, their seconds and rate.
Nothing is written on an error (one line).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from felis.errors import ParameterError


def cmd_phase_record(args) -> int:
    from felis.files import check_target
    from felis.learning import gait_data

    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ParameterError(f"{out}: the gait-data file must end in .npz")
    check_target(out, "gait-data file", ParameterError)
    if args.rate is not None and not 1 <= args.rate <= 1000:
        raise ParameterError(f"--rate must be within 1…1000 Hz, got {args.rate:g}")
    t0 = time.perf_counter()
    if args.from_log:
        if args.set is not None or args.scale is not None:
            raise ParameterError("--set and --scale choose simulated recordings: leave them out with --from-log")
        recs = [gait_data.from_log(p, rate_hz=args.rate) for p in args.from_log]
        set_name = "log"
    else:
        scale = 1.0 if args.scale is None else args.scale
        if not 0 < scale <= 10:
            raise ParameterError(f"--scale must be within 0…10, got {scale:g}")
        set_name = args.set or "all"
        which = ["train", "heldout"] if set_name == "all" else [set_name]
        rate = 100.0 if args.rate is None else args.rate
        recs = [r for w in which for r in gait_data.record_set(w, rate_hz=rate, scale=scale)]
    path = gait_data.save_recordings(out, recs, set_name=set_name)
    wall = time.perf_counter() - t0
    rows = [{"name": r.name, "split": r.split, "source": r.source, "seconds": round(r.duration_s, 3),
             "samples": len(r.t), "rate_hz": r.rate_hz, "contacts": r.contacts is not None} for r in recs]
    total = sum(r.duration_s for r in recs)
    if args.json:
        print(json.dumps({"out": str(path), "set": set_name, "recordings": rows, "seconds": round(total, 3),
                          "wall_s": round(wall, 2)}, indent=1))
        return 0
    for row in rows:
        print(f"{row['name']} ({row['split']}): {row['seconds']:.1f} s, {row['samples']} samples at "
              f"{row['rate_hz']:g} Hz{'' if row['contacts'] else ', no contacts'}")
    print(f"{len(recs)} recording(s), {total:.1f} s in all, recorded in {wall:.1f} s → {path}")
    return 0


def register(sub, parser_class=None) -> None:
    """Add ``felis phase record`` to the ``felis`` sub-commands."""
    phase = sub.add_parser("phase", help="gait data for phase learning: record")
    phasesub = phase.add_subparsers(dest="phase_command", metavar="PHASE_COMMAND", parser_class=parser_class)
    phase.set_defaults(func=lambda a: phase.error("missing sub-command"))
    rec = phasesub.add_parser("record", help="record joint trajectories of the trotting cat (MuJoCo, the default "
                              "train/heldout schedules) or take them from run logs (--from-log)",
                              description="Record the cat stepping in place at several frequencies and lifts, "
                              "with transitions and standing (MuJoCo, deterministic), or take the joint "
                              "trajectories of run logs; write them to one .npz.")
    rec.add_argument("--out", type=Path, required=True, help="gait-data file to write (.npz)")
    rec.add_argument("--set", choices=["train", "heldout", "all"],
                     help="simulation: which default schedules (default all)")
    rec.add_argument("--from-log", type=Path, action="append", metavar="RUN.mcap",
                     help="take a run log instead of simulating (repeat for several)")
    rec.add_argument("--rate", type=float, help="samples per second (default: 100 in simulation, a log's run rate)")
    rec.add_argument("--scale", type=float, help="simulation: multiply every segment's duration (quick checks; "
                     "default 1)")
    rec.add_argument("--json", action="store_true", help="print the summary as JSON")
    rec.set_defaults(func=cmd_phase_record)
