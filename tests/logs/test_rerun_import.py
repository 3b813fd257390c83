"""A third reader: Rerun's own MCAP import (``rerun mcap convert``, the Foxglove and Protobuf decoders) turns a felis
log into a Rerun recording with the robot's transforms, its events and every per-tick channel.

Rerun is not a dependency of felis (rerun-sdk installs ~460 MB: its viewer, CLI and pyarrow), so this test runs
where a ``rerun`` command is given: ``make test-rerun`` makes ``.venv-rerun`` with the pinned rerun-sdk and runs it
(``FELIS_RERUN=<path to rerun>``). Without one it is skipped and says why.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections import Counter

import pytest

from felis.logs.reader import read_log
from felis.sim.robot import load_model, model_path
from felis.spec import load_spec

RERUN = os.environ.get("FELIS_RERUN") or shutil.which("rerun")
pytestmark = pytest.mark.skipif(not RERUN, reason="no rerun command (make test-rerun installs one and runs this)")

CHUNK = re.compile(r"^Chunk\(\S+\) with (\d+) rows .* - (/\S+) - data columns: \[(.*)\]$")


@pytest.fixture(scope="module")
def drop_log(tmp_path_factory):
    from felis.cli.episode import Episode, run_episode

    path = tmp_path_factory.mktemp("rerun") / "drop.mcap"
    run_episode(Episode(robot="cat", controller="landing", duration=0.8, drop=(0.5, 40.0, 0.0, 0.0), log=path))
    return path


def _rerun(*args: str) -> str:
    r = subprocess.run([RERUN, *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_rerun_imports_the_log_with_transforms_events_and_every_tick(drop_log, tmp_path):
    rrd = tmp_path / "drop.rrd"
    _rerun("mcap", "check", str(drop_log))
    _rerun("mcap", "convert", str(drop_log), "-o", str(rrd), "--disable-raw-fallback")
    _rerun("rrd", "verify", str(rrd))
    rows: Counter[tuple[str, str]] = Counter()
    for line in _rerun("rrd", "print", str(rrd)).splitlines():
        m = CHUNK.match(line.strip())
        if m:
            for col in m.group(3).split():
                rows[(m.group(2), col)] += int(m.group(1))
    log = read_log(drop_log)
    ticks = len(log.t)
    bodies = load_model(model_path(load_spec("cat"))).nbody - 1  # /tf carries every body but the world
    # /tf: Foxglove's FrameTransforms become Rerun Transform3D rows, one per body per tick, with both frames
    assert rows[("/tf", "Transform3D:translation")] == ticks * bodies
    assert rows[("/tf", "Transform3D:quaternion")] == ticks * bodies
    assert rows[("/tf", "Transform3D:child_frame")] == ticks * bodies
    # /log: foxglove.Log becomes Rerun's TextLog, one row per event
    assert rows[("/log", "TextLog:text")] == len(log.events) > 0
    # every per-tick Protobuf channel, Foxglove's and felis's own, is decoded message by message
    for topic, schema in (("/joint_states", "foxglove.JointStates"), ("/joint_commands", "foxglove.JointStates"),
                          ("/imu", "felis.Imu"), ("/contacts", "felis.Contacts"), ("/base", "felis.Base"),
                          ("/timing", "felis.Timing")):
        assert rows[(topic, f"{schema}:message")] == log.counts[topic] == ticks, topic
    assert rows[("/robot", "foxglove.SceneUpdate:message")] == 1
