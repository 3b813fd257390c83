"""``felis demo``: the tour, five runs into ``runs/<timestamp>/`` with logs, plots and videos: the cat
through the virtual Dynamixel bus (servo-in-the-loop), a simulated drop under the shipped landing policy, a hard
drop (tilted 143° from 3 m) under the same library (its shelf taken beyond 100° by continuation), the arm tracking a
figure eight with the learned IK, the standing cat pushed under the balance monitor.
"""

from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path

from felis.cli import output
from felis.cli.results import episode, exit_code, print_result
from felis.errors import ParameterError
from felis.shutdown import EXIT_INTERRUPTED

ARM_HOLD_S = 6.0  # the arm holds the figure eight's first point while its servos' I terms take up gravity


def register(sub) -> None:
    """Add ``felis demo``."""
    demo = sub.add_parser("demo", help="the cat through the virtual Dynamixel bus (servo-in-the-loop), then a "
                          "simulated drop, a hard drop, the arm tracking a figure eight with the learned IK, the cat "
                          "pushed under the balance monitor; logs, plots, video")
    demo.add_argument("--out", default="runs", help="directory for runs/<timestamp>/ (default: runs)")
    demo.add_argument("--no-video", action="store_true", help="skip rendering")
    demo.set_defaults(func=cmd_demo)


DEMO_DROP = (1.0, -50.0, -30.0, 0.0)  # height m, roll, pitch, yaw °: inside what the shipped policies land
HARD_DROP = (3.0, 145.0, -12.0, 0.0)  # tilted 143°: the library's motion lands it on time, up to 4 ticks late, 2° off


def cmd_demo(args) -> int:
    """Servo-in-the-loop: the cat stands up through the virtual Dynamixel bus backed by MuJoCo (the
    whole hardware code path: DynamixelRobot, SDK, pseudo-terminal, byte-level servos, physics);
    then the cat dropped tilted from 1 m under the landing controller's default policy (seed 000, issue 21: a vote
    by attitude between the shipped cap policy and motion library, which takes the library for this start), in
    MuJoCo, with video; then a hard drop, tilted 143° from 3 m, under the same controller (its 3 m vote takes the
    library too); then the arm tracking a figure eight with the
    learned IK pipeline (seed 001), with video; then the standing cat pushed, with the balance monitor's margin and
    alarm plotted (seed 004)."""
    root = Path(args.out)
    if root.exists() and not root.is_dir():
        raise ParameterError(f"{root} exists and is not a directory")
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    run_dir = root / stamp
    n = 1
    while run_dir.exists():
        n += 1
        run_dir = root / f"{stamp}-{n}"
    console = output.console()
    t0 = time.perf_counter()
    results = []
    for header, options in _episodes(run_dir, args.no_video):
        console.print(header)
        results.append(episode(args, **options()))
        print_result(results[-1], console)
        if results[-1].report.interrupted:
            return EXIT_INTERRUPTED
    console.print("[bold]felis demo 5/5[/]: the standing cat pushed sideways: the XCoM balance monitor's margin "
                  "and alarm, without a reaction and with the learned strategy selector (MuJoCo)")
    from felis.learning.balance.train import push_demo  # late: the push experiments (MuJoCo)

    push = push_demo(run_dir, video=not args.no_video)
    for name, r in push["runs"].items():
        lead = f", alarm {r['lead_s'] * 1000:.0f} ms before it" if r["lead_s"] else ""
        console.print(f"  {name}: {'fell (' + r['why'] + ')' if r['fell'] else 'stayed up'}{lead}; "
                      f"reaction {r['strategy']}; peak tilt {r['max_tilt_deg']:.0f}°")
    console.print("  " + ", ".join(f"{k}: {v}" for k, v in push["files"].items()))
    console.print(f"demo finished in {time.perf_counter() - t0:.1f} s; outputs in {run_dir}/")
    return max((exit_code(r.report) for r in results), default=0)


def _episodes(run_dir: Path, no_video: bool):
    """The tour's first four runs: (header, a function giving their `episode` keywords when the run comes)."""

    from felis.controllers.arm_track import run_time, trajectory_from
    from felis.drivers.ports import VIRTUAL
    def arm() -> dict:
        eight = trajectory_from("figure8")
        return dict(robot="arm", controller="arm-track", duration=run_time(eight, hold=ARM_HOLD_S),
                    controller_options={"trajectory": eight, "hold": ARM_HOLD_S}, log=run_dir / "arm_figure8.mcap",
                    video=None if no_video else run_dir / "arm_figure8.mp4", video_from=ARM_HOLD_S,
                    plot=run_dir / "arm_figure8.png", meta={"demo": True})

    return (
        ("[bold]felis demo 1/5[/]: the cat stands up through the virtual Dynamixel bus, its servos backed "
         "by MuJoCo (DynamixelRobot → dynamixel-sdk → pty → emulated servos → physics)",
         lambda: dict(robot="cat", controller="stand", duration=3.0, backend="dxl", port=VIRTUAL,
                      rate_hz=50.0, clock="wall", log=run_dir / "stand_dxl.mcap", plot=run_dir / "stand_dxl.png",
                      meta={"demo": True})),
        ("[bold]felis demo 2/5[/]: the cat dropped from 1 m tilted 56° (roll -50°, pitch -30°) under the "
         "landing controller's default policy (seed 000; MuJoCo): at release it reads its attitude from the IMU "
         "and takes whichever of two policies landed more training drops started near it: the cap policy's "
         "closed-loop nets of the paper's size (imitated from the motion library, then evolved) or the motion "
         "library itself, which it takes for this start. Held still, it lands on its "
         "back from this drop; see docs/landing.md for where landing fails",
         # 2.5 s: the 0.45 s fall, the bounce, and the cat settled on four feet (the verdict: touchdown + 0.5 s)
         lambda: dict(robot="cat", controller="landing", duration=2.5,
                      drop=DEMO_DROP, controller_options={"policy": None, "drop_height": DEMO_DROP[0]},
                      log=run_dir / "drop.mcap", video=None if no_video else run_dir / "drop.mp4",
                      plot=run_dir / "drop.png", meta={"demo": True})),
        ("[bold]felis demo 3/5[/]: a hard drop: the cat released tilted 143° (roll 145°, pitch −12°) from 3 m, nearly "
         "upside down, under the same landing controller, whose default votes from 3 m between the shipped "
         "motion library and the 3 m cap policy and takes the library here (MuJoCo): the whole-body motion that "
         "lands most often near the attitude at release. Beyond 100° the "
         "library's "
         "motions were found by continuation from those that land at the edge (felis train landing-library "
         "--extend); from 3 m it lands about three in four of the starts tilted 120–150° (docs/landing.md)",
         lambda: dict(robot="cat", controller="landing", duration=2.5, drop=HARD_DROP,
                      controller_options={"policy": None, "drop_height": HARD_DROP[0]},
                      log=run_dir / "hard_drop.mcap", video=None if no_video else run_dir / "hard_drop.mp4",
                      plot=run_dir / "hard_drop.png", meta={"demo": True})),
        ("[bold]felis demo 4/5[/]: the arm tracks a figure eight: targets → LSTM Motion Predictor → "
         "Posture Estimator → mean filter → exact refinement (MuJoCo; servos with PID 800/100/100, targets taken "
         "ahead by the servos' lag, 6 s at the first point while the I terms take up gravity; the video starts "
         "with the eight)", arm),
    )
