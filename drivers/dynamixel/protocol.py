"""Dynamixel Protocol 2.0 at the byte level: CRC, byte stuffing, packet building and parsing.

The bus driver talks through the unmodified ``dynamixel-sdk``; this module is what the virtual bus
and the tests use to speak the protocol themselves (``shared/reference/dynamixel.md``).

Instruction packet::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | params… | CRC_L CRC_H      LEN = 1 + len(params) + 2

Status packet: the same with INST = 0x55 followed by the error byte, then the parameters.

CRC-16/BUYPASS (polynomial 0x8005, initial 0, no reflection, no final xor) over the whole stuffed
packet from the first ``FF`` to the last parameter, appended low byte first.

Byte stuffing: in INST..params every ``FF FF FD`` is followed by an extra ``FD`` (LEN counts it);
the receiver removes it. A header search skips ``FF FF FD FD``.
"""

from __future__ import annotations

from dataclasses import dataclass

from felis.drivers.framing import skip_to_header

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
MAX_PACKET = 1024  # the SDK's RXPACKET_MAX_LEN / TXPACKET_MAX_LEN bound on LEN

PING, READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x10
STATUS = 0x55
SYNC_READ, SYNC_WRITE, FAST_SYNC_READ = 0x82, 0x83, 0x8A
BULK_READ, BULK_WRITE, FAST_BULK_READ = 0x92, 0x93, 0x9A
INSTRUCTIONS = {PING: "ping", READ: "read", WRITE: "write", REG_WRITE: "reg_write", ACTION: "action",
                FACTORY_RESET: "factory_reset", REBOOT: "reboot", CLEAR: "clear", SYNC_READ: "sync_read",
                SYNC_WRITE: "sync_write", FAST_SYNC_READ: "fast_sync_read", BULK_READ: "bulk_read",
                BULK_WRITE: "bulk_write", FAST_BULK_READ: "fast_bulk_read"}

# Status error byte: bit 7 Alert; bits 0-6 hold one error number.
ALERT = 0x80
RESULT_FAIL, INSTRUCTION_ERROR, CRC_ERROR, DATA_RANGE_ERROR, DATA_LENGTH_ERROR, DATA_LIMIT_ERROR, ACCESS_ERROR = \
    1, 2, 3, 4, 5, 6, 7
STATUS_ERRORS = {RESULT_FAIL: "result fail", INSTRUCTION_ERROR: "instruction error", CRC_ERROR: "CRC error",
                 DATA_RANGE_ERROR: "data range error", DATA_LENGTH_ERROR: "data length error",
                 DATA_LIMIT_ERROR: "data limit error", ACCESS_ERROR: "access error"}


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16/BUYPASS of ``data``, continuing from ``crc``."""
    t = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ b]
    return crc


def stuff(body: bytes | bytearray) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` in INST..params."""
    if b"\xff\xff\xfd" not in body:
        return bytes(body)
    return bytes(body).replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes | bytearray) -> bytes:
    """Remove the ``FD`` stuffed after every ``FF FF FD``."""
    if b"\xff\xff\xfd\xfd" not in body:
        return bytes(body)
    return bytes(body).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def _packet(dxl_id: int, body: bytes) -> bytes:
    body = stuff(body)
    n = len(body) + 2
    head = HEADER + bytes((dxl_id & 0xFF, n & 0xFF, n >> 8))
    pkt = head + body
    c = crc16(pkt)
    return pkt + bytes((c & 0xFF, c >> 8))


def instruction(dxl_id: int, inst: int, params: bytes | bytearray = b"") -> bytes:
    """A complete, stuffed instruction packet."""
    return _packet(dxl_id, bytes((inst,)) + bytes(params))


def status(dxl_id: int, error: int, params: bytes | bytearray = b"") -> bytes:
    """A complete, stuffed status packet."""
    return _packet(dxl_id, bytes((STATUS, error & 0xFF)) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A parsed packet: ``inst`` is the instruction (0x55 for status); ``params`` are unstuffed.

    For a status packet ``error`` is the error byte and ``params`` follow it. ``crc_ok`` is False
    for a well-framed packet whose CRC does not match (a servo answers those with a CRC Error).
    """

    id: int
    inst: int
    params: bytes
    error: int = 0
    crc_ok: bool = True
    raw: bytes = b""


class PacketReader:
    """Incremental parser: ``feed(bytes)`` returns the complete packets found so far.

    Resynchronises on garbage: bytes before a header are dropped (counted in ``dropped``); a header
    with an impossible length is skipped one byte at a time. Never raises on any input.
    ``pending`` is how many bytes wait for the rest of a packet; ``reset()`` drops them (a real
    servo's receiver does the same after an inter-byte gap).
    """

    def __init__(self):
        self.buf = bytearray()
        self.dropped = 0

    @property
    def pending(self) -> int:
        return len(self.buf)

    def reset(self) -> None:
        self.dropped += len(self.buf)
        self.buf.clear()

    def feed(self, data: bytes | bytearray) -> list[Packet]:
        buf = self.buf
        buf += data
        out: list[Packet] = []
        while True:
            skipped, found = skip_to_header(buf, HEADER)  # a possible header prefix at the end is kept
            self.dropped += skipped
            if not found:
                return out
            if len(buf) < 7:
                return out
            n = buf[5] | buf[6] << 8
            if n < 3 or n > MAX_PACKET:
                self.dropped += 1
                del buf[:1]
                continue
            total = 7 + n
            if len(buf) < total:
                return out
            pkt = bytes(buf[:total])
            del buf[:total]
            crc_ok = crc16(pkt[:-2]) == (pkt[-2] | pkt[-1] << 8)
            body = unstuff(pkt[7:-2])
            if not body:
                continue
            inst = body[0]
            if inst == STATUS and len(body) >= 2:
                out.append(Packet(pkt[4], inst, body[2:], body[1], crc_ok, pkt))
            else:
                out.append(Packet(pkt[4], inst, body[1:], 0, crc_ok, pkt))


def describe_status_error(error: int) -> str:
    """``0x87`` -> ``"alert, access error"``; 0 -> ``"ok"``."""
    parts = []
    if error & ALERT:
        parts.append("alert (hardware error)")
    code = error & 0x7F
    if code:
        parts.append(STATUS_ERRORS.get(code, f"error {code}"))
    return ", ".join(parts) or "ok"
