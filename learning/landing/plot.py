"""The landing evolution's learning curves (``<stem>.curves.png``) from its results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.files import write_atomic


def plot_curves(path: Path, results: dict) -> Path:
    """Best f and D per generation per orientation (simple stage); the complex stage's best mean f and
    how many orientations it lands upright on. Agg canvas, no pyplot state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(11, 7.5))
    FigureCanvasAgg(fig)
    ax = fig.subplots(2, 2)
    for c in results["simple"]:
        g = np.arange(1, len(c["best_f"]) + 1)
        label = "k{index} ({r:g}, {p:g}, {y:g})".format(index=c["sample"], r=c["orientation"][0],
                                                       p=c["orientation"][1], y=c["orientation"][2])
        ax[0, 0].plot(g, c["best_f"], label=label)
        ax[0, 1].plot(g, c["best_D"], label=label)
    ax[0, 0].set(title="simple stage: best f (eq. 9 × upright)", xlabel="generation", ylabel="f")
    ax[0, 1].set(title="simple stage: D of the best (eq. 7)", xlabel="generation", ylabel="D")
    ax[0, 0].legend(fontsize=7)
    cx = results["complex"]
    g = np.arange(1, len(cx["best_mean_f"]) + 1)
    ax[1, 0].plot(g, cx["best_mean_f"], label="best: mean f")
    ax[1, 0].plot(g, cx["median_mean_f"], label="median: mean f")
    gx = results.get("general") or {}
    if gx.get("best_mean_f"):
        gg = np.arange(1, len(gx["best_mean_f"]) + 1)
        ax[1, 0].plot(gg, gx["best_mean_f"], label="general stage, best: mean f over its drops")
        ax[1, 0].plot(gg, gx["median_mean_f"], label="general stage, median")
    ax[1, 0].set(title="complex stage: f over the orientations", xlabel="generation", ylabel="mean f")
    ax[1, 0].legend(fontsize=7)
    ax[1, 1].plot(g, cx["best_n_success"], drawstyle="steps-mid", label="upright at the end, f > 0")
    ax[1, 1].plot(g, cx["best_n_landed"], drawstyle="steps-mid", label="landed (feet first, 0.5 s)")
    ax[1, 1].legend(fontsize=7)
    ax[1, 1].set(title="complex stage: orientations the best lands on", xlabel="generation",
                 ylabel="orientations", ylim=(-0.2, len(results["simple"]) + 0.2))
    for a in ax.flat:
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax[1, 1].yaxis.set_major_locator(MaxNLocator(integer=True))
    fig.tight_layout()
    return write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=90), "training curves", ParameterError)
