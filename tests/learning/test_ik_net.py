"""The deep IK nets (seed 001 §3.1.2): numpy inference equals torch, the weights file round-trips and
refuses every kind of bad file with one specific line, training is deterministic, resumes exactly and
learns. Synthetic data only; tiny nets so the whole file runs in a few seconds."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch

from felis.errors import ParameterError, WeightsError
from felis.learning.common.torchstate import torch_to_arrays
from felis.learning.ik import net as ik_net
from felis.learning.ik.infer import NetSpec, NumpyNet, load_arrays, load_weights, lstm_params, mlp_width, param_count
from felis.learning.ik.net import arrays_to_torch, model_from_spec, save_weights
from felis.learning.ik.train import TrainConfig, train_net

MP = NetSpec("lstm", 3, hidden=16, layers=2, n_out=6, name="mp", in_offsets=(-10, -5, 0), out_offsets=(5, 10))
PE = NetSpec("lstm", 5, hidden=12, layers=1, n_out=48, name="pe", in_offsets=(-10, -5, 0, 5, 10),
             out_offsets=(0, 1, 2, 3, 4, 5))


def _random_net(spec: NetSpec, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays of a freshly initialised net with non-trivial normalisation statistics."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = model_from_spec(spec)
    rng = np.random.default_rng(seed)
    model.set_stats(rng.normal(0, 0.3, spec.n_in), rng.uniform(0.2, 2, spec.n_in),
                    rng.normal(0, 1, spec.n_out), rng.uniform(0.1, 3, spec.n_out))
    return torch_to_arrays(model)


def _torch_out(spec: NetSpec, arrays, x: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return arrays_to_torch(spec, arrays)(torch.from_numpy(x.astype(np.float32))).numpy()


@pytest.mark.parametrize("spec", [
    NetSpec("lstm", 5, hidden=32, layers=2, n_out=48, name="a"),
    NetSpec("lstm", 3, hidden=8, layers=3, n_out=6, name="b"),
    NetSpec("lstm", 1, hidden=8, layers=1, n_out=6, name="c"),
    NetSpec("mlp", 5, hidden=32, layers=2, n_out=48, name="d"),
    NetSpec("mlp", 3, hidden=8, layers=1, n_out=6, name="e"),
], ids=lambda s: f"{s.kind}-k{s.k}-h{s.hidden}-L{s.layers}")
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_net_matches_torch(spec, dtype):
    arrays = _random_net(spec)
    x = np.random.default_rng(1).normal(0, 0.5, (17, spec.k, spec.n_in))
    want = _torch_out(spec, arrays, x)
    net = NumpyNet(spec, arrays, dtype)
    got = net(x)
    assert got.shape == (17, spec.n_out) and got.dtype == dtype
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    one = net(x[3])                                        # a single query: (k, n_in) → (n_out,)
    assert one.shape == (spec.n_out,)
    np.testing.assert_allclose(one, want[3], atol=1e-5, rtol=0)


def test_numpy_net_rejects_a_wrong_input_shape():
    net = NumpyNet(MP, _random_net(MP))
    with pytest.raises(ParameterError, match=r"'mp' takes \(3, 3\)"):
        net(np.zeros((5, 3)))


def test_mlp_width_matches_the_lstm_parameter_budget():
    for hidden, layers, k, n_out in [(64, 2, 5, 6), (128, 2, 5, 48), (32, 1, 3, 6), (16, 3, 5, 48)]:
        lstm = NetSpec("lstm", k, hidden=hidden, layers=layers, n_out=n_out)
        mlp = NetSpec("mlp", k, hidden=hidden, layers=layers, n_out=n_out)
        w = mlp_width(mlp)
        assert param_count(lstm) == lstm_params(lstm) == param_count(model_from_spec(lstm))
        assert param_count(mlp) == param_count(model_from_spec(mlp)) <= param_count(lstm)
        assert mlp.width == w
        # one unit wider would exceed the budget
        extra = (k * 3 + 1 + n_out) + (layers - 1) * (2 * w + 2)
        assert param_count(mlp) + extra > param_count(lstm)
    assert mlp_width(NetSpec("mlp", 5, hidden=64, layers=2, n_out=6)) in range(200, 300)


def test_net_spec_rejects_nonsense():
    with pytest.raises(ParameterError, match="kind 'gru'"):
        NetSpec("gru", 3)
    with pytest.raises(ParameterError, match="hidden must be a positive integer"):
        NetSpec("lstm", 3, hidden=0)
    with pytest.raises(ParameterError, match="2 in_offsets for k = 3"):
        NetSpec("lstm", 3, in_offsets=(-5, 0))
    with pytest.raises(ParameterError, match="no '/'"):
        NetSpec("lstm", 3, name="a/b")


def test_importing_ik_net_does_not_import_torch():
    code = "import sys, felis.learning.ik.net as m; assert 'torch' not in sys.modules; print(m.NetSpec('mlp', 3).width)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


# ------------------------------------------------------------------------------------------ weights file


def _save_pair(path):
    nets = {"mp": (MP, _random_net(MP, 1)), "pe": (PE, _random_net(PE, 2))}
    save_weights(path, nets, {"training": {"mp": {"val_loss": np.float32(0.01).item(), "spec": MP}},
                              "data": "synthetic", "offsets": np.arange(3)})
    return nets


def test_weights_round_trip(tmp_path):
    path = tmp_path / "ik.npz"
    nets = _save_pair(path)
    assert not list(tmp_path.glob(".*.tmp"))            # the temporary file was renamed away
    loaded, meta = load_weights(path, expect={"nets": ("mp", "pe"), "mp": MP,
                                              "pe": {"k": 5, "out_offsets": [0, 1, 2, 3, 4, 5]}})
    assert set(loaded) == {"mp", "pe"}
    assert meta["model"] == "felis-ik" and meta["schema"] == 1 and meta["data"] == "synthetic"
    assert meta["training"]["mp"]["val_loss"] == np.float32(0.01).item() and meta["offsets"] == [0, 1, 2]
    assert NetSpec.from_json(meta["training"]["mp"]["spec"]) == MP
    assert meta["nets"]["mp"]["in_offsets"] == [-10, -5, 0] and meta["nets"]["pe"]["out_offsets"] == [0, 1, 2, 3, 4, 5]
    assert meta["nets"]["mp"]["params"] == param_count(MP) == MP.param_count
    arrays, meta2 = load_arrays(path)                     # the raw form re-saves unchanged
    assert meta2 == meta and arrays["pe"][0] == PE
    for key, arr in nets["pe"][1].items():
        np.testing.assert_array_equal(arrays["pe"][1][key], arr)
    for name, (spec, arrays) in nets.items():
        assert loaded[name].spec == spec
        x = np.random.default_rng(3).normal(0, 0.5, (4, spec.k, 3))
        np.testing.assert_array_equal(loaded[name](x), NumpyNet(spec, arrays)(x))
        np.testing.assert_allclose(loaded[name](x), _torch_out(spec, arrays, x), atol=1e-5)
    with np.load(path, allow_pickle=False) as z:             # plain npz, readable without felis
        assert "mp/lstm.weight_hh_l1" in z.files and z["pe/out.weight"].dtype == np.float32


def _rewrite(src, dst, edit):
    """Copy weights file ``src`` to ``dst`` with its arrays (and parsed metadata) changed by ``edit``."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["__meta__"]))
    edit(arrays, meta)
    if "__meta__" in arrays:
        arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(dst, **arrays)
    return dst


def _set(d, key, value):
    d[key] = value


BAD_FILES = {
    "missing": (lambda good, p: p, "no such weights file"),
    "text": (lambda good, p: p.write_text("weights!\n") and p, "not a weights file (.npz)"),
    "truncated": (lambda good, p: p.write_bytes(good.read_bytes()[: good.stat().st_size // 2]) and p,
                  "corrupt or truncated weights file"),
    "npy": (lambda good, p: np.save(p.with_suffix(".npy"), np.zeros(3)) or p.with_suffix(".npy"),
            "a single .npy array"),
    "pickled": (lambda good, p: np.savez(p, a=np.array([{"x": 1}], dtype=object)) or p,
                "holds pickled objects, which felis refuses to load"),
    "pickle": (lambda good, p: p.write_bytes(__import__("pickle").dumps({"w": [1.0]})) and p,
               "not a weights file (.npz)"),
    "no-meta": (lambda good, p: _rewrite(good, p, lambda a, m: a.pop("__meta__")), "no '__meta__' metadata"),
    "model-id": (lambda good, p: _rewrite(good, p, lambda a, m: _set(m, "model", "felis-landing")),
                 "model id 'felis-landing' is not 'felis-ik'"),
    "schema": (lambda good, p: _rewrite(good, p, lambda a, m: _set(m, "schema", 99)), "weights schema 99 is not"),
    "missing-array": (lambda good, p: _rewrite(good, p, lambda a, m: a.pop("pe/lstm.bias_hh_l0")),
                      "net 'pe' lacks array 'lstm.bias_hh_l0'"),
    "shape": (lambda good, p: _rewrite(good, p, lambda a, m: _set(a, "mp/out.bias", np.zeros(7, np.float32))),
              r"net 'mp' array 'out.bias' has shape (7,), the spec needs (6,)"),
    "spec-shape": (lambda good, p: _rewrite(good, p, lambda a, m: _set(m["nets"]["mp"]["spec"], "hidden", 17)),
                   "net 'mp' array 'inp.weight' has shape (16, 3), the spec needs (17, 3)"),
    "nan": (lambda good, p: _rewrite(good, p, lambda a, m: a["mp/lstm.weight_ih_l1"].__setitem__((0, 0), np.nan)),
            "net 'mp' array 'lstm.weight_ih_l1' holds non-finite values"),
    "zero-std": (lambda good, p: _rewrite(good, p, lambda a, m: a["pe/y_std"].__setitem__(0, 0.0)),
                 "'y_std' holds a non-positive standard deviation"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_weights_file_gives_one_specific_line(tmp_path, case):
    good = tmp_path / "good.npz"
    _save_pair(good)
    make, message = BAD_FILES[case]
    bad = make(good, tmp_path / f"{case}.npz")
    with pytest.raises(WeightsError) as err:
        load_weights(bad)
    text = str(err.value)
    assert "\n" not in text and str(bad) in text
    assert message in text, text


@pytest.mark.parametrize("expect, message", [
    ({"ik": None}, "holds nets 'mp', 'pe', not the expected 'ik'"),
    ({"nets": ("mp", "ik", "x")}, "holds nets 'mp', 'pe', not the expected 'ik', 'x'"),
    ({"mp": {"in_offsets": (-4, -2, 0)}}, "net 'mp' has in_offsets (-10, -5, 0), expected (-4, -2, 0)"),
    ({"pe": NetSpec("lstm", 5, n_out=24, name="pe")}, "net 'pe' has n_out 48, expected 24"),
])
def test_weights_not_as_expected(tmp_path, expect, message):
    path = tmp_path / "ik.npz"
    _save_pair(path)
    with pytest.raises(WeightsError) as err:
        load_weights(path, expect=expect)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_save_refuses_bad_nets_and_leaves_no_file(tmp_path):
    arrays = _random_net(MP)
    arrays["out.weight"][0, 0] = np.inf
    with pytest.raises(WeightsError, match="'out.weight' holds non-finite"):
        save_weights(tmp_path / "ik.npz", {"mp": (MP, arrays)})
    with pytest.raises(ParameterError, match="spec name 'mp'"):
        save_weights(tmp_path / "ik.npz", {"pe": (MP, _random_net(MP))})
    with pytest.raises(ParameterError, match="reserved key"):
        save_weights(tmp_path / "ik.npz", {"mp": (MP, _random_net(MP))}, {"model": "x"})
    with pytest.raises(WeightsError, match="must end in .npz"):
        save_weights(tmp_path / "ik.pt", {"mp": (MP, _random_net(MP))})
    assert list(tmp_path.iterdir()) == []


def test_weights_file_is_replaced_whole(tmp_path):
    path = tmp_path / "ik.npz"
    _save_pair(path)
    save_weights(path, {"mp": (MP, _random_net(MP, 5))})
    nets, _ = load_weights(path)
    assert set(nets) == {"mp"} and zipfile.is_zipfile(path)
    assert [p.name for p in tmp_path.iterdir()] == ["ik.npz"]


# ---------------------------------------------------------------------------------------------- training

SMALL = TrainConfig(epochs=2, batch=32, lr=5e-3, lr_decay=0.9, grad_clip=1.0, seed=3, threads=1, kind="lstm",
                    hidden=8, layers=2)


def _data(n: int, seed: int, k: int = 3):
    """A learnable mapping: the targets are smooth functions of the frames."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (n, k, 3)).astype(np.float32)
    y = np.concatenate([x[:, -1] + 0.5 * (x[:, -1] - x[:, 0]), np.sin(2 * x[:, -1]) * 0.3 + 1.0], axis=1)
    return x, y.astype(np.float32)


@pytest.mark.parametrize("kind", ["lstm", "mlp"])
def test_training_is_deterministic(kind):
    cfg = TrainConfig(**{**SMALL.__dict__, "kind": kind})
    spec = cfg.net_spec("mp", 3, 6)
    x, y = _data(200, 0)
    xv, yv = _data(50, 1)
    threads = torch.get_num_threads()
    a, ha = train_net(x, y, xv, yv, spec, cfg)
    b, hb = train_net(x, y, xv, yv, spec, cfg)
    assert torch.get_num_threads() == threads            # the run restores torch's settings
    for key, arr in torch_to_arrays(a).items():
        np.testing.assert_array_equal(arr, torch_to_arrays(b)[key])
    assert ha["train"] == hb["train"] and ha["val"] == hb["val"] and len(ha["lr"]) == 2
    json.dumps(ha)                                        # the history is plain JSON
    c, _ = train_net(x, y, xv, yv, spec, TrainConfig(**{**cfg.__dict__, "seed": 4}))
    assert not np.array_equal(torch_to_arrays(c)["out.weight"], torch_to_arrays(a)["out.weight"])


def test_resume_after_interruption_equals_an_uninterrupted_run(tmp_path):
    cfg = TrainConfig(**{**SMALL.__dict__, "epochs": 4})
    spec = cfg.net_spec("mp", 3, 6)
    x, y = _data(160, 0)
    xv, yv = _data(40, 1)
    whole, hw = train_net(x, y, xv, yv, spec, cfg, checkpoint=tmp_path / "a.npz")

    class Stop(Exception):
        pass

    def stop_after_2(epoch, epochs, train, val):
        if epoch == 2:
            raise Stop

    ckpt = tmp_path / "b.npz"
    with pytest.raises(Stop):
        train_net(x, y, xv, yv, spec, cfg, checkpoint=ckpt, progress=stop_after_2)
    seen = []
    resumed, hr = train_net(x, y, xv, yv, spec, cfg, checkpoint=ckpt, resume=True,
                            progress=lambda *a: seen.append(a[:2]))
    assert seen == [(3, 4), (4, 4)]
    for key, arr in torch_to_arrays(whole).items():
        np.testing.assert_array_equal(arr, torch_to_arrays(resumed)[key])
    assert hr["val"] == hw["val"] and hr["best_epoch"] == hw["best_epoch"] and hr["best_val"] == hw["best_val"]
    # a finished run resumed with more epochs continues; with another config it is refused
    more = TrainConfig(**{**cfg.__dict__, "epochs": 5})
    _, h5 = train_net(x, y, xv, yv, spec, more, checkpoint=ckpt, resume=True)
    assert len(h5["val"]) == 5 and h5["val"][:4] == hw["val"]
    other = TrainConfig(**{**cfg.__dict__, "lr": 1e-3})
    with pytest.raises(WeightsError, match=r"another training config \(lr: 0.005 there, 0.001 now\)"):
        train_net(x, y, xv, yv, spec, other, checkpoint=ckpt, resume=True)
    with pytest.raises(WeightsError, match="another training data"):
        train_net(x[:-1], y[:-1], xv, yv, spec, cfg, checkpoint=ckpt, resume=True)


def test_corrupt_checkpoint_gives_one_line(tmp_path):
    cfg = TrainConfig(**{**SMALL.__dict__, "epochs": 1})
    spec = cfg.net_spec("mp", 3, 6)
    x, y = _data(64, 0)
    ckpt = tmp_path / "c.npz"
    train_net(x, y, None, None, spec, cfg, checkpoint=ckpt)
    ckpt.write_bytes(ckpt.read_bytes()[:-200])
    with pytest.raises(WeightsError) as err:
        train_net(x, y, None, None, spec, cfg, checkpoint=ckpt, resume=True)
    assert "corrupt or truncated IK training checkpoint file" in str(err.value) and "\n" not in str(err.value)
    _save_pair(ckpt)                                      # a weights file is not a checkpoint
    with pytest.raises(WeightsError, match="is no IK training checkpoint"):
        train_net(x, y, None, None, spec, cfg, checkpoint=ckpt, resume=True)


def test_training_reduces_the_loss():
    cfg = TrainConfig(epochs=8, batch=32, lr=1e-2, lr_decay=0.9, seed=0, threads=1)  # architecture: the spec's
    spec = NetSpec("lstm", 3, hidden=16, layers=1, n_out=6, name="mp")
    x, y = _data(1200, 0)
    xv, yv = _data(300, 1)
    model, hist = train_net(x, y, xv, yv, spec, cfg)
    # standardised MSE: 1 would be predicting the mean; the first epoch ends near 0.1
    assert hist["val"][-1] < 0.25 * hist["val"][0] and hist["best_val"] < 0.03
    assert hist["best_epoch"] == int(np.argmin(hist["val"])) + 1
    net = NumpyNet(spec, torch_to_arrays(model))          # the shipped form predicts in target units
    err = net(xv) - yv
    assert float(np.sqrt(np.mean(err ** 2))) < 0.2 * float(np.std(yv))


def test_training_rejects_mismatched_inputs():
    spec = SMALL.net_spec("mp", 3, 6)
    x, y = _data(20, 0)
    with pytest.raises(ParameterError, match=r"inputs have shape \(20, 3, 3\), net 'pe' needs \(N, 5, 3\)"):
        train_net(x, y, None, None, SMALL.net_spec("pe", 5, 6), SMALL)
    with pytest.raises(ParameterError, match="has kind 'mlp' but the training config says 'lstm'"):
        train_net(x, y, None, None, NetSpec("mlp", 3, hidden=8, layers=2, name="mp"), SMALL)
    y[0, 0] = np.nan
    with pytest.raises(ParameterError, match="non-finite"):
        train_net(x, y, None, None, spec, SMALL)
    assert ik_net.SeqNet is type(model_from_spec(spec))
