"""``felis sim drop|render|view``: a simulated run of a robot, dropped or not, judged, logged, rendered
offscreen, or shown in MuJoCo's interactive viewer (needs a display).
"""

from __future__ import annotations

from pathlib import Path

from felis.cli.args import finite, group, json_option, live_option, size
from felis.cli.doctor import has_display
from felis.cli.results import episode, report
from felis.cli.run import drop_args
from felis.errors import FelisError, ParameterError


def register(sub) -> None:
    """Add ``felis sim drop``, ``render`` and ``view``."""
    simsub = group(sub, "sim", "simulation: drop, render, view", "sim_command", "SIM_COMMAND")

    def scenario_args(sp, need_height: bool):
        sp.add_argument("--robot", default="cat", help="robot name or description file (default cat)")
        sp.add_argument("--height", type=finite, required=need_height, help="drop height of the lowest point (m)")
        sp.add_argument("--roll", type=finite, default=0.0, help="initial roll (deg)")
        sp.add_argument("--pitch", type=finite, default=0.0, help="initial pitch (deg)")
        sp.add_argument("--yaw", type=finite, default=0.0, help="initial yaw (deg)")
        sp.add_argument("--controller", default=None,
                        help="controller during the run (default: landing for a dropped cat, else stand)")
        sp.add_argument("--duration", type=finite, default=2.0, help="simulated seconds (default 2)")
        sp.add_argument("--policy", metavar="caps+library|library|shipped|caps|FILE",
                        help="the landing controller's policy, as `felis run landing --policy` (default caps+library: "
                        "at 1 m and 3 m a vote by attitude between the cap policy made for that height and the motion "
                        "library)")

    drop = simsub.add_parser("drop", help="drop the robot and report how it lands")
    scenario_args(drop, need_height=True)
    drop.add_argument("--log", type=Path, help="write an MCAP log here (.mcap)")
    live_option(drop)
    drop.add_argument("--video", type=Path, help="render to this file (.mp4, .gif, .png)")
    json_option(drop)
    drop.add_argument("--servo-params", type=Path, metavar="FILE", help="servo parameters from `felis sysid`")
    drop.set_defaults(func=cmd_sim_drop)

    render = simsub.add_parser("render", help="render a run offscreen to MP4, GIF or PNG (film strip)")
    scenario_args(render, need_height=False)
    render.add_argument("--out", type=Path, required=True, help="output file: .mp4, .gif or .png")
    render.add_argument("--fps", type=finite, default=30.0, help="frames per second (default 30)")
    render.add_argument("--size", type=size, default=(640, 480), help="WIDTHxHEIGHT (default 640x480)")
    json_option(render)
    render.set_defaults(func=cmd_sim_render)

    view = simsub.add_parser("view", help="open the interactive viewer (needs a display)")
    scenario_args(view, need_height=False)
    view.set_defaults(func=cmd_sim_view)


def default_controller(args) -> str:
    """``--controller`` if given; else the landing skill for a cat that is dropped (the landing nets drive
    the cat's joints), else ``stand``."""
    from felis.spec import load_spec
    if args.controller:
        return args.controller
    from felis.learning.landing.policy import JOINTS

    dropped = getattr(args, "height", None) is not None
    return "landing" if dropped and tuple(load_spec(args.robot).names) == JOINTS else "stand"


def controller_options(args, controller: str) -> dict:
    """``--policy`` for the landing controller (which loads it: a bad one is one line, before anything runs), else
    {}."""
    if args.policy is None:
        return {}
    if controller != "landing":
        raise ParameterError(f"--policy belongs to the landing controller, not {controller}")
    return {"policy": Path(args.policy)}


def cmd_sim_drop(args) -> int:
    controller = default_controller(args)
    res = episode(args, robot=args.robot, controller=controller, duration=args.duration,
                  drop=(args.height, args.roll, args.pitch, args.yaw), log=args.log, video=args.video,
                  servo_params=args.servo_params, controller_options=controller_options(args, controller))
    return report(args, res)


def cmd_sim_render(args) -> int:
    controller = default_controller(args)
    res = episode(args, robot=args.robot, controller=controller, duration=args.duration,
                  drop=drop_args(args), video=args.out, fps=args.fps, size=args.size,
                  controller_options=controller_options(args, controller))
    return report(args, res)


def cmd_sim_view(args) -> int:
    from felis.controllers import make_controller
    from felis.loop import run_loop
    from felis.spec import load_spec
    if not has_display():
        raise FelisError("no display here (DISPLAY/WAYLAND_DISPLAY unset): the viewer cannot open; "
                         "use `felis sim render --out FILE.mp4` instead")
    import mujoco.viewer  # late: MuJoCo and its viewer, only for this command

    from felis.sim import MujocoRobot
    from felis.sim.scenarios import drop

    spec = load_spec(args.robot)
    name = default_controller(args)
    dropped = drop_args(args)
    options = controller_options(args, name)
    if name == "landing" and dropped is not None:
        options["drop_height"] = float(dropped[0])
    controller = make_controller(name, **options)
    with MujocoRobot(spec) as robot:
        if dropped is not None:
            drop(robot, *dropped)
        with mujoco.viewer.launch_passive(robot.model, robot.data) as viewer:

            class _Sync:
                def __call__(self, state, command):
                    if not viewer.is_running():
                        raise KeyboardInterrupt
                    viewer.sync()

            run_loop(robot, controller, duration=args.duration, clock="wall", monitors=[_Sync()])
    return 0
