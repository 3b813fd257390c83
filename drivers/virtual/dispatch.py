"""One instruction packet → the status packets the servos on the wire send back, in wire order.

A packet to one ID goes to the servos with that ID (`VirtualServo.direct`); several servos sharing an ID
answer in the same slot and collide (`_collide`). A broadcast PING is answered by every servo in
ascending ID order; group reads (SYNC_/BULK_READ and their FAST_ forms) gather the listed servos' data;
group writes (SYNC_/BULK_WRITE) apply to the listed servos and are answered by none. The rules are the
"Wire" section of `felis.drivers.virtual.server`.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import FAST_SYNC_READ_MIN_FIRMWARE
from felis.drivers.virtual.memory import STATUS_RETURN_LEVEL
from felis.drivers.virtual.packets import GROUP_READS, GROUP_WRITES, Reply, fast_packet, status_packet

if TYPE_CHECKING:
    from felis.drivers.virtual.servo import VirtualServo


def dispatch(servos: Sequence[VirtualServo], pkt: P.Packet) -> list[Reply]:
    """The replies the listening ``servos`` send to one instruction packet, in wire order.

    Never raises on any packet. Every reply is a complete, valid status packet, except that a fast
    read whose list names an absent servo gives a packet short of its announced length
    (`felis.drivers.virtual.server`, Wire).
    """
    if pkt.crc_ok:  # the Bus Watchdog counts every instruction a servo hears: its own ID or broadcast
        for s in servos:
            if pkt.id == s.id or pkt.id == P.BROADCAST_ID:
                s.heard()
    if pkt.id != P.BROADCAST_ID:
        return _collide([(s.return_delay_s, r) for s in servos if s.id == pkt.id and (r := s.direct(pkt)) is not None])
    if not pkt.crc_ok:
        return []
    inst = pkt.inst
    if inst in GROUP_READS:
        return _group_read(servos, pkt)
    if inst in GROUP_WRITES:
        _group_write(servos, pkt)
        return []
    replies = [(s.id, s.return_delay_s, r) for s in servos if (r := s.direct(pkt)) is not None]
    replies.sort(key=lambda x: x[0])  # broadcast PING: ascending ID
    out: list[Reply] = []
    for _, same in itertools.groupby(replies, key=lambda x: x[0]):  # each ID answers in its own slot
        out += _collide([(d, r) for _, d, r in same])
    return out


def _collide(replies: list[Reply]) -> list[Reply]:
    """Servos sharing an ID answer in the same slot and drive the wire at once.

    The half-duplex line reads low while any transmitter drives it low (wired-AND); their start bits
    are modelled one byte apart, so the client receives ``a[k] & b[k−1]``: a garbled packet whose CRC
    fails, as on a real bus with two servos on one ID. One reply passes unchanged.
    """
    if len(replies) < 2:
        return replies
    data = bytearray(replies[0][1])
    for skew, (_, r) in enumerate(replies[1:], start=1):
        shifted = b"\xff" * skew + r
        data += b"\xff" * max(0, len(shifted) - len(data))
        for k, byte in enumerate(shifted):
            data[k] &= byte
    return [(replies[0][0], bytes(data))]


def _group_read(servos: Sequence[VirtualServo], pkt: P.Packet) -> list[Reply]:
    p, inst = pkt.params, pkt.inst
    by_id = {s.id: s for s in servos}
    if inst in (P.SYNC_READ, P.FAST_SYNC_READ):
        if len(p) < 5:
            return []
        addr, length = p[0] | p[1] << 8, p[2] | p[3] << 8
        requests = [(i, addr, length) for i in p[4:]]
    else:
        requests = [(p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8) for k in range(0, len(p) - 4, 5)]
        if not requests or len(p) % 5:
            return []
    fast = inst in (P.FAST_SYNC_READ, P.FAST_BULK_READ)
    announced = sum(4 + length for _, _, length in requests)
    if fast and announced + 3 > P.MAX_PACKET:
        return []
    out: list[Reply] = []
    segments: list[tuple[int, int, bytes]] = []
    delay = None
    for dxl_id, addr, length in requests:
        s = by_id.get(dxl_id)
        if s is None or s.mem[STATUS_RETURN_LEVEL] == 0 or (fast and s.firmware < FAST_SYNC_READ_MIN_FIRMWARE):
            continue
        err, data = s.read_block(addr, length)
        if fast:
            segments.append((dxl_id, err | s.alert, data if not err else bytes(length)))
            delay = s.return_delay_s if delay is None else delay
        else:
            out.append((s.return_delay_s, status_packet(dxl_id, err | s.alert, data)))
    if fast and segments:
        return [(delay or 0.0, fast_packet(announced, segments))]
    return out


def _group_write(servos: Sequence[VirtualServo], pkt: P.Packet) -> None:
    p = pkt.params
    by_id = {s.id: s for s in servos}
    writes: list[tuple[int, int, bytes]] = []
    if pkt.inst == P.SYNC_WRITE:
        if len(p) < 4:
            return
        addr, length = p[0] | p[1] << 8, p[2] | p[3] << 8
        step = 1 + length
        if length == 0 or (len(p) - 4) % step:
            return
        writes = [(p[k], addr, p[k + 1: k + step]) for k in range(4, len(p), step)]
    else:
        k = 0
        while k < len(p):
            if k + 5 > len(p):
                return
            length = p[k + 3] | p[k + 4] << 8
            if k + 5 + length > len(p):
                return
            writes.append((p[k], p[k + 1] | p[k + 2] << 8, p[k + 5: k + 5 + length]))
            k += 5 + length
    for dxl_id, addr, data in writes:
        s = by_id.get(dxl_id)
        if s is not None:
            s.write(addr, bytes(data))

