"""Group transfers on a Dynamixel bus: SYNC_WRITE, SYNC_READ, FAST_SYNC_READ and BULK_READ, with the
per-servo communication counters (`ServoStats`) every transaction updates.

`GroupTransfers` is inherited by :class:`felis.drivers.dynamixel.bus.DynamixelBus`. Replies are matched to
servos by ID (not by position, as ``GroupSyncRead.rxPacket`` does), so one missing servo marks only that
servo stale in the `BlockRead`; a failed fast sync read is retried as a plain sync read of the servos it
left out. `status_params` takes a status packet's parameters by its LEN field (the SDK's byte-unstuffing
leaves the packet list too long).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

import dynamixel_sdk as sdk

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import FAST_SYNC_READ_MIN_FIRMWARE
from felis.errors import ParameterError, PortError

P_ID = 4  # index of the ID byte in a packet


def status_params(pkt: list[int]) -> list[int]:
    """Status parameters (after the error byte), by the LEN field.

    Not ``pkt[9:-2]``: after removing byte stuffing the SDK leaves the list as long as the stuffed
    packet (its tail repeats), so only LEN, which it does update, tells where the parameters end.
    """
    n = (pkt[5] | pkt[6] << 8) - 4  # LEN counts INST, ERR, params, CRC
    return pkt[9: 9 + max(n, 0)]


@dataclass
class ServoStats:
    """Per-servo communication counters since the bus was opened."""

    ok: int = 0
    timeouts: int = 0
    corrupt: int = 0
    retries: int = 0
    status_errors: int = 0
    alerts: int = 0


@dataclass
class BlockRead:
    """Result of a block read: ``data[id]`` is the bytes read, or None when that servo is stale."""

    data: dict[int, bytes | None]
    errors: dict[int, int] = field(default_factory=dict)  # status error byte per servo that answered

    @property
    def stale(self) -> list[int]:
        return [i for i, d in self.data.items() if d is None]


class GroupTransfers:
    """Group reads and writes of `DynamixelBus` (module doc); the bus sets these attributes and provides
    the port calls (`felis.drivers.dynamixel.port.BusPort`)."""

    port_name: str
    retries: int
    use_fast_sync_read: bool
    firmware: dict[int, int]
    stats: dict[int, ServoStats]
    transactions: int
    failed_transactions: int
    _port: sdk.PortHandler | None
    _ph: sdk.PacketHandler
    _lock: threading.RLock

    def _stats(self, dxl_id: int) -> ServoStats:
        s = self.stats.get(dxl_id)
        if s is None:
            s = self.stats[dxl_id] = ServoStats()
        return s


    def sync_write(self, addr: int, length: int, data: dict[int, bytes]) -> None:
        """One SYNC_WRITE of ``length`` bytes at ``addr`` (no replies)."""
        if not data:
            return
        param: list[int] = []
        for i, d in data.items():
            if len(d) != length:
                raise ParameterError(f"sync write: {len(d)} bytes for servo {i}, expected {length}")
            param.append(i)
            param.extend(d)
        port = self._need_port()
        with self._lock:
            self.transactions += 1
            res = self._call(lambda: self._ph.syncWriteTxOnly(port, addr, length, param, len(param)))
        if res != sdk.COMM_SUCCESS:
            self.failed_transactions += 1
            raise PortError(f"sync write failed on {self.port_name}: {self._ph.getTxRxResult(res)}")

    def fast_sync_ok(self, ids: Iterable[int]) -> bool:
        """True when every servo's firmware (from ping) has Fast Sync Read."""
        return self.use_fast_sync_read and all(self.firmware.get(i, 0) >= FAST_SYNC_READ_MIN_FIRMWARE for i in ids)

    def sync_read(self, ids: list[int], addr: int, length: int, *, fast: bool | None = None,
                  retries: int | None = None) -> BlockRead:
        """Read ``length`` bytes at ``addr`` from every servo in one transaction.

        Servos that did not answer (or whose reply was corrupt or short) get ``None``; they are
        retried up to ``retries`` times with a plain sync read of just them.
        """
        if not ids:
            return BlockRead({})
        fast = self.fast_sync_ok(ids) if fast is None else fast
        out = BlockRead({i: None for i in ids})
        todo = list(ids)
        tries = 1 + (self.retries if retries is None else retries)
        for attempt in range(tries):
            if attempt:
                for i in todo:
                    self._stats(i).retries += 1
            got = self._fast_sync_read(todo, addr, length) if fast and attempt == 0 else \
                self._sync_read(todo, addr, length)
            for i, (err, d) in got.items():
                out.data[i] = d
                out.errors[i] = err
            todo = [i for i in todo if out.data[i] is None]
            if not todo:
                break
        return out

    def _sync_read(self, ids: list[int], addr: int, length: int) -> dict[int, tuple[int, bytes]]:
        port, ph = self._need_port(), self._ph
        n = len(ids)
        reply_len = 11 + length

        def run():
            res = ph.syncReadTx(port, addr, length, list(ids), n, False)
            if res != sdk.COMM_SUCCESS:
                return {}, res
            port.setPacketTimeoutMillis(self._timeout_ms(14 + n, n * reply_len, n))
            return self._collect({i: length for i in ids}), sdk.COMM_SUCCESS

        with self._lock:
            self.transactions += 1
            got, res = self._call(run)
        self._account(ids, got)
        if res != sdk.COMM_SUCCESS:
            self.failed_transactions += 1
        return got

    def _fast_sync_read(self, ids: list[int], addr: int, length: int) -> dict[int, tuple[int, bytes]]:
        port, ph = self._need_port(), self._ph
        n = len(ids)
        seg = length + 4

        def run():
            res = ph.syncReadTx(port, addr, length, list(ids), n, True)
            if res != sdk.COMM_SUCCESS:
                return {}, res
            port.setPacketTimeoutMillis(self._timeout_ms(14 + n, 8 + n * seg, n))
            pkt, res = ph.rxPacket(port, True)
            if res != sdk.COMM_SUCCESS:
                return {}, res
            got: dict[int, tuple[int, bytes]] = {}
            body = pkt[8:-2] + [0, 0]  # the last segment's CRC is the packet CRC (already checked)
            for k in range(min(n, len(body) // seg)):
                s = body[k * seg: (k + 1) * seg]
                if s[1] in ids:
                    got[s[1]] = (s[0], bytes(s[2: 2 + length]))
            return got, sdk.COMM_SUCCESS

        with self._lock:
            self.transactions += 1
            got, res = self._call(run)
        if res != sdk.COMM_SUCCESS:
            self.failed_transactions += 1
            # one packet carried every servo's reply: each was lost, to a time-out or a corrupt packet
            lost = "timeouts" if res == sdk.COMM_RX_TIMEOUT else "corrupt"
            for i in ids:
                st = self._stats(i)
                setattr(st, lost, getattr(st, lost) + 1)
            return {}  # the caller retries these servos with a plain sync read
        self._account(ids, got)
        return got

    def _collect(self, lengths: dict[int, int]) -> dict[int, tuple[int, bytes]]:
        """Receive one status per servo until all answered or the timeout passed; match by ID.

        Returns {id: (error byte, data)}; a corrupt packet leaves its servo pending."""
        port, ph = self._port, self._ph
        got: dict[int, tuple[int, bytes]] = {}
        pending = set(lengths)
        for _ in range(3 * len(lengths)):
            pkt, res = ph.rxPacket(port, False)
            if res == sdk.COMM_RX_TIMEOUT:
                break
            if res != sdk.COMM_SUCCESS:
                continue
            i = pkt[P_ID]
            d = status_params(pkt)
            if i in pending and len(d) == lengths[i]:  # a late reply to an earlier packet (a PING's 3 bytes) is not it
                got[i] = (pkt[8], bytes(d))
                pending.discard(i)
                if not pending:
                    break
        return got

    def _account(self, ids: list[int], got: dict[int, tuple[int, bytes]]) -> None:
        for i in ids:
            st = self._stats(i)
            r = got.get(i)
            if r is None:
                st.timeouts += 1
                continue
            st.ok += 1
            if r[0] & P.ALERT:
                st.alerts += 1
            if r[0] & 0x7F:
                st.status_errors += 1

    def bulk_read(self, reads: dict[int, tuple[int, int]]) -> BlockRead:
        """BULK_READ: a different (addr, length) per servo; stale servos get None."""
        if not reads:
            return BlockRead({})
        port, ph = self._need_port(), self._ph
        param: list[int] = []
        for i, (addr, length) in reads.items():
            param += [i, addr & 0xFF, addr >> 8, length & 0xFF, length >> 8]
        rx = sum(11 + ln for _, ln in reads.values())

        def run():
            res = ph.bulkReadTx(port, param, len(param), False)
            if res != sdk.COMM_SUCCESS:
                return {}, res
            port.setPacketTimeoutMillis(self._timeout_ms(10 + len(param), rx, len(reads)))
            return self._collect({i: ln for i, (_, ln) in reads.items()}), sdk.COMM_SUCCESS

        with self._lock:
            self.transactions += 1
            got, _ = self._call(run)
        self._account(list(reads), got)
        out = BlockRead({i: None for i in reads})
        for i, (err, d) in got.items():
            out.data[i], out.errors[i] = d, err
        return out
