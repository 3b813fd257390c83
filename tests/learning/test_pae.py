"""The periodic autoencoder with Fourier latent dynamics (`felis.learning.phase.pae`) and its training
(`felis.learning.phase.train`): the FFT parameterisation against sinusoids with known answers, the phase
layer set analytically, shapes, numpy inference, the weights file, deterministic and resumable training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from felis.errors import ParameterError, PhaseError
from felis.learning.phase.infer import PaeNumpy, load_pae_numpy, window_time
from felis.learning.phase.pae import (
    PAE,
    fft_params,
    fld_loss,
    fld_terms,
    latent_wave,
    load_pae,
    manifold,
    predict,
    predict_frames,
    propagate,
    recon_loss,
    save_pae,
    torch_to_arrays,
)
from felis.learning.phase.train import (
    PhaseTrainConfig,
    cycle_period,
    evaluate_phase,
    make_sequences,
    make_windows,
    train_phase,
)


@pytest.fixture(autouse=True)
def _one_thread():
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


def wave(f, a, b, phase, window, rate):
    """a sin(2π(f t + φ)) + b on the centred window axis, float64, shape (len(f), W)."""
    t = window_time(window, rate)
    f, a, b, phase = (np.asarray(v, dtype=float)[:, None] for v in (f, a, b, phase))
    return a * np.sin(2 * np.pi * (f * t + phase)) + b


def gait(T, J, f=2.0, rate=100.0, seed=0, t0=0.0):
    """Synthetic gait q (T, J) from time t0 (s): per joint a fundamental at f and a second harmonic; the
    joints' phases, amplitudes and offsets drawn from ``seed`` (one seed, one "robot")."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(T)[:, None] / rate
    ph, a, b = rng.uniform(0, 1, J), rng.uniform(0.2, 0.6, J), rng.uniform(-0.3, 0.3, J)
    q = b + a * np.sin(2 * np.pi * (f * t + ph)) + 0.3 * a * np.sin(2 * np.pi * (2 * f * t + 2 * ph + 0.1))
    return q.astype(np.float32)


def circ(d):
    """Distance on the unit circle of phases."""
    return np.abs((np.asarray(d) + 0.5) % 1.0 - 0.5)


def one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg and msg
    return msg


def small_model(J=4, W=32, M=3, seed=0, **kw):
    torch.manual_seed(seed)
    m = PAE(J, W, M, hidden=kw.pop("hidden", 8), kernel=kw.pop("kernel", 9), **kw)
    rng = np.random.default_rng(seed)
    m.set_stats(rng.uniform(-0.5, 0.5, J), rng.uniform(0.2, 1.0, J))
    return m.eval()


# ---------------------------------------------------------------------------------- FFT parameters


@pytest.mark.parametrize("window,rate", [(100, 100.0), (101, 50.0), (64, 200.0)])
def test_fft_params_exact_on_grid(window, rate):
    k0 = np.array([1, 2, 5, 13])
    f0 = k0 * rate / window
    a, b, ph = np.array([0.7, 1.3, 0.2, 2.0]), np.array([0.1, -0.4, 0.0, 3.0]), np.array([0.0, 0.3, 0.55, 0.9])
    z = torch.from_numpy(wave(f0, a, b, ph, window, rate))[None]                      # (1, 4, W) float64
    freq, amp, offset = (v[0].numpy() for v in fft_params(z, rate))
    np.testing.assert_allclose(freq, f0, atol=1e-6)
    np.testing.assert_allclose(amp, a, atol=1e-6)
    np.testing.assert_allclose(offset, b, atol=1e-9)
    # several on-grid waves in one channel: A is their root-sum-square (Parseval)
    two = torch.from_numpy(wave([f0[1]], [0.6], [0], [0.2], window, rate) + wave([f0[2]], [0.8], [0], [0.7], window,
                                                                                  rate))[None]
    assert float(fft_params(two, rate)[1]) == pytest.approx(1.0, abs=1e-9)


def test_fft_params_off_grid_bias_as_documented():
    W, rate = 100, 100.0
    step = rate / W
    f0 = np.array([2.6, 4.3, 7.5, 11.2, 23.7])
    # ends of the window meet (cosine about the centre): no jump, little leakage
    ones, zeros = np.ones(5), np.zeros(5)
    freq, amp, _ = fft_params(torch.from_numpy(wave(f0, ones, zeros, np.full(5, 0.25), W, rate))[None], rate)
    assert np.all(np.abs(freq[0].numpy() - f0) < 0.3 * step)
    assert np.all(np.abs(amp[0].numpy() - 1) < 0.05)
    # every phase: the jump's leakage biases f upward, at most 1.21 grid steps (module docstring)
    worst = 0.0
    for ph in np.linspace(0, 1, 24, endpoint=False):
        freq, _, _ = fft_params(torch.from_numpy(wave(f0, ones, zeros, np.full(5, ph), W, rate))[None], rate)
        worst = max(worst, float(np.max(np.abs(freq[0].numpy() - f0))) / step)
    assert 1.0 < worst <= 1.22


def test_fft_params_flat_channel_is_finite():
    z = torch.full((2, 3, 50), 0.4, dtype=torch.float64, requires_grad=True)
    freq, amp, offset = fft_params(z, 100.0)
    assert torch.all(freq.abs() < 1e-9) and torch.all(amp < 1e-7)   # f = 0 up to FFT round-off
    np.testing.assert_allclose(offset.detach().numpy(), 0.4)
    (freq.sum() + amp.sum() + offset.sum()).backward()
    assert torch.all(torch.isfinite(z.grad))


def test_phase_layer_set_analytically_recovers_phase_and_rebuild_is_exact():
    """V_x(t_k) = (2/W) sin 2πf₀t_k, V_y = (2/W) cos 2πf₀t_k, β = 0 give (s_x, s_y) = a(cos 2πφ₀, sin 2πφ₀)."""
    W, rate = 100, 100.0
    f0, a, b = np.array([2.0, 3.0, 7.0]), np.array([0.5, 1.5, 0.8]), np.array([0.2, -1.0, 0.0])
    phases = np.array([[0.0, 0.35, 0.8], [0.6, 0.999, 0.125]])
    model = PAE(1, W, 3, hidden=4, kernel=5, rate_hz=rate).double()
    t = window_time(W, rate)
    weight = np.stack((np.sin(2 * np.pi * f0[:, None] * t), np.cos(2 * np.pi * f0[:, None] * t)), axis=-1) * 2 / W
    with torch.no_grad():
        model.phase_weight.copy_(torch.from_numpy(weight))
        model.phase_bias.zero_()
    z = torch.from_numpy(np.stack([wave(f0, a, b, p, W, rate) for p in phases]))       # (2, 3, W)
    with torch.no_grad():
        phi = model.phase_of(z)
    assert np.all(circ(phi.numpy() - phases) < 1e-12)
    freq, amp, offset = fft_params(z, rate)
    rebuilt = latent_wave(phi, freq, amp, offset, torch.from_numpy(t))
    np.testing.assert_allclose(rebuilt.numpy(), z.numpy(), atol=1e-9)
    # and φ is the phase at the window's centre: ẑ(0) = A sin 2πφ + b
    mid = latent_wave(phi, freq, amp, offset, torch.zeros(1, dtype=torch.float64))[..., 0]
    np.testing.assert_allclose(mid.numpy(), a * np.sin(2 * np.pi * phases) + b, atol=1e-9)


def test_manifold_numpy_and_torch():
    phase, amp = np.array([[0.0, 0.25, 0.6]]), np.array([[2.0, 1.0, 0.5]])
    want = np.array([[0, 2, 1, 0, 0.5 * math.sin(1.2 * math.pi), 0.5 * math.cos(1.2 * math.pi)]])
    np.testing.assert_allclose(manifold(phase, amp), want, atol=1e-12)
    np.testing.assert_allclose(manifold(torch.from_numpy(phase), torch.from_numpy(amp)).numpy(), want, atol=1e-12)
    assert manifold(phase[0], amp[0]).shape == (6,)


def test_propagate_advances_phase_only():
    p = {"phase": torch.tensor([[0.9, 0.1]]), "freq": torch.tensor([[2.0, 0.5]]),
         "amp": torch.tensor([[1.0, 3.0]]), "offset": torch.tensor([[0.1, 0.2]])}
    q = propagate(p, 3, 0.05)                                   # φ + 3 · f · 0.05
    np.testing.assert_allclose(q["phase"].numpy(), [[0.2, 0.175]], atol=1e-6)
    for k in ("freq", "amp", "offset"):
        assert torch.equal(q[k], p[k])
    many = propagate(p, torch.arange(4), 0.05)
    assert all(v.shape == (1, 4, 2) for v in many.values())
    torch.testing.assert_close(many["phase"][:, 3], q["phase"])


# ---------------------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("J", [4, 12, 20])
@pytest.mark.parametrize("M", [1, 3])
def test_shapes(J, M):
    W, B, N = 32, 2, 4
    model = small_model(J, W, M)
    x = torch.randn(B, J, W)
    params = model.encode(x)
    assert all(params[k].shape == (B, M) for k in ("phase", "freq", "amp", "offset"))
    assert params["z"].shape == (B, M, W)
    assert torch.all((params["phase"] >= 0) & (params["phase"] < 1))
    y, _ = model(x)
    assert y.shape == (B, J, W)
    assert manifold(params["phase"], params["amp"]).shape == (B, 2 * M)
    assert predict(model, x, N, 0.01).shape == (B, N, J, W)
    seq = torch.randn(B, N + 1, J, W)
    terms = fld_terms(model, seq, 0.01)
    assert terms.shape == (N + 1,)
    torch.testing.assert_close(terms[0], recon_loss(model, seq[:, 0]))
    loss = fld_loss(model, seq, 0.9, 0.01)
    torch.testing.assert_close(loss, (0.9 ** torch.arange(N + 1) * terms).sum())
    loss.backward()
    assert all(p.grad is not None and torch.all(torch.isfinite(p.grad)) for p in model.parameters())
    assert PaeNumpy(model.config, torch_to_arrays(model)).encode(x[0].numpy())["phase"].shape == (M,)


def test_predict_last_frame_is_the_shifted_window():
    """Window i of `predict` is decode(φ + i f Δt): the same as decoding the propagated parameters."""
    model = small_model(3, 40, 2, seed=1)
    x = torch.from_numpy(np.ascontiguousarray(gait(40, 3).T[None]))
    with torch.no_grad():
        pred = predict(model, x, 3, 0.02)
        p = propagate(model.encode(x), 2, 0.02)
        torch.testing.assert_close(pred[:, 1], model.decode(p["phase"], p["freq"], p["amp"], p["offset"]))
        torch.testing.assert_close(predict_frames(model, x, 3, 0.02), pred[..., -1])
        # frame c of the window propagated (W−1−c)/rate further: frame 30 of a window 2·0.02 + 9/100 s on
        inner = predict_frames(model, x, 3, 0.02, frame=30)
        p = propagate(model.encode(x), 2 + 9 / (100 * 0.02), 0.02)
        torch.testing.assert_close(inner[:, 1], model.decode(p["phase"], p["freq"], p["amp"], p["offset"])[..., 30])


# ------------------------------------------------------------------------------------------ numpy


def test_numpy_encoder_equals_torch_and_rejects_bad_windows():
    J, W, M = 12, 100, 5
    torch.manual_seed(4)
    model = PAE(J, W, M, hidden=32, kernel=25).eval()
    model.set_stats(np.linspace(-0.5, 0.5, J), np.linspace(0.2, 1.0, J))
    x = np.stack([gait(W, J, f=1.5 + i, seed=i).T for i in range(4)]) + np.random.default_rng(0).normal(
        0, 0.05, (4, J, W)).astype(np.float32)
    with torch.no_grad():
        want = model.encode(torch.from_numpy(x))
    for dtype in (np.float32, np.float64):
        net = PaeNumpy(model.config, torch_to_arrays(model), dtype)
        for b in range(4):
            got = net.encode(x[b].astype(np.float64))
            for k in ("freq", "amp", "offset"):
                np.testing.assert_allclose(got[k], want[k][b].numpy(), rtol=1e-5, atol=1e-5, err_msg=k)
            assert np.all(circ(got["phase"] - want["phase"][b].numpy()) < 1e-5)
    bad = x[0].copy()
    bad[3, 17] = np.nan
    with pytest.raises(PhaseError) as e:
        net.encode(bad)
    assert "joint 3, frame 17" in one_line(e)
    with pytest.raises(PhaseError) as e:
        net.encode(x[0, :, :50])
    assert "(12, 100)" in one_line(e)


# ------------------------------------------------------------------------------------ weights file


def test_weights_file_round_trip(tmp_path):
    joints = [f"j{i}" for i in range(4)]
    model = small_model(4, 32, 3, joints=joints)
    path = save_pae(tmp_path / "pae.npz", model, {"training": {"epochs": 3}, "val": np.float32(0.5)})
    loaded, meta = load_pae(path, expect_joints=joints)
    assert meta["config"]["joints"] == joints and meta["training"] == {"epochs": 3} and meta["val"] == 0.5
    assert loaded.config == model.config
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)
    net, _ = load_pae_numpy(path, expect_joints=4)
    x = np.asarray(gait(32, 4).T)
    with torch.no_grad():
        want = model.encode(torch.from_numpy(x[None]))
    np.testing.assert_allclose(net.encode(x)["amp"], want["amp"][0].numpy(), rtol=1e-5)
    assert not (tmp_path / "pae.npz").with_suffix(".npz.tmp").exists()


def _rewrite(src, dst, drop=(), change=None, meta=None):
    data = dict(np.load(src, allow_pickle=False))
    for k in drop:
        data.pop(k)
    data.update(change or {})
    if meta is not None:
        data["__meta__"] = np.array(meta)
    np.savez(dst, **data)
    return dst


def test_mismatched_weights_files_are_one_line_phase_errors(tmp_path):
    good = save_pae(tmp_path / "good.npz", small_model(4, 32, 3, joints=["a", "b", "c", "d"]))
    cases = {
        "missing": (tmp_path / "nope.npz", "no such PAE weights file"),
        "member": (_rewrite(good, tmp_path / "m.npz", drop=["enc2.weight"]), "lacks array 'enc2.weight'"),
        "shape": (_rewrite(good, tmp_path / "s.npz", change={"phase_bias": np.zeros((3, 3), np.float32)}),
                  "'phase_bias' has shape (3, 3)"),
        "nan": (_rewrite(good, tmp_path / "n.npz", change={"mean": np.full(4, np.nan, np.float32)}), "non-finite"),
        "other model": (_rewrite(good, tmp_path / "o.npz", meta='{"model": "felis-ik", "schema": 1}'),
                        "not a PAE weights file"),
        "no meta": (_rewrite(good, tmp_path / "x.npz", drop=["__meta__"]), "no '__meta__' metadata"),
        "bad config": (_rewrite(good, tmp_path / "c.npz",
                                meta='{"model": "felis-pae", "schema": 1, "config": {"n_joints": 4}}'), "bad config"),
    }
    (tmp_path / "text.npz").write_text("hello")
    cases["text"] = (tmp_path / "text.npz", "not a PAE weights file")
    for name, (path, want) in cases.items():
        with pytest.raises(PhaseError) as e:
            load_pae_numpy(path)
        msg = one_line(e)
        assert str(path) in msg and want in msg, (name, msg)
    with pytest.raises(PhaseError) as e:
        load_pae(good, expect_joints=12)
    assert "takes 4 joints, expected 12" in one_line(e)
    with pytest.raises(PhaseError) as e:
        load_pae_numpy(good, expect_joints=["a", "b", "x", "d"])
    assert "joint 2 is 'c', expected 'x'" in one_line(e)


# ---------------------------------------------------------------------------------------- data


def test_windows_and_sequences():
    q = np.arange(30, dtype=np.float32).reshape(15, 2)        # frame t, joint j → 2t + j
    w = make_windows([q, q[:12]], window=5, stride=3)
    assert w.shape == (4 + 3, 2, 5)
    np.testing.assert_array_equal(w[1, 1], 2 * np.arange(3, 8) + 1)
    s = make_sequences([q], window=5, n_steps=3, stride=4, step=2)   # span 5 + 3·2 = 11 → starts 0, 4
    assert s.shape == (2, 4, 2, 5)
    np.testing.assert_array_equal(s[1, 2, 0], 2 * np.arange(4 + 4, 4 + 4 + 5))
    with pytest.raises(PhaseError) as e:
        make_windows([q, q[:4]], 5, 1)
    assert "trajectory 1 has 4 frames" in one_line(e)
    bad = q.copy()
    bad[9, 1] = np.nan
    with pytest.raises(PhaseError) as e:
        make_windows([q, bad], 5, 1)
    assert "trajectory 1 holds nan at frame 9, joint 1" in one_line(e)
    with pytest.raises(PhaseError) as e:
        make_sequences([q, q[:, :1]], 5, 2, 1)
    assert "trajectory 1 has 1 joints" in one_line(e)


@pytest.mark.parametrize("field,value", [("window", 2), ("kernel", 4), ("alpha", 0.0), ("alpha", 1.5), ("lr", -1.0),
                                         ("fld_weight", float("nan")), ("stride", 0), ("epochs", True)])
def test_config_validation(field, value):
    with pytest.raises(ParameterError) as e:
        PhaseTrainConfig(**{field: value})
    assert field in one_line(e)


def test_cycle_period():
    x = np.stack([gait(100, 3, f=f, seed=1).T for f in (2.0, 2.5, 4.0, 2.2)])
    np.testing.assert_array_equal(cycle_period(x), [50, 40, 25, 45])          # 100 / 2.2 = 45.5


# ------------------------------------------------------------------------------------------- training


TINY = PhaseTrainConfig(window=40, n_phases=2, hidden=6, kernel=5, rate_hz=100.0, epochs=6, batch=8, lr=2e-2,
                        stride=8, fld_steps=3, alpha=0.9, fld_weight=0.5, seed=2, threads=1)


def test_training_is_deterministic_and_resumes_bit_identically(tmp_path):
    train = [gait(150, 3, seed=0), gait(120, 3, f=2.5, seed=1)]
    val = [gait(100, 3, f=2.2, seed=2)]
    threads = torch.get_num_threads()
    a, ha = train_phase(train, val, TINY, checkpoint=tmp_path / "a.ckpt")
    assert torch.get_num_threads() == threads
    b, hb = train_phase(train, val, TINY)
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    assert ha["train"] == hb["train"] and ha["val"] == hb["val"]
    assert ha["train"][-1] < 0.5 * ha["train"][0] and ha["val_recon"][-1] < ha["val_recon"][0]
    assert len(ha["val_fld"]) == 6 and 1 <= ha["best_epoch"] <= 6
    # stop after 3 epochs (the progress callback raises), then resume to 6
    def stop(epoch, *_):
        if epoch == 3:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        train_phase(train, val, TINY, checkpoint=tmp_path / "c.ckpt", progress=stop)
    c, hc = train_phase(train, val, TINY, checkpoint=tmp_path / "c.ckpt", resume=True)
    for k, v in a.state_dict().items():
        assert torch.equal(v, c.state_dict()[k]), k
    assert hc["train"] == ha["train"] and hc["best_epoch"] == ha["best_epoch"]
    # a checkpoint of another run is refused
    with pytest.raises(PhaseError) as e:
        train_phase(train, val, PhaseTrainConfig(**{**TINY.__dict__, "seed": 3}), checkpoint=tmp_path / "c.ckpt",
                    resume=True)
    assert "another training config (seed: 2 there, 3 now)" in one_line(e)


def test_short_training_finds_the_gait_frequency_and_fld_beats_constant_velocity():
    """2 Hz gait with a second harmonic; after 25 short epochs the strongest channel sits near 2 Hz, and
    FLD predicts held-out stretches of the same gait better than constant velocity."""
    cfg = PhaseTrainConfig(window=100, n_phases=3, hidden=8, kernel=9, rate_hz=100.0, epochs=25, batch=16, lr=1e-2,
                           lr_decay=1.0, stride=10, fld_steps=5, seed=0)
    train = [gait(400, 4, seed=0), gait(400, 4, seed=0, t0=5.01)]
    held_out = [gait(300, 4, seed=0, t0=0.137)]
    model, hist = train_phase(train, None, cfg)
    assert hist["val"] == hist["train"] and hist["train"][-1] < 0.05 * hist["train"][0]
    with torch.no_grad():
        p = model.encode(torch.from_numpy(make_windows(held_out, 100, 20)))
    dominant = int(p["amp"].mean(0).argmax())
    f = float(p["freq"][:, dominant].mean())
    k = max(round(f / 2.0), 1)
    assert abs(f - 2.0 * k) < 0.15 * 2.0 * k, f
    ev = evaluate_phase(model, held_out, n_steps=10)
    assert set(ev["pred_mse"]) == {"fld", "fld_centre", "const_vel", "last_cycle"} and len(ev["horizon_s"]) == 10
    assert ev["period_frames_median"] == 50 and ev["pred_mse_final"]["last_cycle"] < 1e-10   # exactly periodic
    assert ev["pred_mse"]["const_vel"][-1] > 10 * ev["pred_mse"]["const_vel"][0]
    assert ev["pred_mse_final"]["fld"] < 0.5 * ev["pred_mse_final"]["const_vel"]
    assert 0 < ev["recon_mse"] < 0.005
