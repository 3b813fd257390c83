"""Running an episode from a command and reporting it: ``felis run``, ``felis sim drop|render``, ``felis demo``.

`episode` runs one (`felis.cli.episode`) with a progress bar unless ``--json``; `report` prints its
result as JSON or text and gives the exit code: 0, 1 when a failure stopped the run (the reason also
on standard error), 130 when a signal did.
"""

from __future__ import annotations

from felis.cli import output
from felis.shutdown import EXIT_INTERRUPTED


def episode(args, **kw):
    """Run `Episode(**kw)`; a progress bar over its time unless the command prints JSON."""
    from felis.cli.episode import Episode, run_episode
    if getattr(args, "live", None) is not None:
        kw.setdefault("live", args.live)
        kw.setdefault("on_live", output.live)
    ep = Episode(**kw)
    progress = None
    if not getattr(args, "json", False):
        progress = output.LoopProgress(f"{ep.robot} {ep.controller}", ep.duration)
        ep.progress = progress
    try:
        return run_episode(ep)
    finally:
        if progress is not None:
            progress.stop()


def report(args, res) -> int:
    """Print an episode's result (JSON or text); exit code 1 if a failure stopped it (the reason also on
    stderr), 130 if a signal did."""
    if args.json:
        output.print_json(res.as_dict())
    else:
        print_result(res, output.console())
    return exit_code(res.report)


def exit_code(report) -> int:
    if report.interrupted:
        return EXIT_INTERRUPTED
    if not report.ok:
        output.error(f"run stopped: {report.stopped}")
        return output.EXIT_ERROR
    return 0


def print_result(res, console) -> None:
    r = res.report
    t = r.timing
    console.print(f"[bold]{r.robot}[/] · controller {r.controller} · {r.ticks} ticks at {r.rate_hz:g} Hz "
                  f"({r.sim_time_s:.2f} s simulated in {r.wall_time_s:.2f} s) · stopped: {r.stopped}")
    console.print(f"loop: control path mean {t.mean_ms:.3f} ms, p99 {t.p99_ms:.3f} ms, max {t.max_ms:.3f} ms; "
                  f"{t.overruns} overruns of the {t.period_ms:g} ms period; monitors+log {t.monitors_mean_ms:.2f} "
                  f"ms/tick; safety: {r.safety}")
    comm_bad = r.read_failures or r.stale_ticks or r.write_failures or any(r.comm.values())
    if r.comm or comm_bad:
        c = r.comm
        colour = "yellow" if comm_bad else "green"
        console.print(f"[{colour}]communication: {r.read_failures} read failures, {r.stale_ticks} stale ticks, "
                      f"{r.write_failures} write failures; {c.get('retries', 0)} retries, {c.get('timeouts', 0)} "
                      f"timeouts, {c.get('corrupt', 0)} corrupt replies[/]")
    if r.torque_off_verified is not None:
        if r.torque_off_verified:
            console.print("[green]torque off: read back as 0 on every servo[/]")
        else:
            console.print("[red]torque off could NOT be verified: check the servos (`felis torque off`)[/]")
    if not r.ok:
        console.print(f"[red]stopped: {r.stopped}[/]")
    if res.drop is not None:
        console.print(f"drop: {res.drop.height:g} m, roll {res.drop.roll:g}° pitch {res.drop.pitch:g}° "
                      f"yaw {res.drop.yaw:g}° (free fall √(2h/g) = {res.drop.fall_time:.3f} s)")
    for w in getattr(res, "warnings", []):
        console.print(f"[yellow]warning:[/] {w}")
    if res.landing is not None:
        colour = "green" if res.landing.on_feet else "yellow"
        console.print(f"[{colour}]{res.landing.summary()}[/]")
    final_tilt = getattr(res, "final_tilt_deg", None)
    if final_tilt is not None:
        colour = "green" if final_tilt <= 30 else "yellow"
        console.print(f"[{colour}]final tilt from the IMU: {final_tilt:.0f}° from upright[/]")
    summary = getattr(res, "controller", None)
    if summary and "tracking_error" in summary:
        c, m = summary["command_error"], summary["tracking_error"]
        if c["median_mm"] is not None and m["median_mm"] is not None:
            console.print(f"arm-track: {summary['frames']} frames; IK error of the commands median "
                          f"{c['median_mm']:.2g} mm, max {c['max_mm']:.2g} mm; measured tool point vs target median "
                          f"{m['median_mm']:.1f} mm, p95 {m['p95_mm']:.1f} mm (servo lag included); unreachable "
                          f"{summary['unreachable']}, invalid {summary['invalid']}")
    for kind, path in res.files.items():
        console.print(f"{kind}: {path}")
