"""IK demonstration data (felis.learning.ik.data): the posture rule, demonstrations, corpus, splits,
network windows, angle encoding, files (npz corpus, CSV trajectories, run logs) and builtins."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from felis import armkin
from felis.armkin import REACH, SHOULDER
from felis.controllers import arm_posture as AP
from felis.controllers import trajectories as TR
from felis.errors import LogError, ParameterError, TrajectoryError
from felis.learning.ik import corpus as C
from felis.learning.ik import data as D
from felis.learning.ik import infer as IN

SEED = 11


@pytest.fixture(scope="module")
def corpus():
    return D.make_corpus(40, SEED)


def _workspace_grid() -> np.ndarray:
    """Points meeting the geometric bounds on a grid (r, z) × 12 azimuths (±15°, ±45°, …, ±165°: the
    joint1 limit margin excludes a 0.05 rad wedge straight behind the base)."""
    r, z = np.meshgrid(np.linspace(AP.R_MIN, 0.36, 36), np.linspace(AP.Z_MIN, 0.43, 50))
    r, z = r.ravel(), z.ravel()
    keep = np.hypot(r, z - SHOULDER[2]) <= AP.D_MAX * REACH
    r, z = r[keep], z[keep]
    th = np.linspace(-np.pi, np.pi, 12, endpoint=False) + np.pi / 12
    return np.concatenate([D._cyl(r, np.full_like(r, a), z) for a in th])


# ---------------------------------------------------------------------------------------------
# the demonstrator


def test_posture_rule_feasible_over_the_whole_workspace():
    pts = _workspace_grid()
    assert AP.in_workspace(pts).all()  # the rule excludes nothing the geometric bounds allow
    q, ok = armkin.ik_closed(pts, AP.posture_pitch(pts), True)
    assert ok.all() and armkin.within_limits(q).all()


def test_posture_rule_limits():
    # far reach along the reach direction; close and low pointing (nearly) down
    far = SHOULDER + 0.95 * REACH * np.array([math.cos(-0.3), 0.0, math.sin(-0.3)])
    assert AP.posture_pitch(far) == pytest.approx(0.3, abs=0.01)
    close_low = np.array([SHOULDER[0] + 0.08, 0.0, 0.03])
    assert 1.3 < AP.posture_pitch(close_low) < math.pi / 2
    # vectorised, and independent of the azimuth
    pts = np.array([[0.2, 0.0, 0.1], [0.012, 0.188, 0.1], [-0.176, 0.0, 0.1]])
    assert np.allclose(AP.posture_pitch(pts), AP.posture_pitch(pts[0]))
    assert AP.posture_pitch(pts.reshape(3, 1, 3)).shape == (3, 1)


def test_posture_rule_is_smooth():
    """Finite differences along random lines through the workspace: a kink (slope jump s) would give
    |Δ²φ|/h² ≈ s/h = 10⁴ s, a curvature jump an unbounded |Δ³φ|/h³."""
    rng = np.random.default_rng(0)
    h = 1e-4
    checked = 0
    for _ in range(100):
        a = D._sample_point(rng, rng.uniform(-3, 3), 0.3)
        b = D._sample_point(rng, rng.uniform(-3, 3), 0.3)
        u = (b - a) / np.linalg.norm(b - a)
        pts = a + np.arange(0.0, min(np.linalg.norm(b - a), 0.2), h)[:, None] * u
        if not AP.in_workspace(pts).all():
            continue
        phi = AP.posture_pitch(pts)
        assert np.abs(np.diff(phi, 2)).max() / h**2 < 300
        assert np.abs(np.diff(phi, 3)).max() / h**3 < 2e4
        checked += 1
    assert checked > 20


def test_rule_feasible_and_smooth_on_corpus(corpus):
    for tr in corpus:
        assert AP.in_workspace(tr.p).all()
        assert armkin.within_limits(tr.q, tol=0).all()
        phi = AP.posture_pitch(tr.p, AP.path_velocity(tr.p))
        assert np.abs(np.diff(phi)).max() < 0.05  # rad per frame: no jumps
        assert np.abs(np.diff(tr.q, axis=0)).max() <= D.QD_MAX * AP.DT + 1e-12


def test_demo_joints_reproduce_points(corpus):
    for tr in corpus:
        assert np.abs(armkin.fk(tr.q) - tr.p).max() < 1e-9
        assert np.allclose(armkin.pitch(tr.q), AP.posture_pitch(tr.p, AP.path_velocity(tr.p)), atol=1e-9)
        assert armkin.elbow_up(tr.q).all()


def test_posture_rule_leads_vertical_motion():
    p = np.array([0.2, 0.0, 0.15])
    rest = AP.posture_pitch(p)
    down = AP.posture_pitch(p, np.array([0.0, 0.0, -0.1]))
    up = AP.posture_pitch(p, np.array([0.0, 0.0, 0.1]))
    assert down > rest > up
    w = AP.smootherstep((np.linalg.norm(p - armkin.SHOULDER) / armkin.REACH - AP.D_NEAR) / (AP.D_FAR - AP.D_NEAR))
    assert down - rest == pytest.approx((1 - w) * AP.K_LEAD * np.tanh(0.1 / AP.V_LEAD), abs=1e-12)
    assert AP.posture_pitch(p, np.array([0.3, -0.2, 0.0])) == pytest.approx(rest)  # horizontal motion: no lead
    np.testing.assert_allclose(AP.path_velocity(np.outer(np.arange(5) * AP.DT, [1.0, 2.0, 3.0])),
                               np.tile([1.0, 2.0, 3.0], (5, 1)), atol=1e-12)


def test_demo_joints_names_first_infeasible_frame():
    pts = np.tile([0.25, 0.0, 0.15], (6, 1))
    pts[3] = [0.6, 0.0, 0.1]  # out of reach
    pts[5] = [0.6, 0.0, 0.1]
    with pytest.raises(TrajectoryError, match=r"^frame 3: target \(0\.6000, 0\.0000, 0\.1000\) m"):
        AP.demo_joints(pts)
    with pytest.raises(TrajectoryError, match="shape"):
        AP.demo_joints(np.zeros((4, 2)))


# ---------------------------------------------------------------------------------------------
# trajectories and corpus


def test_trajectories_are_realistic(corpus):
    assert {tr.kind for tr in corpus} == set(D.KINDS)
    assert [tr.ident for tr in corpus] == list(range(40))
    for tr in corpus:
        assert D.MIN_LEN - 0.01 <= tr.t[-1] <= D.MAX_LEN + 0.01
        assert np.allclose(np.diff(tr.t), AP.DT)
        v = np.linalg.norm(np.diff(tr.p, axis=0), axis=1) / AP.DT
        a = np.linalg.norm(np.diff(tr.p, 2, axis=0), axis=1) / AP.DT**2
        assert v.max() <= D.V_MAX and a.max() <= D.A_MAX
        assert v[0] < 0.01 and v[-1] < 0.01  # starts from and ends at rest
    q1 = np.concatenate([tr.q[:, 0] for tr in D.make_corpus(120, 2)])
    front = np.mean(np.abs(q1) < np.pi / 2)
    assert 0.6 < front < 0.98 and np.any(np.abs(q1) > 2.5)  # mostly in front, some behind


def test_make_corpus_is_deterministic(corpus):
    again = D.make_corpus(40, SEED)
    for a, b in zip(corpus, again, strict=True):
        assert (a.kind, a.ident) == (b.kind, b.ident)
        assert np.array_equal(a.t, b.t) and np.array_equal(a.p, b.p) and np.array_equal(a.q, b.q)
    short = D.make_corpus(5, SEED)  # a prefix of the longer corpus
    assert all(np.array_equal(a.p, b.p) for a, b in zip(short, corpus[:5], strict=False))
    other = D.make_corpus(5, SEED + 1)
    assert not any(a.p.shape == b.p.shape and np.array_equal(a.p, b.p) for a, b in zip(short, other, strict=True))
    assert D.make_corpus(0, SEED) == []


def test_generate_unknown_kind():
    with pytest.raises(ParameterError, match="unknown trajectory kind 'zigzag'"):
        D.generate("zigzag", np.random.default_rng(0))


def test_split_has_no_leakage_and_covers_everything(corpus):
    train, val, test = D.split(corpus, seed=3)
    assert (len(train), len(val), len(test)) == (32, 4, 4)
    ids = [{tr.ident for tr in s} for s in (train, val, test)]
    assert not (ids[0] & ids[1] or ids[0] & ids[2] or ids[1] & ids[2])
    assert ids[0] | ids[1] | ids[2] == set(range(40))
    frames = [{row.tobytes() for tr in s for row in tr.p} for s in (train, val, test)]
    assert not (frames[0] & frames[1] or frames[0] & frames[2] or frames[1] & frames[2])
    again = D.split(corpus, seed=3)
    assert [[tr.ident for tr in s] for s in again] == [[tr.ident for tr in s] for s in (train, val, test)]
    assert [tr.ident for tr in D.split(corpus, seed=4)[1]] != [tr.ident for tr in val]


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 7])
def test_split_sizes(corpus, n):
    parts = D.split(corpus[:n], seed=0)
    assert sum(len(p) for p in parts) == n
    if n >= 3:
        assert all(len(p) >= 1 for p in parts)
    with pytest.raises(ParameterError):
        D.split(corpus, 0, fractions=(0.8, -0.1, 0.3))


# ---------------------------------------------------------------------------------------------
# network data


def _tiny(n: int = 12, ident: int = 0) -> TR.Trajectory:
    p = SHOULDER + np.outer(np.arange(n), [0.01, 0.0, 0.0]) + np.array([0.1, 0.0, 0.0])
    q = np.outer(np.arange(n), [0.1, 0.2, -0.3, 0.4])
    return TR.Trajectory(t=np.arange(n) * AP.DT, p=p, q=q, kind="hand", ident=ident)


def test_normalise():
    assert np.allclose(IN.normalise(SHOULDER), 0)
    assert np.allclose(IN.normalise(SHOULDER + [REACH, 0, 0]), [1, 0, 0])


def test_windows_shapes_and_edge_padding():
    tr = _tiny()
    v = IN.normalise(tr.p)
    X, Y = D.windows([tr], IN.MP_IN, IN.MP_OUT)
    assert X.dtype == np.float32 and Y.dtype == np.float32
    assert X.shape == (12, 3, 3) and Y.shape == (12, 6)
    assert np.allclose(X[0], v[[0, 0, 0]]) and np.allclose(Y[0], v[[5, 10]].ravel())
    assert np.allclose(X[7], v[[0, 2, 7]]) and np.allclose(Y[7], v[[11, 11]].ravel())
    assert np.allclose(X[11], v[[1, 6, 11]]) and np.allclose(Y[11], v[[11, 11]].ravel())
    X, Y = D.windows([tr, _tiny(5, 1)], IN.PE_IN, IN.PE_OUT, target="angles")
    assert X.shape == (17, 5, 3) and Y.shape == (17, 48)
    assert np.allclose(Y[3].reshape(6, 8), IN.encode_angles(tr.q[[3, 4, 5, 6, 7, 8]]), atol=1e-7)
    assert np.allclose(Y[10].reshape(6, 8), IN.encode_angles(tr.q[[10, 11, 11, 11, 11, 11]]), atol=1e-7)
    assert np.allclose(IN.decode_angles(Y[12].reshape(6, 8)), _tiny(5).q[[0, 1, 2, 3, 4, 4]], atol=1e-6)
    X, Y = D.windows([], IN.MP_IN, IN.MP_OUT, target="angles")
    assert X.shape == (0, 3, 3) and Y.shape == (0, 16)
    nq = TR.Trajectory(t=tr.t, p=tr.p, q=None, kind="file", ident=-1)
    with pytest.raises(TrajectoryError, match="no joint angles"):
        D.windows([nq], IN.PE_IN, IN.PE_OUT, target="angles")
    with pytest.raises(ParameterError):
        D.windows([tr], IN.MP_IN, IN.MP_OUT, target="poses")


def test_encode_decode_round_trip():
    q = np.array([[np.pi, -np.pi, 0.0, 1.0], [np.pi - 1e-9, -np.pi + 1e-9, -2.5, 3.0]])
    x = IN.encode_angles(q)
    assert x.shape == (2, 8)
    assert np.allclose(x[0, :2], [0.0, -1.0]) and np.allclose(x[0, 2:4], [0.0, -1.0])
    back = IN.decode_angles(x)
    assert np.abs(np.angle(np.exp(1j * (back - q)))).max() < 1e-12
    assert np.abs(x[1, :2] - x[0, :2]).max() < 1e-8  # continuous across ±π
    rng = np.random.default_rng(0)
    qr = rng.uniform(-np.pi, np.pi, (5, 7, 4))
    assert np.allclose(IN.decode_angles(IN.encode_angles(qr)), qr, atol=1e-12)
    assert np.allclose(IN.decode_angles(3.0 * IN.encode_angles(qr)), qr)  # pairs need not be unit


# ---------------------------------------------------------------------------------------------
# files


def test_corpus_npz_round_trip(tmp_path, corpus):
    items = corpus[:4] + [TR.Trajectory(t=corpus[4].t, p=corpus[4].p, q=None, kind="file", ident=99)]
    path = C.save_corpus(tmp_path / "sub" / "corpus.npz", items)
    back = C.load_corpus(path)
    assert [(tr.kind, tr.ident) for tr in back] == [(tr.kind, tr.ident) for tr in items]
    for a, b in zip(items, back, strict=True):
        assert np.array_equal(a.t, b.t) and np.array_equal(a.p, b.p)
        assert (a.q is None and b.q is None) or np.array_equal(a.q, b.q)
    assert C.load_corpus(C.save_corpus(tmp_path / "empty.npz", [])) == []


def test_corpus_npz_errors(tmp_path):
    with pytest.raises(TrajectoryError, match="no such corpus file"):
        C.load_corpus(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(TrajectoryError, match="not a corpus .npz file"):
        C.load_corpus(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", w=np.zeros(3))
    with pytest.raises(TrajectoryError, match="missing array"):
        C.load_corpus(tmp_path / "other.npz")
    np.savez(tmp_path / "pickled.npz", t=np.zeros(1), p=np.zeros((1, 3)), q=np.zeros((1, 4)),
             start=np.array([0, 1]), meta=np.array([{"a": 1}], dtype=object))
    with pytest.raises(TrajectoryError):
        C.load_corpus(tmp_path / "pickled.npz")
    meta = json.dumps({"format": "felis-ik-corpus", "version": 1, "kinds": ["x"], "ids": [0], "has_q": [True]})
    np.savez(tmp_path / "bad.npz", t=np.zeros(2), p=np.zeros((2, 3)), q=np.zeros((3, 4)),
             start=np.array([0, 2]), meta=np.array(meta))
    with pytest.raises(TrajectoryError, match="inconsistent shapes") as info:
        C.load_corpus(tmp_path / "bad.npz")
    assert "\n" not in str(info.value)


def test_csv_round_trip(tmp_path, corpus):
    tr = corpus[0]
    path = TR.write_trajectory_csv(tmp_path / "a" / "tr.csv", tr)
    assert path.read_text().splitlines()[0] == "t,x,y,z,q1,q2,q3,q4"
    back = TR.read_trajectory_csv(path)
    assert (back.kind, back.q) == ("file", None)
    assert np.array_equal(back.t, tr.t) and np.array_equal(back.p, tr.p)
    # columns in any order, extra columns ignored, blank lines skipped, spaces allowed
    (tmp_path / "b.csv").write_text("z, note ,x,t,y\n0.1,a,0.2,0.0,0.0\n\n0.1,b,0.21,0.0101,0.0\n")
    b = TR.read_trajectory_csv(tmp_path / "b.csv")
    assert np.allclose(b.t, [0, 0.0101]) and np.allclose(b.p, [[0.2, 0, 0.1], [0.21, 0, 0.1]])


@pytest.mark.parametrize("text, match", [
    ("t,x,y\n0,0,0\n0.01,0,0\n", r"bad\.csv:1: missing column 'z'"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,abc,0\n", r"bad\.csv:3: column y: 'abc' is not a number"),
    ("t,x,y,z\n0,0,0,0\n0.01,nan,0,0\n", r"bad\.csv:3: column x: 'nan' is not finite"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,0,inf\n", r"bad\.csv:3: column z: 'inf' is not finite"),
    ("t,x,y,z\n0,0,0,0\n", r"bad\.csv: 1 data row\(s\); a trajectory needs at least 2"),
    ("t,x,y,z\n", r"bad\.csv: 0 data row"),
    ("", r"bad\.csv:1: empty"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,0,0\n0.01,0,0,0\n", r"bad\.csv:4: column t: 0.01 s is not after 0.01 s"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,0,0\n0.005,0,0,0\n", r"bad\.csv:4: column t: 0.005 s is not after"),
    ("t,x,y,z\n0,0,0,0\n0.02,0,0,0\n", r"bad\.csv:3: column t: step 0.02 s .*100 Hz"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,0,0\n0.0212,0,0,0\n", r"bad\.csv:4: column t: step 0.0112 s"),
    ("t,x,y,z\n0,0,0,0\n0.01,0,0\n", r"bad\.csv:3: 3 fields, the header has 4"),
    ("t,x,y,z,t\n0,0,0,0,0\n0.01,0,0,0,0\n", r"bad\.csv:1: column 't' appears 2 times"),
])
def test_csv_bad_input(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=match) as info:
        TR.read_trajectory_csv(path)
    assert "\n" not in str(info.value)


def test_csv_missing_or_not_a_file(tmp_path):
    with pytest.raises(TrajectoryError, match=r"none\.csv: no such trajectory file"):
        TR.read_trajectory_csv(tmp_path / "none.csv")
    with pytest.raises(TrajectoryError, match="is a directory"):
        TR.read_trajectory_csv(tmp_path)
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00t,x")
    with pytest.raises(TrajectoryError, match="not a text CSV file"):
        TR.read_trajectory_csv(tmp_path / "bin.csv")


# ---------------------------------------------------------------------------------------------
# builtins and recorded demonstrations


@pytest.mark.parametrize("name, kw", [("circle", {}), ("circle", {"plane": "horizontal"}), ("figure8", {}),
                                      ("circle", {"duration": 3.3}), ("figure8", {"duration": 13.0})])
def test_builtins_feasible_and_smooth(name, kw):
    tr = TR.builtin_trajectory(name, **kw)
    assert tr.kind == name and tr.q is not None and len(tr) >= 2
    assert np.allclose(np.diff(tr.t), AP.DT)
    assert AP.in_workspace(tr.p).all()
    assert np.abs(armkin.fk(tr.q) - tr.p).max() < 1e-9
    v = np.linalg.norm(np.diff(tr.p, axis=0), axis=1) / AP.DT
    a = np.linalg.norm(np.diff(tr.p, 2, axis=0), axis=1) / AP.DT**2
    assert v[0] < 1e-3 and v[-1] < 1e-3 and v.max() < 0.15 and a.max() < 0.5
    if name == "circle" and "duration" not in kw:
        c = TR.CIRCLE_CENTRE[kw.get("plane", "vertical")]
        assert np.allclose(np.linalg.norm(tr.p - c, axis=1), 0.06, atol=1e-12)
        assert np.allclose(tr.p[0], tr.p[-1], atol=1e-12)  # whole laps close the curve
    if name == "figure8":
        extent = tr.p.max(axis=0) - tr.p.min(axis=0)
        assert extent[1] == pytest.approx(0.12, abs=2e-3) and extent[2] == pytest.approx(0.06, abs=2e-3)


def test_builtin_errors():
    assert set(TR.BUILTINS) == {"circle", "figure8"}
    with pytest.raises(ParameterError, match="unknown builtin trajectory 'square'"):
        TR.builtin_trajectory("square")
    with pytest.raises(ParameterError, match="plane"):
        TR.builtin_trajectory("circle", plane="diagonal")
    with pytest.raises(ParameterError, match="duration"):
        TR.builtin_trajectory("circle", duration=float("nan"))


def _write_log(path, robot: str, q: np.ndarray):
    from felis.hal import State
    from felis.logs.runlog import RunLog
    from felis.spec import load_spec

    spec = load_spec(robot)
    with RunLog(path, spec) as log:
        for i, qi in enumerate(q):
            full = np.zeros(spec.n)
            full[: len(qi)] = qi
            log.state(State(t=i * AP.DT, q=full, dq=np.zeros(spec.n)))
        log.close()


def test_recorded_demos(tmp_path, corpus):
    q = corpus[1].q[:50]
    _write_log(tmp_path / "arm.mcap", "arm", q)
    tr = C.recorded_demos(tmp_path / "arm.mcap")
    assert tr.kind == "recorded" and np.allclose(tr.t, np.arange(50) * AP.DT)
    assert np.array_equal(tr.q, q) and np.abs(tr.p - corpus[1].p[:50]).max() < 1e-9
    _write_log(tmp_path / "cat.mcap", "cat", np.zeros((5, 12)))
    with pytest.raises(TrajectoryError, match="not a run log of the arm"):
        C.recorded_demos(tmp_path / "cat.mcap")
    _write_log(tmp_path / "short.mcap", "arm", q[:1])
    with pytest.raises(TrajectoryError, match="at least 2"):
        C.recorded_demos(tmp_path / "short.mcap")
    with pytest.raises(LogError):
        C.recorded_demos(tmp_path / "none.mcap")
