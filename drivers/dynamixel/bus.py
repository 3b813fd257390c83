"""`DynamixelBus`: Protocol 2.0 on the unmodified ``dynamixel-sdk``, with its sharp edges filed off.

One object per serial port. Items are addressed by name (``bus.read(3, "present_position")``) in SI
units through the control tables of :mod:`felis.drivers.dynamixel.controltable`, or raw with ``raw=True``.
`DynamixelBus` inherits the serial port (exclusive open, reply timeouts, the SDK's busy flag) from
:mod:`felis.drivers.dynamixel.port` and the group transfers (sync, fast sync and bulk reads, sync writes,
per-servo counters) from :mod:`felis.drivers.dynamixel.group`; this module holds the unicast transactions
with retries, discovery (ping, scan), items by name and the guards.

What this layer adds to the SDK (``shared/reference/dynamixel.md``):

* **Transactions from SDK primitives.** Requests go out with the SDK's own ``txPacket`` /
  ``syncReadTx`` / ``syncWriteTxOnly``; replies come back through its ``rxPacket``. We set the reply
  timeout ourselves (``port.setPacketTimeoutMillis``) from the bytes on the wire, the Return Delay
  Time and the adapter's latency timer, instead of the SDK's fixed 2×16 ms + 2 ms.
* **Sync read by ID, not by position.** ``GroupSyncRead.rxPacket`` stops at the first missing
  servo and then returns 0 for everyone. Here every reply is matched to its ID, so one missing
  servo marks only that servo stale; the others' data and their status error bytes are kept.
* **A failed read never yields numbers.** Single reads raise :class:`NoReplyError` /
  :class:`CorruptReplyError`; block reads return ``None`` for a servo that did not answer.
* **Retries with per-servo counters** (:class:`ServoStats`), and recovery from the SDK's stuck
  ``port.is_using`` flag (counted in ``bus.busy_recoveries``).
* **Fast Sync Read** where every servo's firmware has it (≥ 45), falling back to a plain sync read
  for the servos a failed fast read left out.
* **Parameters by LEN.** The SDK's ``removeStuffing`` leaves a reply list as long as the stuffed
  packet (its last bytes repeat), so a reply whose data contained ``FF FF FD`` would read a CRC
  byte as data; parameters are taken by the LEN field (found by the fuzz test).
* **Guards.** Unknown items, out-of-range values and read-only items are refused before anything
  is sent; EEPROM items (address < 64) are written only after reading Torque Enable = 0; a port
  that does not exist, lacks permission, or vanishes mid-run is one :class:`PortError` line.

Status error bytes: bit 7 (Alert) means a hardware error; :meth:`hardware_error` decodes
Hardware Error Status (addr 70) to names. Status errors on writes raise :class:`ServoStatusError`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import dynamixel_sdk as sdk

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import (
    BAUD_RATES,
    EEPROM_END,
    ControlTable,
    Item,
    address,
    control_table,
    decode_hardware_error,
    model_name,
    unsupported,
)
from felis.drivers.dynamixel.group import P_ID, BlockRead, GroupTransfers, ServoStats, status_params
from felis.drivers.dynamixel.port import (
    SDK_BAUDS,
    BusPort,
    candidate_ports,
    check_port_path,
    latency_fix,
    latency_timer_ms,
    lock_port,
    port_holders,
)
from felis.errors import (
    CorruptReplyError,
    NoReplyError,
    ParameterError,
    PortError,
    ServoStatusError,
)

_TORQUE_ENABLE = address("torque_enable")
_HW_ERROR = address("hardware_error_status")
_LED = address("led")
_RETURN_DELAY = address("return_delay_time")


@dataclass(frozen=True)
class Found:
    """A servo found by :meth:`DynamixelBus.scan`."""

    id: int
    baud: int
    model_number: int
    firmware: int

    @property
    def model(self) -> str:
        return model_name(self.model_number)


class DynamixelBus(GroupTransfers, BusPort):
    """A Dynamixel Protocol 2.0 bus on one serial port.

    Args:
        port: device path (``/dev/ttyUSB0``, a pseudo-terminal of the virtual bus, …).
        baud: bits per second; one of :data:`SDK_BAUDS`.
        retries: extra attempts for single reads/writes and for servos a block read missed.
        timeout_margin_ms: slack added to every computed reply timeout (default: ``$FELIS_TIMEOUT_MARGIN_MS``,
            else 10 ms on a pseudo-terminal and 4 ms on an adapter; raise it for slow hubs or loaded hosts).
        return_delay_us: the Return Delay Time assumed when computing timeouts (servos set up by
            ``felis`` use 0; factory servos 500 µs: :meth:`check_return_delay` finds them).
        fast_sync_read: use FAST_SYNC_READ when every servo's firmware has it (after :meth:`ping`).
    """

    def __init__(self, port: str, baud: int = 1_000_000, *, retries: int = 1, timeout_margin_ms: float | None = None,
                 return_delay_us: float = 0.0, fast_sync_read: bool = True):
        if baud not in SDK_BAUDS:
            raise ParameterError(f"baud rate {baud} is not one Dynamixel X servos and the SDK share; "
                                 f"use one of {', '.join(map(str, SDK_BAUDS))}")
        if retries < 0:
            raise ParameterError(f"retries must be >= 0, got {retries}")
        self.port_name = port
        self.baud = baud
        self.retries = retries
        self.return_delay_us = return_delay_us
        self.use_fast_sync_read = fast_sync_read
        self._latency_ms: float | None = None
        self._margin_ms = timeout_margin_ms
        self._port: sdk.PortHandler | None = None
        self._lock_fd: int | None = None  # holds the port's exclusive flock while open
        self._ph = sdk.PacketHandler(2.0)
        self._lock = threading.RLock()
        self.models: dict[int, ControlTable] = {}
        self.firmware: dict[int, int] = {}
        self.stats: dict[int, ServoStats] = {}
        self.busy_recoveries = 0
        self.transactions = 0
        self.failed_transactions = 0

    # ------------------------------------------------------------------ transactions
    def _transact(self, txpacket: list[int], expect_id: int | None, rx_len: int) -> tuple[list[int] | None, int]:
        """Send one instruction; wait for the status of ``expect_id`` (None: no reply expected).

        Returns (status packet, SDK result code)."""
        port = self._need_port()
        ph = self._ph

        def run():
            res = ph.txPacket(port, txpacket)
            if res != sdk.COMM_SUCCESS or expect_id is None:
                return None, res
            tx_len = (txpacket[5] | txpacket[6] << 8) + 7
            port.setPacketTimeoutMillis(self._timeout_ms(tx_len, rx_len, 1))
            for _ in range(8):  # skip stray replies: other IDs, late ones of another length (bounded)
                pkt, res = ph.rxPacket(port, False)
                if res != sdk.COMM_SUCCESS or (pkt[P_ID] == expect_id and (len(status_params(pkt)) == rx_len - 11
                                                                            or pkt[8] & 0x7F)):
                    return pkt, res
            return None, sdk.COMM_RX_CORRUPT

        with self._lock:
            self.transactions += 1
            pkt, res = self._call(run)
        if res != sdk.COMM_SUCCESS:
            self.failed_transactions += 1
        return pkt, res

    def _status_of(self, dxl_id: int, what: str, inst: int, params: list[int], rx_data: int,
                   retries: int | None = None) -> tuple[int, list[int]]:
        """Unicast instruction with retries; returns (error byte, params after the error byte)."""
        txpacket = [0] * 8 + list(params) + [0, 0]
        n = len(params) + 3
        txpacket[P_ID], txpacket[5], txpacket[6], txpacket[7] = dxl_id, n & 0xFF, n >> 8, inst
        st = self._stats(dxl_id)
        last = sdk.COMM_RX_TIMEOUT
        for attempt in range(1 + (self.retries if retries is None else retries)):
            if attempt:
                st.retries += 1
            pkt, res = self._transact(list(txpacket), dxl_id, 11 + rx_data)
            if res == sdk.COMM_SUCCESS:
                err = pkt[8]
                data = status_params(pkt)
                if len(data) != rx_data and not err & 0x7F:  # short, or a late reply to an earlier packet
                    st.corrupt += 1
                    last = sdk.COMM_RX_CORRUPT
                    continue
                st.ok += 1
                if err & P.ALERT:
                    st.alerts += 1
                if err & 0x7F:
                    st.status_errors += 1
                return err, data
            last = res
            if res == sdk.COMM_RX_TIMEOUT:
                st.timeouts += 1
            else:
                st.corrupt += 1
        if last == sdk.COMM_RX_TIMEOUT:
            raise NoReplyError(f"servo {dxl_id} did not answer {what} at {self.baud} bps on {self.port_name} "
                               f"(missing, powered off, or at another baud rate: `felis scan` finds it)")
        raise CorruptReplyError(f"servo {dxl_id}: corrupt reply to {what} ({self._ph.getTxRxResult(last)}); "
                                "check wiring, termination and baud rate")


    # ------------------------------------------------------------------ discovery
    def ping(self, dxl_id: int, retries: int | None = None) -> Found:
        """Ping one servo; records its model and firmware. NoReplyError when it does not answer."""
        _check_id(dxl_id)
        err, data = self._status_of(dxl_id, "ping", P.PING, [], 3, retries)
        if len(data) < 3:
            raise CorruptReplyError(f"servo {dxl_id}: ping reply too short")
        number, fw = data[0] | data[1] << 8, data[2]
        self._remember(dxl_id, number, fw)
        return Found(dxl_id, self.baud, number, fw)

    def _remember(self, dxl_id: int, number: int, fw: int) -> None:
        try:
            self.models[dxl_id] = control_table(number)
        except ParameterError:
            self.models.pop(dxl_id, None)
        self.firmware[dxl_id] = fw

    def try_ping(self, dxl_id: int, retries: int = 0) -> Found | None:
        try:
            return self.ping(dxl_id, retries)
        except (NoReplyError, CorruptReplyError):
            return None

    def scan(self, ids: Iterable[int] | None = None, bauds: Iterable[int] | None = None,
             progress: Callable[[int, int, str], None] | None = None) -> list[Found]:
        """Find servos across baud rates.

        Without ``ids`` each baud rate gets one broadcast ping (every servo answers) and each answer
        is confirmed by a unicast ping; with ``ids`` only those IDs are pinged. ``progress(done,
        total, label)`` is called as it goes. The port is left at its original baud rate.
        """
        bauds = list(bauds) if bauds is not None else list(SDK_BAUDS)
        for b in bauds:
            if b not in SDK_BAUDS:
                raise ParameterError(f"baud rate {b} not supported; use one of {', '.join(map(str, SDK_BAUDS))}")
        id_list = None if ids is None else list(ids)
        for i in id_list or []:
            _check_id(i)
        original = self.baud
        found: list[Found] = []
        steps = len(bauds) * (len(id_list) if id_list else 1)
        done = 0
        try:
            for b in bauds:
                self.set_baud(b)
                if id_list is None:
                    if progress:
                        progress(done, steps, f"{b} bps: broadcast ping")
                    data, _ = self._call(lambda: self._ph.broadcastPing(self._port))
                    candidates = sorted(data)
                    done += 1
                else:
                    candidates = id_list
                for i in candidates:
                    f = self.try_ping(i, retries=1)
                    if f is not None:
                        found.append(f)
                    if id_list is not None:
                        done += 1
                        if progress:
                            progress(done, steps, f"{b} bps: ID {i}")
        finally:
            if self._port is not None:
                self.set_baud(original)
        if progress:
            progress(steps, steps, "done")
        return found


    # ------------------------------------------------------------------ items
    def table(self, dxl_id: int) -> ControlTable:
        """The control table of a servo (pinged once to learn its model)."""
        t = self.models.get(dxl_id)
        if t is None:
            f = self.ping(dxl_id)
            t = self.models.get(dxl_id)
            if t is None:
                raise ParameterError(f"servo {dxl_id}: {unsupported(f.model_number)}")
        return t

    def register(self, dxl_id: int, model: str, firmware: int | None = None) -> None:
        """Declare a servo's model without pinging it (from a robot description)."""
        self.models[dxl_id] = control_table(model)
        if firmware is not None:
            self.firmware[dxl_id] = firmware

    def item(self, dxl_id: int, name: str) -> Item:
        return self.table(dxl_id).item(name)

    def read_raw(self, dxl_id: int, addr: int, length: int, retries: int | None = None) -> bytes:
        """READ ``length`` bytes at ``addr``; raises on no reply, corrupt reply or status error. ``retries``:
        extra attempts (default the bus's)."""
        _check_id(dxl_id)
        err, data = self._status_of(dxl_id, f"read {length} B at {addr}", P.READ,
                                    [addr & 0xFF, addr >> 8, length & 0xFF, length >> 8], length, retries)
        if err & 0x7F:
            raise ServoStatusError(dxl_id, err, f"read of {length} bytes at address {addr}",
                                   P.describe_status_error(err))
        return bytes(data[:length])

    def read(self, dxl_id: int, name: str, raw: bool = False, *, retries: int | None = None):
        """Read an item by name: SI units (rad, rad/s, A, V, s, °C; enums as values), or raw. ``retries``: extra
        attempts (default the bus's)."""
        it = self.item(dxl_id, name)
        value = it.decode(self.read_raw(dxl_id, it.addr, it.size, retries))
        return value if raw else it.to_si(value)

    def write_raw(self, dxl_id: int, addr: int, data: bytes, what: str = "write") -> None:
        """WRITE bytes at ``addr``; raises on no reply or a status error. Broadcast gets no reply."""
        params = [addr & 0xFF, addr >> 8, *data]
        if dxl_id == P.BROADCAST_ID:
            txpacket = [0] * 8 + params + [0, 0]
            n = len(params) + 3
            txpacket[P_ID], txpacket[5], txpacket[6], txpacket[7] = dxl_id, n & 0xFF, n >> 8, P.WRITE
            self._transact(txpacket, None, 0)
            return
        _check_id(dxl_id)
        err, _ = self._status_of(dxl_id, what, P.WRITE, params, 0)
        if err & 0x7F:
            raise ServoStatusError(dxl_id, err, what, P.describe_status_error(err))

    def write(self, dxl_id: int, name: str, value, raw: bool = False, *, dry_run: bool = False) -> int:
        """Write an item by name (SI or raw). Checks writability and range first; EEPROM items only
        after reading Torque Enable = 0. Returns the raw value (written, or that would be with
        ``dry_run``)."""
        it = self.item(dxl_id, name)
        if not it.writable:
            raise ParameterError(f"{it.name} is read-only")
        if raw:
            value = int(value)
            it.check(value)
        else:
            value = it.from_si(value)
        if it.addr < EEPROM_END:
            self.require_torque_off(dxl_id, it.name)
        if it.name == "goal_position" and self.read(dxl_id, "operating_mode", raw=True) == 3:
            lo = self.read(dxl_id, "min_position_limit", raw=True)
            hi = self.read(dxl_id, "max_position_limit", raw=True)
            if not lo <= value <= hi:
                raise ParameterError(f"goal_position {value} is outside servo {dxl_id}'s position limits {lo}…{hi} "
                                     f"ticks ({it.to_si(lo):+.3f}…{it.to_si(hi):+.3f} rad) in position mode")
        if not dry_run:
            self.write_raw(dxl_id, it.addr, it.encode(value), f"write {it.name} = {value}")
        return value

    def require_torque_off(self, dxl_id: int, what: str) -> None:
        if self.read(dxl_id, "torque_enable", raw=True):
            raise ParameterError(f"servo {dxl_id}: {what} is in EEPROM and can only be written with torque off "
                                 f"(`felis torque off --id {dxl_id}`)")


    # ------------------------------------------------------------------ operations
    def torque(self, ids: Iterable[int], on: bool) -> None:
        """Torque Enable for several servos in one sync write."""
        self.sync_write(_TORQUE_ENABLE, 1, {i: bytes((1 if on else 0,)) for i in ids})

    def led(self, dxl_id: int, on: bool) -> None:
        self.write_raw(dxl_id, _LED, bytes((1 if on else 0,)), "write led")

    def reboot(self, dxl_id: int) -> None:
        """REBOOT: clears a hardware-error shutdown; torque comes back off."""
        _check_id(dxl_id)
        err, _ = self._status_of(dxl_id, "reboot", P.REBOOT, [], 0)
        if err & 0x7F:
            raise ServoStatusError(dxl_id, err, "reboot", P.describe_status_error(err))

    def hardware_error(self, dxl_id: int) -> tuple[int, list[str]]:
        """Hardware Error Status: (bits, names)."""
        bits = self.read_raw(dxl_id, _HW_ERROR, 1)[0]
        return bits, decode_hardware_error(bits)

    def check_return_delay(self, ids: Iterable[int], retries: int | None = None) -> list[tuple[int, float, str]]:
        """Servos whose Return Delay Time is not 0: (id, seconds, fix). One plain sync read (``retries``: extra
        tries for servos it missed, default the bus's); a servo that never answered it is left out (a speed
        warning, not a reason to fail)."""
        ids = list(ids)
        if not ids:
            return []
        res = self.sync_read(ids, _RETURN_DELAY, 1, fast=False, retries=retries)
        return [(i, d[0] * 2e-6, f"felis torque off --id {i} && felis write {i} return_delay_time 0 --raw")
                for i in ids if (d := res.data[i]) is not None and d[0]]


def _check_id(dxl_id: int) -> None:
    if not isinstance(dxl_id, int) or not 0 <= dxl_id <= P.MAX_ID:
        raise ParameterError(f"servo ID must be 0…{P.MAX_ID}, got {dxl_id!r}")


def baud_code(table: ControlTable, bps: int) -> int:
    """The Baud Rate item code for ``bps`` on this model; ParameterError when the model lacks it."""
    for code, b in table.baud_rates.items():
        if b == bps:
            return code
    rates = ', '.join(map(str, table.baud_rates.values()))
    raise ParameterError(f"{table.model} has no {bps} bps; it supports {rates}")


__all__ = ["DynamixelBus", "PortError", "NoReplyError", "CorruptReplyError", "ServoStatusError", "ServoStats",
           "Found", "BlockRead", "SDK_BAUDS", "BAUD_RATES", "baud_code", "check_port_path", "latency_timer_ms",
           "latency_fix", "candidate_ports", "lock_port", "port_holders"]
