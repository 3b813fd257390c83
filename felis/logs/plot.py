"""A one-page PNG overview of a run log, for a quick look without Foxglove.

Panels share the time axis: joint positions (commanded targets dashed in the joint's colour),
joint velocities and, when the log has them, the height (m) and the IMU tilt (deg). Events are
vertical lines in every panel, one colour per kind.

Tilt is the angle between the body's up axis and world up. For the orientation quaternion
(w, x, y, z) the body z axis in world coordinates has z component ``1 − 2(x² + y²)``, so::

    tilt = arccos(1 − 2(x² + y²))

Drawn with matplotlib's object API (``Figure`` + ``FigureCanvasAgg``): no pyplot, no global
backend switch, safe on a machine without a display and inside other programs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from felis.errors import LogError, ParameterError
from felis.files import write_atomic
from felis.logs.reader import LogData, read_log
from felis.rotations import tilt_deg


def plot_log(path: str | Path, out: str | Path) -> Path:
    """Plot the run log at ``path`` into the PNG ``out`` (written atomically); returns ``out``.

    Raises LogError when the log cannot be read or the image cannot be written.
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ParameterError(f"{out}: plot output must end in .png")
    data = read_log(path)
    fig = _figure(data)
    write_atomic(out, lambda fh: fig.savefig(fh, format="png", dpi=110), "plot", LogError)
    return out


def _figure(data: LogData):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    tilt = tilt_deg(data.quat) if data.quat is not None else None
    show_height = data.height is not None and bool(np.isfinite(data.height).any())
    show_tilt = tilt is not None and bool(np.isfinite(tilt).any())
    rows = 2 + show_height + show_tilt
    fig = Figure(figsize=(12, 2.6 * rows + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    title = f"{data.robot} — {data.path.name}"
    if not data.complete:
        title += " (cut off: run did not end properly)"
    fig.suptitle(title)

    ax_q, ax_dq = axes[0], axes[1]
    colours = [f"C{i % 10}" for i in range(len(data.joints))]
    styles = ["-", "-."] if len(data.joints) > 10 else ["-"]  # 10 colours in the cycle
    for i, name in enumerate(data.joints):
        style = styles[(i // 10) % len(styles)]
        ax_q.plot(data.t, data.q[:, i], style, color=colours[i], lw=1.2, label=name)
        if len(data.cmd_t):
            ax_q.plot(data.cmd_t, data.cmd_q[:, i], "--", color=colours[i], lw=0.9, alpha=0.75)
        ax_dq.plot(data.t, data.dq[:, i], style, color=colours[i], lw=1.0)
    if len(data.cmd_t):
        ax_q.plot([], [], "--", color="0.4", lw=0.9, label="(dashed: commanded)")
    ax_q.set_ylabel("position (rad)")
    ax_q.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    ax_dq.set_ylabel("velocity (rad/s)")

    row = 2
    if show_height:
        axes[row].plot(data.t, data.height, color="k", lw=1.2)
        axes[row].set_ylabel("height (m)")
        row += 1
    if show_tilt:
        axes[row].plot(data.t, tilt, color="k", lw=1.2)
        axes[row].set_ylabel("tilt (deg)")
        row += 1

    _events(axes, data.events)
    if not len(data.t):
        ax_q.text(0.5, 0.5, "no state messages", transform=ax_q.transAxes, ha="center", va="center")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    return fig


def _events(axes, events: list[dict]) -> None:
    """Vertical lines at event times, one colour per kind; the kinds go in a legend."""
    by_kind: dict[str, list[float]] = {}
    for e in events:
        t = e.get("t")
        if isinstance(t, int | float) and np.isfinite(t):
            by_kind.setdefault(str(e.get("kind", "?")), []).append(float(t))
    if not by_kind:
        return
    # colours outside the C0-C9 cycle the joints use, dotted so they do not read as data
    palette = ["crimson", "black", "darkviolet", "darkgoldenrod", "teal", "saddlebrown"]
    for k, (kind, ts) in enumerate(sorted(by_kind.items())):
        colour = palette[k % len(palette)]
        for ax in axes:
            ax.vlines(ts, 0, 1, transform=ax.get_xaxis_transform(), colors=colour, lw=1.0, alpha=0.7,
                      linestyles=":", label=f"{kind} ({len(ts)})" if ax is axes[1] else None)
    axes[1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False,
                   title="events")
