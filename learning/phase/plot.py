"""A one-page PNG of what a trained phase model (`felis.learning.phase.pae`, seed 003) reads from a gait: a run
log (``.mcap``) or one recording of a gait-data file (``.npz``, `felis.learning.phase.data`).

The recording's joint trajectory, resampled onto the model's rate by linear interpolation when it was
recorded at another, goes through `felis.learning.phase.estimator.phase_track`: per frame, from the
window of the last W frames, each latent channel c's phase φ_c *now*, frequency f_c and amplitude A_c
(nothing for the first W − 1 frames). Panels, sharing the time axis:

* one row per channel: A_c·sin 2πφ_c, the channel's wave as the phase rebuilds it (one cycle per
  period of the phase, its height the amplitude), with ±A_c as a thin envelope; the gait channel (from
  the weights' calibration, ``meta["phase_estimator"]["channel"]``) drawn thicker and labelled;
* the gait channel's frequency (Hz), faint where its amplitude is below the stepping threshold (the
  channel then carries no gait and its frequency is noise), with the commanded step frequency of the
  recording's gait clock when it is known (simulated recordings; 0 while standing);
* the gait channel's amplitude, with the stepping threshold (``stepping_amp``) dashed and, when the
  recording knows it, the time the gait stepped shaded.

Below, the phase manifold per channel: the points (A sin 2πφ, A cos 2πφ) on small equal-aspect axes,
coloured by time. A steady gait draws a circle of radius A, standing collapses onto the centre, a change of
amplitude moves between rings. Weights without a calibration still plot: the gait channel is then the one
with the largest median amplitude over the recording, and no threshold is drawn.

Drawn with matplotlib's object API as `felis.logs.plot` does (``Figure`` + ``FigureCanvasAgg``, no pyplot),
written atomically.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from felis.errors import ParameterError, PhaseError
from felis.files import check_target, write_atomic
from felis.learning.phase.data import GaitRecording, from_log, load_recordings
from felis.learning.phase.estimator import DEFAULT_WEIGHTS, phase_track
from felis.learning.phase.infer import PaeNumpy, load_pae_numpy

DPI = 110
WIDTH_IN = 12.0


def plot_phase(source: str | Path, out: str | Path, weights: str | Path | None = None,
               recording: str | None = None) -> Path:
    """Plot the phase model ``weights`` (default `DEFAULT_WEIGHTS`) on ``source`` (a run log ``.mcap`` or a
    gait-data file ``.npz``, whose recording ``recording`` is drawn, default its first) into the PNG
    ``out``, written atomically; returns ``out``.

    One-line errors: ParameterError for an output that is not ``.png`` or ``recording`` with a run log;
    PhaseError for a missing or unusable source or weights file, an unknown recording name (listing the
    names), weights whose joints differ from the recording's, a recording shorter than one window.
    Nothing is written on an error.
    """
    out, source = Path(out), Path(source)
    if out.suffix.lower() != ".png":
        raise ParameterError(f"{out}: the phase plot must end in .png")
    check_target(out, "phase plot", ParameterError)
    if weights is None:
        if not DEFAULT_WEIGHTS.exists():
            raise PhaseError(f"no phase model at {DEFAULT_WEIGHTS}: run `felis train phase` first, or pass --weights")
        weights = DEFAULT_WEIGHTS
    weights = Path(weights)
    rec = _recording(source, recording)
    pae, meta = load_pae_numpy(weights)
    cfg = pae.config
    if cfg.joints is not None and tuple(cfg.joints) != tuple(rec.joints):
        raise PhaseError(f"{weights}: phase model joints {list(cfg.joints)} differ from the joints of "
                         f"{source.name} {list(rec.joints)}")
    if cfg.n_joints != len(rec.joints):
        raise PhaseError(f"{weights}: phase model takes {cfg.n_joints} joints, {source.name} has "
                         f"{len(rec.joints)} ({', '.join(rec.joints)})")
    rec = resample(rec, cfg.rate_hz)
    if len(rec.t) < cfg.window:
        raise PhaseError(f"{source}: recording {rec.name!r} has {len(rec.t)} frames at {cfg.rate_hz:g} Hz "
                         f"({rec.duration_s:.2f} s); the phase model needs at least {cfg.window} (one window)")
    track = phase_track(pae, rec.q)
    fig = _figure(rec, track, pae, meta, title=f"{source.name} — recording {rec.name!r} — weights {weights.name}")
    write_atomic(out, lambda fh: fig.savefig(fh, format="png", dpi=DPI), "phase plot", PhaseError)
    return out


def _recording(source: Path, name: str | None) -> GaitRecording:
    """The recording to plot: a run log's, or the named (default first) one of a gait-data file."""
    if source.suffix.lower() != ".npz":
        if name is not None:
            raise ParameterError(f"{source}: a run log holds one recording; --recording picks one of a "
                                 "gait-data file (.npz)")
        return from_log(source)
    recs = load_recordings(source)
    if name is None:
        return recs[0]
    for r in recs:
        if r.name == name:
            return r
    raise PhaseError(f"{source}: no recording {name!r}; the file holds {', '.join(r.name for r in recs)}")


def resample(rec: GaitRecording, rate_hz: float) -> GaitRecording:
    """``rec`` on a uniform grid at ``rate_hz`` from its first time (q, frequency and amplitude linear,
    clock phase, stepping and contacts nearest sample); unchanged when it is at that rate already."""
    if math.isclose(rec.rate_hz, rate_hz, rel_tol=1e-9) or len(rec.t) < 2:
        return rec
    t = rec.t
    grid = t[0] + np.arange(int(math.floor((t[-1] - t[0]) * rate_hz + 1e-9)) + 1) / rate_hz

    def lin(a: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(grid, t, col) for col in a.T], axis=1) if a.ndim == 2 else np.interp(grid, t, a)

    right = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
    near = np.where(grid - t[right - 1] <= t[right] - grid, right - 1, right)
    return replace(rec, t=grid, q=lin(rec.q), rate_hz=float(rate_hz),
                   contacts=None if rec.contacts is None else rec.contacts[near],
                   clock_phase=rec.clock_phase[near], frequency_hz=lin(rec.frequency_hz),
                   amplitude=lin(rec.amplitude), stepping=rec.stepping[near])


def _calibration(meta: dict, amp: np.ndarray, n_phases: int) -> tuple[int, float | None, str]:
    """(gait channel, stepping threshold or None, how the channel was chosen)."""
    cal = meta.get("phase_estimator")
    if isinstance(cal, dict) and isinstance(cal.get("channel"), int) and 0 <= cal["channel"] < n_phases:
        thr = cal.get("stepping_amp")
        return cal["channel"], float(thr) if isinstance(thr, int | float) else None, "calibrated"
    with np.errstate(all="ignore"):
        med = np.nanmedian(amp, axis=0)
    return int(np.nanargmax(med)) if np.isfinite(med).any() else 0, None, "largest amplitude; no calibration"


def _figure(rec: GaitRecording, track: dict, pae: PaeNumpy, meta: dict, title: str):
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    M = pae.config.n_phases
    phase, amp, freq = track["phase"], track["amp"], track["freq"]
    gait, thr, how = _calibration(meta, amp, M)
    t = rec.t
    known = rec.source == "sim" or bool(rec.stepping.any())  # the recording has a gait clock

    top_h = 0.9 * M + 2 * 1.8
    fig = Figure(figsize=(WIDTH_IN, top_h + 2.9 + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    fig.suptitle(f"{title}\ngait channel {gait} ({how}), {M} channels, window {pae.config.window} frames at "
                 f"{pae.config.rate_hz:g} Hz")
    top, bottom = fig.subfigures(2, 1, height_ratios=[top_h, 2.9])
    axes = top.subplots(M + 2, 1, sharex=True, height_ratios=[0.9] * M + [1.8, 1.8])
    wave = amp * np.sin(2 * np.pi * phase)
    for c in range(M):
        ax = axes[c]
        g = c == gait
        ax.plot(t, wave[:, c], color=f"C{c % 10}", lw=1.3 if g else 0.8)
        ax.plot(t, amp[:, c], color="0.55", lw=0.6)
        ax.plot(t, -amp[:, c], color="0.55", lw=0.6)
        ax.set_ylabel(f"ch {c}" + (" (gait)" if g else ""), fontweight="bold" if g else "normal")
    axes[0].set_title("A·sin 2πφ per channel (grey: ±A)", fontsize="medium", loc="left")

    ax_f, ax_a = axes[M], axes[M + 1]
    f_gait = freq[:, gait]
    if thr is None:
        ax_f.plot(t, f_gait, color=f"C{gait % 10}", lw=1.2, label=f"ch {gait} frequency")
    else:  # below the threshold the channel carries no gait: its frequency is noise, drawn faint
        ax_f.plot(t, f_gait, color=f"C{gait % 10}", lw=0.8, alpha=0.35, label=f"ch {gait} frequency, not stepping")
        ax_f.plot(t, np.where(amp[:, gait] > thr, f_gait, np.nan), color=f"C{gait % 10}", lw=1.3,
                  label=f"ch {gait} frequency, stepping")
    if known:
        ax_f.plot(t, rec.frequency_hz, "--", color="k", lw=1.0, label="gait clock (0: standing)")
    ax_f.set_ylabel("frequency (Hz)")
    ax_f.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    ax_a.plot(t, amp[:, gait], color=f"C{gait % 10}", lw=1.2, label=f"ch {gait} amplitude")
    if thr is not None:
        ax_a.axhline(thr, ls="--", color="crimson", lw=1.0, label=f"stepping threshold {thr:.3g}")
    if known and rec.stepping.any():
        ax_a.fill_between(t, 0, 1, where=rec.stepping, transform=ax_a.get_xaxis_transform(), color="0.85",
                          step="mid", label="gait clock stepping")
    ax_a.set_ylabel("amplitude")
    ax_a.set_ylim(bottom=0)
    if t[-1] > t[0]:
        ax_a.set_xlim(t[0], t[-1])  # the whole recording, the first window's frames (no estimate) included
    ax_a.set_xlabel("time (s)")
    ax_a.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    for ax in axes:
        ax.grid(True, alpha=0.3)

    mans = bottom.subplots(1, M, squeeze=False)[0]
    norm = Normalize(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1.0)
    ok = np.isfinite(phase[:, 0])
    for c, ax in enumerate(mans):
        x, y = amp[ok, c] * np.sin(2 * np.pi * phase[ok, c]), amp[ok, c] * np.cos(2 * np.pi * phase[ok, c])
        ax.plot(x, y, color="0.8", lw=0.4, zorder=1)
        ax.scatter(x, y, c=t[ok], cmap="viridis", norm=norm, s=3, linewidths=0, zorder=2)
        r = float(np.max(amp[ok, c])) * 1.1 if ok.any() else 1.0
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        ax.set_aspect("equal", "box")
        ax.axhline(0, color="0.7", lw=0.5)
        ax.axvline(0, color="0.7", lw=0.5)
        ax.tick_params(labelsize="x-small")
        ax.set_title(f"ch {c}" + (" (gait)" if c == gait else ""), fontsize="small",
                     fontweight="bold" if c == gait else "normal")
        ax.set_xlabel("A sin 2πφ", fontsize="x-small")
    mans[0].set_ylabel("A cos 2πφ", fontsize="x-small")
    bottom.colorbar(ScalarMappable(norm=norm, cmap=colormaps["viridis"]), ax=list(mans), label="time (s)",
                    shrink=0.9)
    return fig
