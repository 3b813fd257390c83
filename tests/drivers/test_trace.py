"""The packet trace (`felis.drivers.dynamixel.trace`): ``--trace FILE`` on a bus command and on ``felis run
--backend dxl``, through the real ``dynamixel-sdk`` over a pty against the virtual bus.

Every traced line is checked independently of the trace's own decoder: its hex is parsed again with
`felis.drivers.dynamixel.protocol.PacketReader` (one packet, CRC valid, the ID and instruction the line
names), instructions are answered by statuses of the same ID, times never go back. Damaged replies are
marked (CRC-BAD, SHORT, JUNK); no trace leaves the SDK's port methods unwrapped; Ctrl-C flushes the file.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import dynamixel_sdk as sdk
import pytest

from felis.cli.main import main
from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.port import WaitingPortHandler
from felis.drivers.dynamixel.trace import PacketTrace, TracedBus
from felis.drivers.virtual import VirtualBus
from felis.spec import load_spec

BAUD = 1_000_000
NAMES = {name.upper(): inst for inst, name in P.INSTRUCTIONS.items()} | {"STATUS": P.STATUS}


@pytest.fixture(autouse=True)
def margin(monkeypatch):
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "100")  # the bus serves from this process: room on a loaded machine


def packets(path: Path) -> list[tuple[float, str, int, str, str, P.Packet]]:
    """(time, TX/RX, ID, name, decoded text, packet parsed again from the hex) of every packet line; asserts that
    each line's hex is one CRC-valid packet with the ID and instruction the line names."""
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            continue
        text, hexpart = line.split(" | ")
        t, direction, dxl_id, name, *_ = text.split()
        found = P.PacketReader().feed(bytes.fromhex(hexpart))
        assert len(found) == 1 and found[0].crc_ok, line
        pkt = found[0]
        assert pkt.raw == bytes.fromhex(hexpart) and pkt.id == int(dxl_id) and pkt.inst == NAMES[name], line
        out.append((float(t), direction, int(dxl_id), name, text, pkt))
    times = [p[0] for p in out]
    assert times == sorted(times)
    return out


def test_read_trace_pairs_every_instruction_with_its_status(tmp_path):
    with VirtualBus.for_robot("arm", baud=BAUD) as vb:
        trace = tmp_path / "sub" / "read.trace"
        assert main(["read", "12", "present_position", "--port", vb.port, "--trace", str(trace)]) == 0
    lines = trace.read_text().splitlines()
    assert lines[0].startswith("# felis packet trace") and lines[-1] == "# end: 2 TX, 2 RX packets, 0 damaged"
    got = packets(trace)
    assert [(d, i, n) for _, d, i, n, _, _ in got] == [("TX", 12, "PING"), ("RX", 12, "STATUS"), ("TX", 12, "READ"),
                                                        ("RX", 12, "STATUS")]
    assert "model=1020" in got[1][4] and "addr=132 len=4" in got[2][4]
    assert got[3][5].params == got[3][5].raw[9:13]  # the four bytes of Present Position


def test_run_on_dxl_traces_group_transfers_per_id_and_the_torque_off(tmp_path, capsys):
    spec = load_spec("arm")
    ids = [j.servo_id for j in spec.joints]
    trace = tmp_path / "run.trace"
    with VirtualBus.for_robot(spec, baud=BAUD) as vb:  # the suite's 1 s deadman (tests/conftest.py)
        rc = main(["run", "hold", "--robot", "arm", "--backend", "dxl", "--port", vb.port, "--duration", "0.2",
                   "--trace", str(trace), "--json"])
    out = capsys.readouterr().out
    assert rc == 0, out
    got = packets(trace)
    tx = [p for p in got if p[1] == "TX"]
    reads = [p for p in tx if p[3] in ("SYNC_READ", "FAST_SYNC_READ")]
    writes = [p for p in tx if p[3] == "SYNC_WRITE"]
    assert len(reads) >= 10 and len(writes) >= 10  # a 0.2 s run at 100 Hz, one read and one write per tick
    assert all(f"ids={','.join(map(str, ids))}" in p[4] for p in reads if "addr=126" in p[4])
    for _, _, _, _, text, pkt in writes:  # decoded per ID: each ID's bytes are those in the packet
        n = pkt.params[2] | pkt.params[3] << 8
        rows = pkt.params[4:]
        for k in range(0, len(rows), n + 1):
            assert f" {rows[k]}={rows[k + 1:k + 1 + n].hex().upper()}" in text
    last = [p for p in writes if "addr=64 len=1" in p[4]][-1][4]  # the shutdown path's torque off, traced
    assert all(f" {i}=00" in last for i in ids)
    fast = [p for p in got if p[1] == "RX" and p[2] == P.BROADCAST_ID]
    for p in fast:  # a fast sync read's one reply, decoded per servo
        assert all(f" {i}=" in p[4] for i in ids)
    assert trace.read_text().splitlines()[-1].startswith("# end: ")


def test_damaged_replies_are_marked(tmp_path):
    trace = tmp_path / "bad.trace"
    ping = P.instruction(1, P.PING)
    status = P.status(1, 0, bytes((0xB0, 0x04, 0x34)))
    corrupt = bytearray(status)
    corrupt[9] ^= 0x10
    with PacketTrace(trace) as tr:
        tr.tx(ping)
        tr.rx(b"\x00\x13" + status[:5])  # junk, then a reply that stops short
        tr.rx(status[5:8])
        tr.tx(ping)  # the next instruction: the unfinished reply is over
        tr.rx(bytes(corrupt))
        tr.tx(ping)
        tr.rx(status[:6])  # still unfinished when the trace closes
    lines = trace.read_text().splitlines()
    body = [ln.split(" ", 1)[1] for ln in lines[1:-1]]
    assert body[0].startswith("TX 1 PING")
    assert body[1] == "RX JUNK 2 bytes before a header"
    assert body[2] == f"RX SHORT 8 bytes (no complete packet) | {status[:8].hex(' ').upper()}"
    assert body[4].startswith("RX 1 STATUS CRC-BAD err=0")
    assert body[6] == f"RX SHORT 6 bytes (no complete packet) | {status[:6].hex(' ').upper()}"
    assert lines[-1] == "# end: 3 TX, 1 RX packets, 4 damaged"


def test_no_trace_leaves_the_sdk_port_alone_and_a_trace_wraps_it(tmp_path):
    with VirtualBus.for_models(["XL330-M288-T"], baud=BAUD) as vb:
        with DynamixelBus(vb.port, BAUD) as b:
            port = b._port
            assert isinstance(port, sdk.PortHandler) and port.writePort.__func__ is sdk.PortHandler.writePort
            assert port.readPort.__func__ is WaitingPortHandler.readPort  # the SDK's, waiting instead of spinning
        trace = tmp_path / "t.trace"
        with PacketTrace(trace) as tr, TracedBus(vb.port, BAUD, trace=tr) as b:
            assert not hasattr(b._port.writePort, "__func__")
            b.set_baud(57600)  # a note in the trace
            b.set_baud(BAUD)
            b.ping(1)
    text = trace.read_text()
    assert "baud 57600" in text and " TX 1 PING " in text
    assert not (tmp_path / "never.trace").exists()
    with PacketTrace(tmp_path / "never.trace"):
        pass  # nothing traced: no file
    assert not (tmp_path / "never.trace").exists()


def test_bad_trace_path_is_one_line_and_ctrl_c_flushes_the_trace(tmp_path, capsys):
    with VirtualBus.for_robot("arm", baud=BAUD) as vb:
        (tmp_path / "dir").mkdir()
        assert main(["read", "11", "led", "--port", vb.port, "--trace", str(tmp_path / "dir")]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: cannot write packet trace") and len(err.splitlines()) == 1
        assert vb.stats.packets == 0  # refused before the bus was opened
        assert main(["run", "hold", "--robot", "arm", "--trace", str(tmp_path / "t.trace")]) == 1
        assert "--trace records the Dynamixel bus" in capsys.readouterr().err

        # Ctrl-C: a real SIGINT to this process while `felis monitor` polls; felis's handler unwinds it
        trace = tmp_path / "monitor.trace"

        def interrupt():
            deadline = time.monotonic() + 30
            while vb.stats.packets < 20 and time.monotonic() < deadline:  # monitoring: packets on the bus
                time.sleep(0.02)
            os.kill(os.getpid(), signal.SIGINT)

        threading.Thread(target=interrupt, daemon=True).start()
        rc = main(["monitor", "--port", vb.port, "--robot", "arm", "--rate", "50", "--trace", str(trace), "--json"])
    assert rc == 130, capsys.readouterr().err
    assert vb.stats.packets >= 20
    lines = trace.read_text().splitlines()
    assert lines[-1].startswith("# end: ") and len(lines) > 20
    # every line whole and CRC-valid: nothing cut by the interrupt, except that a reply the SIGINT stopped halfway
    # through reading is traced as what arrived (one "RX SHORT" record, the last packet line; CI saw it once)
    body = [x for x in lines if not x.startswith("#")]
    if " RX SHORT " in body[-1]:
        assert body[-1].split()[1:3] == ["RX", "SHORT"] and "(no complete packet)" in body[-1]
        cut = trace.with_suffix(".whole")
        cut.write_text("\n".join(x for x in lines if x != body[-1]) + "\n")
        trace = cut
    packets(trace)
