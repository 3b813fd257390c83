"""The step response of one arm joint (joint2, the shoulder, under gravity) with the firmware's controller as shipped
(P/I/D 800/100/100, `felis.sim.servo.controller`) against the P-only model felis had before (P 800, I = D = 0):
a 0.3 rad step from the ready pose, 4 s, MuJoCo at 1 kHz. Writes a PNG (matplotlib, Agg) and prints the steady
errors.

    MUJOCO_GL=egl python bench/servo_step.py [--out servo_step.png] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from felis.hal import Command
from felis.sim.robot import MujocoRobot
from felis.spec import load_spec

JOINT, STEP, SECONDS, DT = "joint2", 0.3, 4.0, 0.01


def response(pid: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    spec = load_spec("arm")
    joints = tuple(dataclasses.replace(j, pid=pid) if j.name.startswith("joint") else j for j in spec.joints)
    spec = dataclasses.replace(spec, joints=joints)
    r = MujocoRobot(spec, quantize=False)
    r.connect()
    r.arm()
    i = spec.index(JOINT)
    q = spec.pose("stand")
    r.write(Command(q=q))
    r.advance(3.0)  # settle on the start pose (the integral takes up gravity)
    goal = q.copy()
    goal[i] += STEP
    t, y = [], []
    t0 = r.read().t
    for _ in range(int(SECONDS / DT)):
        r.write(Command(q=goal))
        r.advance(DT)
        s = r.read()
        t.append(s.t - t0)
        y.append(s.q[i] - q[i])
    r.close()
    return np.array(t), np.array(y)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="servo_step.png")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    t, full = response((800, 100, 100))
    _, ponly = response((800, 0, 0))
    out = {"joint": JOINT, "step_rad": STEP,
           "final_error_mrad": {"pid_800_100_100": float((STEP - full[-1]) * 1e3),
                                "p_only_800": float((STEP - ponly[-1]) * 1e3)},
           "png": args.out}
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    ax.axhline(STEP, color="0.6", lw=0.8, ls="--", label="goal")
    ax.plot(t, ponly, label="P only (P 800), felis before")
    ax.plot(t, full, label="firmware controller, P/I/D 800/100/100")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{JOINT} − start (rad)")
    ax.set_title("arm shoulder, 0.3 rad step under gravity (MuJoCo)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(json.dumps(out, indent=2) if args.json else
          f"{JOINT} step {STEP} rad: steady error P only {out['final_error_mrad']['p_only_800']:.2f} mrad, "
          f"PID {out['final_error_mrad']['pid_800_100_100']:.2f} mrad; plot {args.out}")


if __name__ == "__main__":
    main()
