"""System identification recovers known servo parameters (issue 4's acceptance figure).

A virtual bus (its own process, servos backed by the MuJoCo cat on a stand) runs with servo
parameters changed on purpose for the joints under test (kp ×1.4, damping ×0.7, armature ×2,
friction ×1.5, torque limit ×0.8). ``felis sysid --port virtual`` records step and chirp responses
through the whole hardware path (dynamixel-sdk, pty, `DynamixelRobot`) and fits. Printed per joint:
the fitted/true error of each parameter (goal: kp and damping within 10 %) and the step-response RMS
error with datasheet parameters against fitted ones (goal: ≥ 5× smaller). The anchor is the
datasheet model in the same run.

    python bench/sysid_recovery.py [--joints fl_pitch,tail_pitch] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from felis.calib.sysid import default_params, with_params
from felis.sim.servo_file import save_servo_params
from felis.spec import load_spec

CHANGE = {"kp": 1.4, "damping": 0.7, "armature": 2.0, "frictionloss": 1.5, "torque_limit": 0.8}
FIELDS = ("kp", "damping", "armature", "frictionloss", "torque_limit")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="cat")
    ap.add_argument("--joints", default="fl_pitch,tail_pitch")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    spec = load_spec(args.robot)
    joints = args.joints.split(",")
    truth = with_params({n: p for n, p in default_params(spec).items() if n in joints}, **CHANGE)
    with tempfile.TemporaryDirectory() as tmp:
        truth_file = Path(tmp) / "truth.json"
        save_servo_params(truth_file, spec.name, truth)
        out = Path(tmp) / "fit.json"
        cmd = [sys.executable, "-m", "felis", "sysid", "--robot", spec.name, "--joints", args.joints, "--port",
               "virtual", "--yes", "--json", "--virtual-servo-params", str(truth_file), "--out", str(out)]
        p = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, MUJOCO_GL="egl"))
        if p.returncode != 0:
            print(p.stderr, file=sys.stderr)
            return p.returncode
        res = json.loads(p.stdout)
    rows = []
    for name in joints:
        j = res["joints"][name]
        err = {f: 100.0 * (j["fitted"][f] / getattr(truth[name], f) - 1.0) for f in FIELDS}
        rows.append({"joint": name, "error_pct": err, "step_rms_default": j["step_rms_before"],
                     "step_rms_fitted": j["step_rms_after"], "ratio": j["step_improvement"]})
    ok = all(abs(r["error_pct"]["kp"]) <= 10 and abs(r["error_pct"]["damping"]) <= 10 and r["ratio"] >= 5
             for r in rows)
    if args.json:
        print(json.dumps({"rows": rows, "ok": ok}, indent=2))
        return 0 if ok else 1
    print(f"{'joint':12} " + " ".join(f"{f:>13}" for f in FIELDS) + "   step RMS default→fitted (mrad)  ratio")
    for r in rows:
        print(f"{r['joint']:12} " + " ".join(f"{r['error_pct'][f]:+12.1f}%" for f in FIELDS)
              + f"   {1e3 * r['step_rms_default']:8.2f} → {1e3 * r['step_rms_fitted']:6.2f}"
              + f"            {r['ratio']:5.1f}×")
    print("goals (kp, damping within 10 %; step RMS ≥ 5× smaller):", "met" if ok else "NOT met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
