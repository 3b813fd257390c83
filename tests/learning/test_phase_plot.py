"""``felis phase plot`` and `felis.learning.phase.plot`: a tiny phase model really trained on a short MuJoCo
trot and calibrated, plotted over a gait-data file and over a run log made by the ``felis`` command;
one-line errors that write nothing. Real MuJoCo, real files, no mocks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from matplotlib.image import imread
from test_cli import felis, ok, tree

from felis.errors import ParameterError, PhaseError
from felis.learning.phase.data import record_sim, save_recordings
from felis.learning.phase.estimator import DEFAULT_WEIGHTS, calibrate
from felis.learning.phase.infer import PaeConfig, load_pae_numpy
from felis.learning.phase.pae import model_from_config, save_pae
from felis.learning.phase.plot import DPI, WIDTH_IN, plot_phase, resample
from felis.learning.phase.train import PhaseTrainConfig, train_phase

TROT = ((1.0, 0.0, 0.0), (4.0, 2.0, 0.5), (2.0, 0.0, 0.0))
CFG = PhaseTrainConfig(window=50, n_phases=3, hidden=8, kernel=13, epochs=4, fld_steps=4, threads=1)


def _half_rate(rec, name):
    """Every other sample of ``rec``: the same gait recorded at half the rate."""
    k = slice(None, None, 2)
    return dataclasses.replace(rec, t=rec.t[k], q=rec.q[k], contacts=rec.contacts[k], clock_phase=rec.clock_phase[k],
                               frequency_hz=rec.frequency_hz[k], amplitude=rec.amplitude[k], stepping=rec.stepping[k],
                               rate_hz=rec.rate_hz / 2, name=name)


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Calibrated weights trained on a 7 s trot, a gait-data file (the trot at 100 and 50 Hz, and a 0.4 s
    blip), a 3 s simulated run log, and two models that do not fit the cat (4 joints; a 4 s window)."""
    d = tmp_path_factory.mktemp("phase_plot")
    rec = record_sim(TROT, name="trot")
    blip = record_sim(((0.1, 0.0, 0.0),), name="blip")
    save_recordings(d / "gait.npz", [rec, _half_rate(rec, "trot-50"), blip], set_name="test")
    model, _ = train_phase([rec.q], None, CFG, joints=rec.joints)
    save_pae(d / "bare.npz", model)
    cal = calibrate(load_pae_numpy(d / "bare.npz")[0], [rec.q], [rec.stepping])
    save_pae(d / "w.npz", model, {"phase_estimator": cal})

    t = np.arange(300) / 100.0
    wave = np.stack([np.sin(2 * np.pi * 2.0 * t + k) for k in range(4)], axis=1)
    four, _ = train_phase([wave], None, dataclasses.replace(CFG, epochs=1), joints=("a", "b", "c", "d"))
    save_pae(d / "four.npz", four)
    wide = model_from_config(PaeConfig(12, 400, 2, 4, 5, 100.0, tuple(rec.joints)))
    save_pae(d / "wide.npz", wide)

    ok(felis(d, "run", "step-in-place", "--robot", "cat", "--duration", "3", "--log", "run.mcap"))
    return d, rec, cal


def _png(path):
    img = imread(path)
    assert img.ndim == 3 and img.shape[1] == round(WIDTH_IN * DPI)  # 12 in at 110 dpi
    assert 0.6 * img.shape[1] < img.shape[0] < 1.2 * img.shape[1]  # 3 channels: a little less tall than wide
    assert img[..., :3].std() > 0.05  # drawn, not blank
    return img


def test_plot_a_gait_data_file_and_a_run_log(made, tmp_path):
    d, _, _ = made
    out = plot_phase(d / "gait.npz", tmp_path / "trot.png", weights=d / "w.npz")
    assert out == tmp_path / "trot.png" and out.stat().st_size > 20_000
    _png(out)
    _png(plot_phase(d / "gait.npz", tmp_path / "trot50.png", weights=d / "w.npz", recording="trot-50"))
    _png(plot_phase(d / "run.mcap", tmp_path / "log.png", weights=d / "w.npz"))
    _png(plot_phase(d / "gait.npz", tmp_path / "bare.png", weights=d / "bare.npz"))  # no calibration: still plots
    assert tree(tmp_path) == {"trot.png", "trot50.png", "log.png", "bare.png"}  # no temporary files left


def test_resample_to_the_models_rate(made):
    _, rec, _ = made
    half = _half_rate(rec, "half")
    back = resample(half, 100.0)
    assert back.rate_hz == 100.0 and np.allclose(np.diff(back.t), 0.01) and back.t[0] == rec.t[0]
    assert np.allclose(back.q[::2], half.q) and np.allclose(back.q[1::2], (half.q[:-1] + half.q[1:]) / 2)
    assert back.stepping.dtype == bool and back.stepping.sum() == pytest.approx(rec.stepping.sum(), abs=2)
    assert resample(rec, 100.0) is rec


def test_cli(made, tmp_path):
    d, _, _ = made
    r = ok(felis(tmp_path, "phase", "plot", str(d / "gait.npz"), "--out", "p.png", "--weights", str(d / "w.npz"),
                 "--recording", "trot-50"))
    assert r.stdout.strip() == "plot: p.png"
    _png(tmp_path / "p.png")
    r = ok(felis(tmp_path, "phase", "plot", str(d / "run.mcap"), "--out", "sub/log.png", "--weights",
                 str(d / "w.npz")))
    assert r.stdout.strip() == "plot: sub/log.png"
    _png(tmp_path / "sub" / "log.png")


def _error(cwd, *args) -> str:
    r = felis(cwd, "phase", "plot", *args)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


def test_errors_are_one_line_and_write_nothing(made, tmp_path):
    d, rec, _ = made
    w = str(d / "w.npz")
    gait, log = str(d / "gait.npz"), str(d / "run.mcap")
    cases = [
        ((gait, "--out", "x.png", "--weights", w, "--recording", "nope"),
         ["no recording 'nope'", "trot, trot-50, blip"]),
        ((gait, "--out", "x.png", "--weights", w, "--recording", "blip"),
         ["'blip' has 40 frames at 100 Hz", "needs at least 50 (one window)"]),
        ((log, "--out", "x.png", "--weights", str(d / "wide.npz")),
         ["has 300 frames at 100 Hz (2.99 s)", "needs at least 400 (one window)"]),
        ((log, "--out", "x.png", "--weights", str(d / "four.npz")),
         ["phase model joints ['a', 'b', 'c', 'd'] differ", f"run.mcap {list(rec.joints)}"]),
        ((gait, "--out", "x.jpg", "--weights", w), ["x.jpg: the phase plot must end in .png"]),
        ((log, "--out", "x.png", "--weights", w, "--recording", "trot"), ["a run log holds one recording"]),
        ((str(tmp_path / "nope.mcap"), "--out", "x.png", "--weights", w), ["no such run log"]),
        ((gait, "--out", "x.png", "--weights", str(tmp_path / "nope.npz")), ["nope.npz: no such PAE weights file"]),
    ]
    if not DEFAULT_WEIGHTS.exists():  # until the model ships
        cases.append(((gait, "--out", "x.png"), ["no phase model at", "run `felis train phase` first"]))
    for args, fragments in cases:
        line = _error(tmp_path, *args)
        for fragment in fragments:
            assert fragment in line, line
    assert tree(tmp_path) == set()
    with pytest.raises(PhaseError, match="no recording 'nope'"):
        plot_phase(gait, tmp_path / "x.png", weights=w, recording="nope")
    with pytest.raises(ParameterError, match="must end in .png"):
        plot_phase(gait, tmp_path / "x.svg", weights=w)
    assert tree(tmp_path) == set()
