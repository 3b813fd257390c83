"""Two readers that felis does not own check its logs: a port of Foxglove's JSON-schema rules (every JSON
channel's schema), and the `mcap` reader with the Protobuf decoder of `mcap-protobuf-support` (every message of
a real simulated drop decodes). The per-tick Protobuf templates (`felis.logs.wire`) decode to what the SDK's own
encoder writes. Rerun's MCAP import is the third reader (`tests/logs/test_rerun_import.py`, `make test-rerun`).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from foxglove.messages import (
    FrameTransform,
    FrameTransforms,
    JointState,
    JointStates,
    Log,
    Quaternion,
    SceneUpdate,
    Timestamp,
    Vector3,
)
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from felis.logs.messages import BASE, IMU, TIMING, contacts_message
from felis.logs.monitorlog import MonitorExport
from felis.logs.reader import protobuf_class
from felis.logs.schemas import FAULTS_SCHEMA, jsonable, schema_of
from felis.logs.skills import BALANCE_SCHEMA, PHASE_SCHEMA
from felis.logs.wire import FrameTransformsEncoder, JointStatesEncoder
from tests.logs.foxglove_rules import Rejected, parse_json_schema

WELL_KNOWN = {s.name: s.data for s in (JointStates.get_schema(), FrameTransforms.get_schema(),
                                        SceneUpdate.get_schema(), Log.get_schema())}


@pytest.fixture(scope="module")
def drop_log(tmp_path_factory):
    """A real simulated drop of the cat under the landing controller, logged as `felis sim drop --log` does."""
    from felis.cli.episode import Episode, run_episode

    path = tmp_path_factory.mktemp("drop") / "drop.mcap"
    res = run_episode(Episode(robot="cat", controller="landing", duration=0.8, drop=(0.5, 40.0, 0.0, 0.0), log=path))
    assert res.files["log"] == str(path)
    return path


@pytest.fixture(scope="module")
def balance_log(tmp_path_factory):
    """The trotting cat under the balance monitor with the learned phase estimator as its gait gate, logged as
    `felis run balance --base step-in-place --gate phase --log` does: /balance every tick, /phase once the
    estimator's window is full."""
    from felis.cli.episode import Episode, run_episode

    path = tmp_path_factory.mktemp("balance") / "balance.mcap"
    run_episode(Episode(robot="cat", controller="balance", duration=1.4, log=path,
                        controller_options={"base": "step-in-place", "gate": "phase"}))
    return path


@pytest.fixture(scope="module")
def monitor_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("mon") / "m.mcap"
    sink = MonitorExport(None, path, [1, 2], robot="cat", joints=["spine_pitch", "spine_yaw"])
    ok = {"id": 1, "stale": False, "position": 0.1, "velocity": 0.0, "current": 0.01, "temperature": 30,
          "voltage": 12.1, "status_error": 0, "hardware_errors": []}
    missing = {"id": 2, "stale": True, "position": None, "velocity": None, "current": None, "temperature": None,
               "voltage": None, "status_error": 0, "hardware_errors": []}
    for i in range(5):
        sink.write(i / 30, [ok, missing])
    sink.close()
    return path


# ---------------------------------------------------------------------------------------------
# reader 1: Foxglove's schema rules


def test_the_port_rejects_what_foxglove_rejected_in_felis_0_2():
    for bad in ({"type": "object", "properties": {"t": {"type": ["number", "null"]}}},  # a union
                {"type": "object", "properties": {"detail": {"type": "object"}}},  # no properties
                {"type": "object", "properties": {"servos": {"type": "array"}}},  # no items
                {"type": "object", "properties": {"m": {"type": "array", "items": {"type": "array",
                                                                                   "items": {"type": "number"}}}}},
                {"type": "object"}):  # felis 0.2's /summary
        with pytest.raises(Rejected):
            parse_json_schema(bad)
    parse_json_schema(FAULTS_SCHEMA)
    parse_json_schema(BALANCE_SCHEMA)
    parse_json_schema(PHASE_SCHEMA)


def test_inferred_schemas_pass_for_awkward_values():
    value = jsonable({"a": None, "b": [[1, 2], [3]], "c": {}, "d": [], "e": [{"x": 1}, {"y": "s"}], "f": np.float64(2),
                      "g": [1, 2.5], "h": float("nan"), "i": (True, False)})
    parse_json_schema(schema_of(value))
    assert "a" not in value and "h" not in value and value["b"] == [{"items": [1, 2]}, {"items": [3]}]


FELIS = {m.schema.name: m.schema.data for m in (IMU, BASE, TIMING, contacts_message(["fl_foot", "fr_foot", "hl_foot",
                                                                                     "hr_foot"]))}


@pytest.mark.parametrize("which", ["drop_log", "balance_log", "monitor_log"])
def test_every_channel_is_well_known_or_passes_foxglove_rules(which, request):
    path = request.getfixturevalue(which)
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    seen = set()
    for ch in summary.channels.values():
        schema = summary.schemas[ch.schema_id]
        seen.add(ch.topic)
        if ch.message_encoding == "protobuf" and schema.name.startswith("felis."):  # felis's own, in Protobuf
            assert schema.encoding == "protobuf" and schema.data == FELIS[schema.name], ch.topic
        elif ch.message_encoding == "protobuf":
            assert schema.encoding == "protobuf" and WELL_KNOWN.get(schema.name) == schema.data, ch.topic
        else:
            assert (ch.message_encoding, schema.encoding) == ("json", "jsonschema"), ch.topic
            parse_json_schema(json.loads(schema.data), schema.name)
    if which == "drop_log":
        assert seen >= {"/meta", "/robot", "/joint_states", "/joint_commands", "/tf", "/imu", "/contacts", "/base",
                        "/faults", "/timing", "/landing", "/summary"}
    elif which == "balance_log":
        assert seen >= {"/joint_states", "/tf", "/balance", "/phase"}
        assert summary.schemas[next(c.schema_id for c in summary.channels.values() if c.topic == "/balance")].data \
            == json.dumps(BALANCE_SCHEMA).encode()
    else:
        assert seen == {"/meta", "/joint_states", "/monitor"}


# ---------------------------------------------------------------------------------------------
# reader 2: mcap + the Protobuf decoder


def _decode_all(path) -> list[tuple]:
    """(topic, log time, decoded) of every message, in file order: Protobuf ones by mcap-protobuf-support's
    decoder, JSON ones by ``json``."""
    out = []
    factory, decoders = DecoderFactory(), {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            if channel.message_encoding == "protobuf":
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for("protobuf", schema)
                out.append((channel.topic, message.log_time, decoders[schema.id](message.data)))
            else:
                out.append((channel.topic, message.log_time, json.loads(message.data)))
    return out


def test_balance_and_phase_messages_fit_their_schemas(balance_log):
    """Every /balance and /phase message decodes and carries only the fields of its schema, each of the
    schema's one type (Foxglove reads a field by its schema); the estimator's phase is in [0, 1)."""
    kinds = {"number": (int, float), "boolean": (bool,), "string": (str,), "object": (dict,)}
    msgs = {"/balance": [], "/phase": []}
    states = 0
    for topic, ns, m in _decode_all(balance_log):
        states += topic == "/joint_states"
        if topic in msgs:
            msgs[topic].append((ns, m))
    assert len(msgs["/balance"]) == states == 140 and 10 <= len(msgs["/phase"]) < states
    for topic, schema in (("/balance", BALANCE_SCHEMA), ("/phase", PHASE_SCHEMA)):
        times = [ns for ns, _ in msgs[topic]]
        assert times == sorted(times)
        for _, m in msgs[topic]:
            for k, v in m.items():
                field = schema["properties"][k]
                assert isinstance(v, kinds[field["type"]]) and (field["type"] == "boolean") == isinstance(v, bool)
                if field["type"] == "object":
                    assert set(v) <= set(field["properties"])
                    assert all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v.values())
    b = [m for _, m in msgs["/balance"]]
    assert all({"margin", "alarm", "warning", "class", "xcom", "com"} <= set(m) for m in b)
    assert all(-0.5 < m["margin"] < 0.5 for m in b)
    ph = [m for _, m in msgs["/phase"]]
    assert all(m["source"] == "estimator" and 0 <= m["phase"] < 1 for m in ph)


def test_every_message_of_a_drop_decodes_with_mcap_and_protobuf(drop_log):
    counts: dict[str, int] = {}
    last: dict[str, int] = {}
    factory, decoders = DecoderFactory(), {}
    with open(drop_log, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            if channel.message_encoding == "protobuf":
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for("protobuf", schema)
                decoded = decoders[schema.id](message.data)
            else:
                decoded = json.loads(message.data)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            assert message.log_time >= last.get(channel.topic, 0)  # in time order on each channel
            last[channel.topic] = message.log_time
            if channel.topic == "/joint_states":
                assert len(decoded.joints) == 12 and decoded.joints[0].name == "spine_pitch"
                assert decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos == message.log_time
            elif channel.topic == "/tf":
                frames = [tf.child_frame_id for tf in decoded.transforms]
                assert "upper_body" in frames and "fl_foot" in frames
                assert all(tf.parent_frame_id == "world" for tf in decoded.transforms)
                r = decoded.transforms[0].rotation
                assert abs(r.x**2 + r.y**2 + r.z**2 + r.w**2 - 1) < 1e-6
            elif channel.topic == "/robot":
                frames = {e.frame_id for e in decoded.entities}
                assert "world" in frames and "upper_body" in frames  # the floor and the cat's bodies
                assert sum(len(e.cubes) + len(e.spheres) + len(e.cylinders) for e in decoded.entities) > 15
            elif channel.topic == "/meta":
                assert decoded["robot"] == "cat" and message.log_time > 1_600_000_000 * 10**9
    assert counts["/joint_states"] == counts["/joint_commands"] == counts["/tf"] == 80
    assert counts["/robot"] == counts["/meta"] == counts["/landing"] == counts["/summary"] == 1


# ---------------------------------------------------------------------------------------------
# the templates against the SDK's encoder


def test_templates_decode_to_what_the_sdk_encodes():
    rng = np.random.default_rng(3)
    ns = 1_760_000_000_123_456_789
    names = ["upper_body", "head", "x"]
    v = rng.normal(size=(3, 7))
    v[1, 2] = 0.0  # a zero the SDK leaves out and the template writes
    cls = protobuf_class("foxglove.FrameTransforms", FrameTransforms.get_schema().data)
    sdk = FrameTransforms(transforms=[FrameTransform(
        timestamp=Timestamp(sec=ns // 10**9, nsec=ns % 10**9), parent_frame_id="world", child_frame_id=n,
        translation=Vector3(x=a[0], y=a[1], z=a[2]), rotation=Quaternion(x=a[3], y=a[4], z=a[5], w=a[6]))
        for n, a in zip(names, v.tolist(), strict=True)])
    enc = FrameTransformsEncoder(names)
    assert cls.FromString(enc.encode(ns, v)) == cls.FromString(sdk.encode())
    for other in (0, 5, 10**9 - 1, ns + 7):  # timestamps of every length reuse or add a template
        assert cls.FromString(enc.encode(other, v)).transforms[2].timestamp.nanos == other % 10**9
    jcls = protobuf_class("foxglove.JointStates", JointStates.get_schema().data)
    q, dq = rng.normal(size=4), rng.normal(size=4)
    q[1] = np.nan
    mine = jcls.FromString(JointStatesEncoder(list("abcd"), ("position", "velocity")).encode(ns, (q, dq)))
    sdk = jcls.FromString(JointStates(timestamp=Timestamp(sec=ns // 10**9, nsec=ns % 10**9), joints=[
        JointState(name=n, position=a, velocity=b) for n, a, b in zip("abcd", q.tolist(), dq.tolist(),
                                                                      strict=True)]).encode())
    assert [j.name for j in mine.joints] == list("abcd") and not mine.joints[0].HasField("effort")
    assert np.isnan(mine.joints[1].position) and np.isnan(sdk.joints[1].position)
    mine.joints[1].position = sdk.joints[1].position = 0.0  # NaN != NaN
    assert mine == sdk


def test_the_shipped_layout_opens_panels_on_channels_the_logs_have(drop_log):
    """docs/foxglove-layout.json (README, "Logs in Foxglove"): 3D, plot, log and raw-message panels, each on a
    channel a drop log has; the plotted joint names are the cat's (or the arm's)."""
    import re
    from pathlib import Path

    from felis.spec import load_spec

    layout = json.loads((Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json").read_text())
    panels = {k.split("!")[0] for k in layout["configById"]}
    assert panels == {"3D", "Plot", "Log", "RawMessages"}
    text = json.dumps(layout["configById"])
    topics = set(re.findall(r'"(/[a-z_]+)[."]', text)) | set(re.findall(r"(/[a-z_]+)\.", text))
    with open(drop_log, "rb") as fh:
        have = {c.topic for c in make_reader(fh).get_summary().channels.values()}
    assert topics and topics <= have, topics - have
    names = set(re.findall(r'name==\\"(\w+)\\"', text))
    assert names and names <= set(load_spec("cat").names) | set(load_spec("arm").names)


def test_csv_export_has_every_per_tick_channel(balance_log, tmp_path):
    """`felis log export LOG --csv DIR`: the joints, the IMU, the skills' channels (/balance, /phase) and /timing,
    a row per message, a column per number (nested fields joined with dots), flags as 0/1."""
    import csv

    from felis.logs.export import export_csv
    from felis.logs.reader import channel_messages, read_log

    files = {p.name: p for p in export_csv(balance_log, tmp_path / "csv")}
    assert {"joint_states.csv", "joint_commands.csv", "imu.csv", "events.csv", "balance.csv", "phase.csv",
            "timing.csv"} <= set(files)
    data = read_log(balance_log)
    msgs = channel_messages(balance_log, {"/balance", "/phase"})
    for name, topic in (("balance.csv", "/balance"), ("phase.csv", "/phase")):
        with open(files[name]) as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == data.counts[topic] == len(msgs[topic]) > 0
        t, _ = msgs[topic][-1]
        assert float(rows[-1]["t"]) == pytest.approx(t, abs=1e-6)
    with open(files["balance.csv"]) as fh:
        header = next(csv.reader(fh))
    assert {"margin", "alarm", "warning", "xcom.x", "xcom.y", "com.z"} <= set(header) and "class" not in header
    with open(files["joint_states.csv"]) as fh:
        assert sum(1 for _ in fh) == len(data.t) + 1
