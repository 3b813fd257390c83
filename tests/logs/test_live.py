"""The live view (`felis.logs.live`): a real Foxglove WebSocket server on localhost and a real client speaking
the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``, with the `websockets` library) subscribed to a
simulated run on the wall clock: it receives the scene, joint states, transforms and events, each channel in
time order.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import threading
import time

import numpy as np
import pytest
import websockets

from felis.controllers import PoseController
from felis.errors import ParameterError
from felis.logs.live import LiveView, parse_address
from felis.logs.reader import protobuf_class
from felis.logs.runlog import RunLog
from felis.loop import run_loop
from felis.sim import MujocoRobot
from felis.sim.scene import MujocoPoses, model_scene
from felis.spec import load_spec

TOPICS = ("/robot", "/joint_states", "/tf", "/log")
SUBPROTOCOL = "foxglove.sdk.v1"  # the Foxglove WebSocket protocol as the SDK's server names it (formerly
#                                  foxglove.websocket.v1; same messages)


def test_parse_address():
    assert parse_address("8765") == ("127.0.0.1", 8765)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address("[::1]:0") == ("::1", 0)
    for bad in ("x", "70000", "host:"):
        with pytest.raises(ParameterError, match="--live"):
            parse_address(bad)


async def _client(url: str, subscribed: threading.Event, done: threading.Event, got: dict) -> None:
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
        channels: dict[str, dict] = {}
        while not set(TOPICS) <= set(channels):
            msg = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["op"] == "advertise":
                    channels.update({c["topic"]: c for c in m["channels"]})
        subs = {i: channels[t] for i, t in enumerate(TOPICS)}
        await ws.send(json.dumps({"op": "subscribe",
                                  "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()]}))
        subscribed.set()
        got["channels"] = {t: channels[t] for t in TOPICS}
        while True:
            try:
                msg = await asyncio.wait_for(ws.recv(), 0.5 if done.is_set() else 10)
            except (TimeoutError, websockets.ConnectionClosed):  # quiet, or the command ended and closed it
                return
            if isinstance(msg, bytes) and msg[0] == 1:  # message data: op, subscription id, log time, payload
                sub, log_time = struct.unpack_from("<IQ", msg, 1)
                got.setdefault(subs[sub]["topic"], []).append((log_time, msg[13:]))


def test_client_receives_a_live_run_in_order():
    spec = load_spec("cat")
    got: dict = {}
    subscribed, done = threading.Event(), threading.Event()
    with LiveView(("127.0.0.1", 0)) as view, MujocoRobot(spec) as robot:
        assert view.url.startswith("ws://127.0.0.1:") and view.port > 0
        log = RunLog(None, spec, {"test": "live"}, scene=model_scene(robot.model), poses=MujocoPoses(robot),
                     live=view)
        client = threading.Thread(target=lambda: asyncio.run(_client(view.url, subscribed, done, got)))
        client.start()
        assert subscribed.wait(20), "the client never subscribed"
        for _ in range(200):  # the server has taken the subscriptions (the client sent them)
            if all(view.watchers(t)[0] for t in TOPICS):
                break
            time.sleep(0.01)

        def mark(state, command):  # an event every 10 ticks
            if round(state.t * 100) % 10 == 0:
                log.event(state.t, "mark", tick=round(state.t * 100))

        report = run_loop(robot, PoseController("stand"), duration=0.6, clock="wall", log=log, monitors=[mark])
        log.close({"ticks": report.ticks})
        done.set()
        client.join(30)
    assert not client.is_alive()
    ch = got["channels"]
    assert {ch[t]["schemaName"] for t in TOPICS} == {"foxglove.SceneUpdate", "foxglove.JointStates",
                                                      "foxglove.FrameTransforms", "foxglove.Log"}

    def decode(topic):
        c = ch[topic]
        cls = protobuf_class(c["schemaName"], base64.b64decode(c["schema"]))
        return [(t, cls.FromString(data)) for t, data in got.get(topic, [])]

    scene = decode("/robot")  # logged before the client subscribed: latched, sent on subscription
    assert len(scene) == 1 and {e.frame_id for e in scene[0][1].entities} >= {"world", "upper_body"}
    states, tfs, events = decode("/joint_states"), decode("/tf"), decode("/log")
    assert len(states) >= 0.8 * report.ticks and len(tfs) >= 0.8 * report.ticks
    for items in (states, tfs):
        times = [t for t, _ in items]
        assert times == sorted(times) and len(set(times)) == len(times)  # in order, none twice
    assert [t for t, _ in events] == sorted(t for t, _ in events)
    assert [j.name for j in states[0][1].joints] == list(spec.names)
    assert "upper_body" in {tf.child_frame_id for tf in tfs[-1][1].transforms}
    kinds = [m.name for _, m in events]
    assert kinds[0] == "armed" and kinds[-1] == "stopped"  # the loop's own events frame the run
    ticks = [json.loads(m.message.split(" ", 1)[1])["tick"] for _, m in events if m.name == "mark"]
    assert ticks == list(range(ticks[0], ticks[0] + 10 * len(ticks), 10)) and len(ticks) >= 4
    state_times = {t for t, _ in states}
    assert all(t in state_times for t, _ in events)  # events share their tick's time
    assert np.all(np.diff([t for t, _ in states]) > 0)


def _listening() -> set[str]:
    """Inodes of this process's listening TCP sockets (from /proc)."""
    import os

    mine = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            mine.add(target[8:-1])
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            f = row.split()
            if f[3] == "0A" and f[9] in mine:  # LISTEN
                out.add(f[9])
    return out


def test_nothing_listens_without_live(tmp_path):
    """A run log without a live view opens no listening socket; with one, exactly the view listens."""
    spec = load_spec("arm")
    before = _listening()
    with RunLog(tmp_path / "a.mcap", spec):
        assert _listening() == before
    with LiveView("0") as view, RunLog(None, spec, live=view):
        assert len(_listening() - before) == 1


def test_eval_landing_serves_its_one_drop_live(tmp_path, monkeypatch, capsys):
    """``felis eval landing --live``: the one drop runs on the wall clock while a real client watches it; the
    verdict is the evaluation's, printed as usual."""
    from felis.cli import output
    from felis.cli.main import main

    drops = tmp_path / "drop.json"
    drops.write_text(json.dumps([{"roll_deg": 0, "pitch_deg": 0, "yaw_deg": 0, "height_m": 0.3}]))
    got: dict = {}
    subscribed, done = threading.Event(), threading.Event()
    clients = []

    def on_live(url):  # the address the command prints: a client connects to it
        clients.append(threading.Thread(target=lambda: asyncio.run(_client(url, subscribed, done, got))))
        clients[0].start()

    monkeypatch.setattr(output, "live", on_live)
    rc = main(["eval", "landing", "--drops", str(drops), "--policy", "stand", "--live", "0", "--json"])
    done.set()
    assert rc == 0 and clients
    clients[0].join(30)
    result = json.loads(capsys.readouterr().out)
    assert result["total"] == 1 and result["drops"][0]["height_m"] == 0.3
    ch = got["channels"]

    def decode(topic):
        c = ch[topic]
        cls = protobuf_class(c["schemaName"], base64.b64decode(c["schema"]))
        return [(t, cls.FromString(data)) for t, data in got.get(topic, [])]

    states, tfs = decode("/joint_states"), decode("/tf")
    assert len(decode("/robot")) == 1
    assert len(states) >= 50 and len(tfs) >= 50  # ≈ 125 ticks of 1.25 s on the wall clock, the client came early
    for items in (states, tfs):
        times = [t for t, _ in items]
        assert times == sorted(times) and len(set(times)) == len(times)


def test_eval_live_needs_one_episode(capsys):
    from felis.cli.main import main

    assert main(["eval", "balance", "--pushes", "random:2", "--live", "0"]) != 0
    assert "--live shows one episode, and 2 pushes are given" in capsys.readouterr().err


_HAMMER = r"""
import asyncio, json, sys, websockets
async def main(url):
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        print("connected", flush=True)
        k = 1
        while True:  # subscriptions to channels that do not exist: the SDK logs an error for each, under a lock
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": k + i, "channelId": 10_000_000 + k + i} for i in range(50)]}))
            k += 50
            try:
                await asyncio.wait_for(ws.recv(), 0.001)
            except asyncio.TimeoutError:
                pass
asyncio.run(main(sys.argv[1]))
"""

_RUNS = r"""
import subprocess, sys, time
from felis.logs.live import LiveView
from felis.logs.runlog import RunLog
from felis.spec import load_spec
spec = load_spec("cat")
with LiveView(("127.0.0.1", 0)) as view:
    client = subprocess.Popen([sys.executable, "-c", sys.argv[1], view.url], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, text=True)
    assert client.stdout.readline().strip() == "connected"
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < float(sys.argv[2]):
        RunLog(None, spec, live=view).close()  # channels made and closed while the viewer sends
        n += 1
    client.kill()
print("runs", n)
"""


@pytest.mark.parametrize("level", [None, pytest.param("error", marks=pytest.mark.slow)])
def test_closing_channels_while_a_viewer_subscribes_never_deadlocks(level):
    """The SDK's server thread logs (Python, the GIL) while it holds a client's lock; a run closing its channels
    holds the GIL and waits for that lock (`felis.logs.sdk`). A viewer subscribing to unknown channels hits that
    path thousands of times a second; 4 s of logs opened and closed must all finish. The control (slow): with
    the SDK's records forwarded again (``FOXGLOVE_LOG_LEVEL=error``) the same script hangs."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "FOXGLOVE_LOG_LEVEL"}
    if level is not None:
        env["FOXGLOVE_LOG_LEVEL"] = level
    try:
        r = subprocess.run([sys.executable, "-c", _RUNS, _HAMMER, "4"], capture_output=True, text=True, timeout=60,
                           env=env)
    except subprocess.TimeoutExpired:
        assert level is not None, "closing a live view's channels deadlocked"
        return
    assert level is None, "the control did not deadlock: this test no longer provokes the SDK's lock order"
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(r.stdout.split()[-1]) > 100
