"""Packet trace: every instruction and status packet on a Dynamixel bus, one line each, with its time.

Hooked at the byte level: `PacketTrace.attach` wraps the ``writePort`` / ``readPort`` (and ``setBaudRate``)
of the SDK's ``PortHandler`` object, so the trace holds exactly the bytes that went to and came from the
serial device, whichever SDK call sent them. The bytes are cut into packets by felis's own parser
(`felis.drivers.dynamixel.protocol.PacketReader`), decoded, and written as::

    12.003417 TX 1 WRITE addr=64 len=1 data=01 | FF FF FD 00 01 06 00 03 40 00 01 CC E6
    12.004102 RX 1 STATUS err=0 | FF FF FD 00 01 04 00 55 00 A1 0C

time in seconds since the trace started (monotonic clock; an RX packet's time is when its last byte was
read), direction, ID, instruction and its decoded parameters, then the packet's bytes in hex as on the wire
(stuffed, CRC included). Group instructions are decoded per ID (``SYNC_WRITE addr=116 len=4 1=00080000
2=…``, ``SYNC_READ … ids=1,2``, ``BULK_READ 1@132+4 …``); a status is decoded against the instruction it
answers (a ping's model and firmware, a fast sync read's per-ID segments). Damaged traffic is marked:
``CRC-BAD`` (a framed packet whose CRC does not match), ``RX SHORT`` (bytes of a packet that never
completed, flushed when the next instruction goes out or the trace closes) and ``RX JUNK n bytes`` (bytes
before any header). Lines starting with ``#`` are notes: the header, baud-rate changes, the closing count.

Cost: with no trace nothing is wrapped, so the bus runs the SDK's own methods. The file is created at
the first packet (a command refused before it talks writes nothing), written through a buffer and flushed
when the trace closes, which the command's ``with`` block does on every way out (an error, Ctrl-C /
SIGTERM as `felis.shutdown.Interrupted`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Self

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.errors import ParameterError
from felis.files import check_target, prepare_parent

HEADER_LINE = "# felis packet trace: seconds since start, TX host->servo / RX servo->host, decoded | wire bytes (hex)"


class PacketTrace:
    """A packet trace written to ``path`` (module doc). Use as a context manager; `attach` it to a port.

    The constructor checks the path (a folder, or a file in the way of a folder, is one ParameterError
    line) and creates nothing."""

    def __init__(self, path: str | os.PathLike, clock: Callable[[], float] = time.monotonic):
        self.path = Path(path)
        check_target(self.path, "packet trace", ParameterError)
        parent = next((p for p in self.path.parents if p.exists()), None)
        if parent is not None and not os.access(parent, os.W_OK):
            raise ParameterError(f"cannot write packet trace {self.path}: no permission to write in {parent}")
        self._clock = clock
        self._t0: float | None = None  # set when the first port is attached: times count from there
        self._file: IO[str] | None = None
        self._tx = P.PacketReader()
        self._rx = P.PacketReader()
        self._last: P.Packet | None = None  # the last instruction sent: what the next status answers
        self.counts = {"TX": 0, "RX": 0, "bad": 0}

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Mark an unfinished reply, write the closing count, flush and close (nothing if no packet went by)."""
        if self._file is None:
            return
        self._flush_rx()
        c = self.counts
        self._write(f"# end: {c['TX']} TX, {c['RX']} RX packets, {c['bad']} damaged")
        f, self._file = self._file, None
        f.close()

    def attach(self, port) -> None:
        """Trace a ``dynamixel_sdk.PortHandler`` (or anything with its ``writePort``/``readPort``/``setBaudRate``):
        its methods are wrapped on the object itself; attaching twice is harmless."""
        if getattr(port, "_felis_trace", None) is self:
            return
        if self._t0 is None:
            self._t0 = self._clock()
        write, read, set_baud = port.writePort, port.readPort, port.setBaudRate

        def writePort(packet):  # noqa: N802 - the SDK's name
            n = write(packet)
            self.tx(bytes(packet))
            return n

        def readPort(length):  # noqa: N802
            data = read(length)
            if data:
                self.rx(bytes(data))
            return data

        def setBaudRate(baudrate):  # noqa: N802
            ok = set_baud(baudrate)
            self.note(f"baud {baudrate}")
            return ok

        port.writePort, port.readPort, port.setBaudRate = writePort, readPort, setBaudRate
        port._felis_trace = self

    # ------------------------------------------------------------------ bytes in
    def tx(self, data: bytes) -> None:
        """Bytes the host wrote: a reply still incomplete is marked short first (its time is over)."""
        self._flush_rx()
        for pkt in self._tx.feed(data):
            self._last = pkt
            self._packet("TX", pkt)

    def rx(self, data: bytes) -> None:
        """Bytes the host read."""
        before = self._rx.dropped
        packets = self._rx.feed(data)
        junk = self._rx.dropped - before
        if junk:
            self.counts["bad"] += 1
            self._write(f"{self._now()} RX JUNK {junk} bytes before a header")
        for pkt in packets:
            self._packet("RX", pkt)

    def note(self, text: str) -> None:
        self._write(f"# {self._now()} {text}")

    # ------------------------------------------------------------------ lines
    def _flush_rx(self) -> None:
        if self._rx.pending:
            rest = bytes(self._rx.buf)
            self._rx.buf.clear()
            self.counts["bad"] += 1
            self._write(f"{self._now()} RX SHORT {len(rest)} bytes (no complete packet) | {_hex(rest)}")

    def _packet(self, direction: str, pkt: P.Packet) -> None:
        self.counts[direction] += 1
        mark = ""
        if not pkt.crc_ok:
            self.counts["bad"] += 1
            mark = " CRC-BAD"
        if pkt.inst == P.STATUS:
            body = f"STATUS{mark} err={_err(pkt.error)}{_status_fields(pkt, self._last)}"
        else:
            body = f"{_name(pkt.inst)}{mark}{_instruction_fields(pkt)}"
        self._write(f"{self._now()} {direction} {pkt.id} {body} | {_hex(pkt.raw)}")

    def _now(self) -> str:
        if self._t0 is None:
            self._t0 = self._clock()
        return f"{self._clock() - self._t0:.6f}"

    def _write(self, line: str) -> None:
        if self._file is None:
            prepare_parent(self.path, "packet trace", ParameterError)
            try:
                self._file = open(self.path, "w", encoding="ascii", buffering=1 << 16)  # noqa: SIM115 - closed in close()
            except OSError as e:
                raise ParameterError(f"cannot write packet trace {self.path}: {e.strerror or e}") from None
            self._file.write(HEADER_LINE + "\n")
        self._file.write(line + "\n")


class TracedBus(DynamixelBus):
    """A `DynamixelBus` whose port is traced: ``trace`` is attached every time the port opens."""

    def __init__(self, port: str, baud: int = 1_000_000, *, trace: PacketTrace, **kw):
        super().__init__(port, baud, **kw)
        self.trace = trace

    def open(self) -> Self:
        super().open()
        self.trace.attach(self._port)
        return self


# ------------------------------------------------------------------ decoding
def _hex(data: bytes) -> str:
    return data.hex(" ").upper()


def _name(inst: int) -> str:
    return P.INSTRUCTIONS.get(inst, f"INST_0x{inst:02X}").upper()


def _err(error: int) -> str:
    return "0" if not error else f"0x{error:02X} ({P.describe_status_error(error)})"


def _u16(b: bytes, i: int) -> int:
    return b[i] | b[i + 1] << 8


def _instruction_fields(pkt: P.Packet) -> str:
    """The parameters of an instruction, decoded (group instructions per ID); raw hex when malformed."""
    p, inst = pkt.params, pkt.inst
    try:
        if inst in (P.PING, P.ACTION, P.REBOOT) and not p:
            return ""
        if inst == P.READ and len(p) == 4:
            return f" addr={_u16(p, 0)} len={_u16(p, 2)}"
        if inst in (P.WRITE, P.REG_WRITE) and len(p) >= 3:
            return f" addr={_u16(p, 0)} len={len(p) - 2} data={p[2:].hex().upper()}"
        if inst == P.FACTORY_RESET and len(p) == 1:
            what = {0xFF: "all", 0x01: "all but ID", 0x02: "all but ID and baud"}.get(p[0], "invalid")
            return f" option=0x{p[0]:02X} ({what})"
        if inst in (P.SYNC_READ, P.FAST_SYNC_READ) and len(p) >= 5:
            return f" addr={_u16(p, 0)} len={_u16(p, 2)} ids={','.join(map(str, p[4:]))}"
        if inst == P.SYNC_WRITE and len(p) >= 4:
            addr, n = _u16(p, 0), _u16(p, 2)
            rows = p[4:]
            if n and len(rows) % (n + 1) == 0:
                per = [f"{rows[k]}={rows[k + 1:k + 1 + n].hex().upper()}" for k in range(0, len(rows), n + 1)]
                return f" addr={addr} len={n} " + " ".join(per)
        if inst in (P.BULK_READ, P.FAST_BULK_READ) and len(p) % 5 == 0 and p:
            return " " + " ".join(f"{p[k]}@{_u16(p, k + 1)}+{_u16(p, k + 3)}" for k in range(0, len(p), 5))
        if inst == P.BULK_WRITE:
            out, k = [], 0
            while k + 5 <= len(p):
                n = _u16(p, k + 3)
                out.append(f"{p[k]}@{_u16(p, k + 1)}+{n}={p[k + 5:k + 5 + n].hex().upper()}")
                k += 5 + n
            if k == len(p) and out:
                return " " + " ".join(out)
    except IndexError:
        pass
    return f" params={p.hex().upper()}" if p else ""


def _status_fields(pkt: P.Packet, last: P.Packet | None) -> str:
    """A status's parameters, decoded against the instruction it answers."""
    p = pkt.params
    asked = last.inst if last is not None else None
    if asked == P.PING and len(p) == 3:
        return f" model={_u16(p, 0)} fw={p[2]}"
    if asked == P.FAST_SYNC_READ and pkt.id == P.BROADCAST_ID and last is not None and len(last.params) >= 4:
        n = _u16(last.params, 2)
        seg = n + 4  # error, ID, data, CRC; the last segment's CRC is the packet's
        body = bytes((pkt.error,)) + p + b"\0\0"
        out = []
        for k in range(len(body) // seg):
            s = body[k * seg:(k + 1) * seg]
            out.append(f"{s[1]}={s[2:2 + n].hex().upper()}" + (f"(err={_err(s[0])})" if s[0] else ""))
        if len(body) % seg:
            out.append(f"SHORT+{len(body) % seg}")
        return " " + " ".join(out)
    return f" data={p.hex().upper()}" if p else ""
