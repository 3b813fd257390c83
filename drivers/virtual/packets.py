"""Status packets as the emulated servos send them, and the instruction groups the dispatcher tells apart.

`status_packet` is `felis.drivers.dynamixel.protocol.status` with the CRC of the constant prefix cached:
it builds the reply to every read, the bus's hot path. `fast_packet` builds the one packet of a
FAST_SYNC_READ / FAST_BULK_READ, whose segments chain their CRCs (``shared/reference/dynamixel.md``).
"""

from __future__ import annotations

from felis.drivers.dynamixel import protocol as P

GROUP_READS = (P.SYNC_READ, P.FAST_SYNC_READ, P.BULK_READ, P.FAST_BULK_READ)
GROUP_WRITES = (P.SYNC_WRITE, P.BULK_WRITE)
READS = (P.READ, *GROUP_READS)  # answered at Status Return Level >= 1

Reply = tuple[float, bytes]  # (the replying servo's return delay in s, status packet)

_PREFIX_CRC: dict[tuple[int, int, int], int] = {}


def status_packet(dxl_id: int, error: int, data: bytes = b"") -> bytes:
    """`protocol.status` with the CRC of the constant prefix cached (the hot path of every read)."""
    if b"\xff\xff\xfd" in data:
        return P.status(dxl_id, error, data)
    n = len(data) + 4
    key = (dxl_id, n, error)
    head = P.HEADER + bytes((dxl_id, n & 0xFF, n >> 8, P.STATUS, error))
    crc = _PREFIX_CRC.get(key)
    if crc is None:
        crc = _PREFIX_CRC[key] = P.crc16(head)
    crc = P.crc16(data, crc)
    return head + data + bytes((crc & 0xFF, crc >> 8))


def fast_packet(n_announced: int, segments: list[tuple[int, int, bytes]]) -> bytes:
    """A FAST_SYNC/BULK_READ status (ID 0xFE, not stuffed) announcing ``n_announced`` parameter bytes.

    Each servo appends ``ERR ID data CRC`` where its CRC covers every byte on the wire before it,
    earlier servos' CRC bytes included, so the last CRC is the whole packet's CRC (what the SDK
    checks). A missing servo's segment is absent and the packet is short of its announced length.
    """
    length = 1 + n_announced
    pkt = bytearray(P.HEADER + bytes((P.BROADCAST_ID, length & 0xFF, length >> 8, P.STATUS)))
    crc = P.crc16(pkt)
    for dxl_id, err, data in segments:
        seg = bytes((err & 0xFF, dxl_id)) + data
        crc = P.crc16(seg, crc)
        tail = bytes((crc & 0xFF, crc >> 8))
        pkt += seg + tail
        crc = P.crc16(tail, crc)
    return bytes(pkt)

