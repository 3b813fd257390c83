"""`DynamixelBus`: Protocol 2.0 on the unmodified ``dynamixel-sdk``, with its sharp edges filed off.

One object per serial port. Items are addressed by name (``bus.read(3, "present_position")``) in SI
units through the control tables of :mod:`felis.drivers.dynamixel.controltable`, or raw with ``raw=True``.

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

import contextlib
import errno
import fcntl
import glob
import math
import os
import stat
import termios
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import dynamixel_sdk as sdk
import serial

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.controltable import (
    BAUD_RATES,
    EEPROM_END,
    FAST_SYNC_READ_MIN_FIRMWARE,
    ControlTable,
    Item,
    address,
    control_table,
    decode_hardware_error,
    model_name,
)
from felis.errors import (
    CommError,
    CorruptReplyError,
    NoReplyError,
    ParameterError,
    PortError,
    ServoStatusError,
)

SDK_BAUDS = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)  # both SDK and servo support
_TORQUE_ENABLE = address("torque_enable")
_HW_ERROR = address("hardware_error_status")
_LED = address("led")






@dataclass
class ServoStats:
    """Per-servo communication counters since the bus was opened."""

    ok: int = 0
    timeouts: int = 0
    corrupt: int = 0
    retries: int = 0
    status_errors: int = 0
    alerts: int = 0


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


@dataclass
class BlockRead:
    """Result of a block read: ``data[id]`` is the bytes read, or None when that servo is stale."""

    data: dict[int, bytes | None]
    errors: dict[int, int] = field(default_factory=dict)  # status error byte per servo that answered

    @property
    def stale(self) -> list[int]:
        return [i for i, d in self.data.items() if d is None]


def check_port_path(port: str) -> None:
    """Raise PortError with the fix when ``port`` does not exist, is not a device, or lacks permission."""
    try:
        st = os.stat(port)
    except FileNotFoundError:
        raise PortError(f"serial port {port} does not exist (is the adapter plugged in? `felis find-port` "
                        "lists candidates)") from None
    except OSError as e:
        raise PortError(f"serial port {port}: {e.strerror}") from None
    if not stat.S_ISCHR(st.st_mode):
        raise PortError(f"{port} is not a serial device")
    if not os.access(port, os.R_OK | os.W_OK):
        raise PortError(f"no permission to open {port}: add yourself to its group "
                        f"(`sudo usermod -aG dialout $USER`, then log in again) or run with access to it")


def latency_timer_ms(port: str) -> int | None:
    """The FTDI latency timer of a USB serial port (sysfs), or None when it has none (pty, ACM)."""
    name = os.path.basename(os.path.realpath(port))
    path = f"/sys/bus/usb-serial/devices/{name}/latency_timer"
    try:
        with open(path) as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def latency_fix(port: str, ms: int) -> str | None:
    """The fix for a slow FTDI latency timer, or None when it is already 1 ms or less."""
    if ms <= 1:
        return None
    name = os.path.basename(os.path.realpath(port))
    return (f"FTDI latency timer on {port} is {ms} ms (caps a request/reply loop near {1000 // (ms + 1)} Hz); fix: "
            f"echo 1 | sudo tee /sys/bus/usb-serial/devices/{name}/latency_timer  (permanent: udev rule "
            'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1")')


def _is_pty(port: str) -> bool:
    real = os.path.realpath(port)
    return real.startswith("/dev/pts/") or real.startswith("/dev/pty")


def port_holders(port: str) -> list[str]:
    """Other processes that hold ``port``, as ``"PID 123 (felis monitor …)"`` (best effort, Linux /proc).

    The holders of its lock (``/proc/locks``) when there are any; else every process with it open."""
    real = os.path.realpath(port)
    me = os.getpid()
    pids = [p for p in _lock_holders(real) if p != me] or [p for p in _openers(real) if p != me]
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                cmd = f.read(4096).replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            cmd = "?"
        out.append(f"PID {pid} ({cmd[:100]})")
    return out


def _lock_holders(real: str) -> list[int]:
    try:
        st = os.stat(real)
        with open("/proc/locks") as f:
            lines = f.read(1 << 20).splitlines()
    except OSError:
        return []
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids = []
    for line in lines:
        parts = line.split()
        if "->" in parts:  # a waiter, not a holder
            continue
        if len(parts) >= 6 and parts[1] == "FLOCK" and parts[5].lower() == key.lower() and parts[4].isdigit():
            pids.append(int(parts[4]))
    return pids


def _openers(real: str) -> list[int]:
    pids = []
    for pid_dir in glob.glob("/proc/[0-9]*"):
        try:
            fds = os.listdir(f"{pid_dir}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"{pid_dir}/fd/{fd}") == real:
                    pids.append(int(os.path.basename(pid_dir)))
                    break
            except OSError:
                continue
    return pids


def in_use_message(port: str) -> str:
    holders = port_holders(port)
    who = f" by {', '.join(holders)}" if holders else " by another program"
    return (f"{port} is in use{who}: two programs on one bus corrupt each other's replies; stop the other one "
            "first (another felis, Dynamixel Wizard, a serial console)")


def lock_port(port: str) -> int:
    """Take the exclusive advisory lock of a serial device; returns the descriptor that holds it.

    PortError naming the holder when another program has it locked (or opened it with TIOCEXCL)."""
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        if e.errno == errno.EBUSY:
            raise PortError(in_use_message(port)) from None
        raise PortError(f"cannot open {port}: {e.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise PortError(in_use_message(port)) from None
        raise PortError(f"cannot lock {port}: {e.strerror}") from None
    return fd


class DynamixelBus:
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

    # ------------------------------------------------------------------ port
    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> DynamixelBus:
        """Open the port exclusively; PortError (one line, with the fix) when it cannot be.

        Exclusive: before the SDK touches the device (pyserial's open reconfigures the line and flushes
        its input queue, which would steal another program's replies), an ``flock(LOCK_EX)`` is taken on
        it, as pyserial's ``exclusive=True`` does; a second felis program, or any client that locks the
        same way, is refused with one line naming the holder. ``TIOCEXCL`` is then set on the SDK's
        descriptor, so other non-root programs cannot open the device at all while felis has it.
        """
        if self.is_open:
            return self
        check_port_path(self.port_name)
        self._lock_fd = lock_port(self.port_name)
        port = sdk.PortHandler(self.port_name)
        port.baudrate = self.baud
        try:
            port.openPort()
        except (serial.SerialException, OSError) as e:
            self._unlock()
            msg = str(e)
            if "busy" in msg.lower() or getattr(e, "errno", None) == errno.EBUSY:
                raise PortError(in_use_message(self.port_name)) from None
            raise PortError(f"cannot open {self.port_name}: {msg}") from None
        with contextlib.suppress(OSError, AttributeError, termios.error):
            fcntl.ioctl(port.ser.fileno(), termios.TIOCEXCL)
        self._port = port
        pty = _is_pty(self.port_name)
        lat = latency_timer_ms(self.port_name)
        self._latency_ms = 0.0 if pty else float(lat if lat is not None else sdk.port_handler.LATENCY_TIMER)
        if self._margin_ms is None:
            self._margin_ms = _env_margin_ms() if os.environ.get("FELIS_TIMEOUT_MARGIN_MS") else 10.0 if pty else 4.0
        return self

    def close(self) -> None:
        with self._lock:
            if self._port is not None:
                try:
                    if self._port.ser is not None:
                        with contextlib.suppress(OSError, AttributeError, termios.error):
                            fcntl.ioctl(self._port.ser.fileno(), termios.TIOCNXCL)
                        self._port.closePort()
                except (serial.SerialException, OSError):
                    pass
                self._port = None
            self._unlock()

    def _unlock(self) -> None:
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)  # closing the descriptor releases the flock
            self._lock_fd = None

    def __enter__(self) -> DynamixelBus:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def set_baud(self, baud: int) -> None:
        """Switch the host side to another baud rate (the servos' own rate is the ``baud_rate`` item)."""
        if baud not in SDK_BAUDS:
            raise ParameterError(f"baud rate {baud} not supported; use one of {', '.join(map(str, SDK_BAUDS))}")
        self.baud = baud
        if self._port is not None:
            with self._lock:
                self._call(lambda: self._port.setBaudRate(baud))

    def listen(self, seconds: float, limit: int = 4096) -> bytes:
        """Bytes that arrive on the port within ``seconds`` without being asked for (a Dynamixel bus sends
        none): the diagnosis of a port that is something else, e.g. the IMU's."""
        port = self._need_port()
        out = bytearray()
        deadline = time.monotonic() + seconds
        with self._lock:
            while time.monotonic() < deadline and len(out) < limit:
                chunk = self._call(lambda: port.readPort(limit - len(out)))
                if chunk:
                    out.extend(chunk)
                else:
                    time.sleep(0.005)
        return bytes(out)

    def check_quiet(self, seconds: float = 0.05) -> None:
        """CommError when the port sends data unprompted (a Dynamixel bus is silent until asked): the operator
        gave the IMU's port, or another device's, as the bus; the message names a BNO08x when it is one."""
        data = self.listen(seconds)
        if len(data) < 8:
            return
        from felis.drivers.imu import looks_like_rvc

        what = "BNO08x UART-RVC IMU frames" if looks_like_rvc(data) else f"{len(data)} bytes that no one asked for"
        raise CommError(f"{self.port_name} sends data unprompted ({what}); a Dynamixel bus is silent until asked: "
                        "are --port and --imu-port swapped?")

    def latency_warning(self) -> str | None:
        """The FTDI latency-timer fix for this port, or None when it is fine (or not an FTDI)."""
        ms = latency_timer_ms(self.port_name)
        return None if ms is None else latency_fix(self.port_name, ms)

    # ------------------------------------------------------------------ low level
    def _need_port(self) -> sdk.PortHandler:
        if self._port is None:
            raise PortError(f"{self.port_name} is not open")
        return self._port

    def _call(self, fn: Callable):
        """Run an SDK call; turn a vanished port into PortError and clear the busy flag afterwards."""
        port = self._need_port()
        if port.is_using:  # left set by an earlier failed or interrupted transaction
            port.is_using = False
            self.busy_recoveries += 1
        try:
            return fn()
        except (serial.SerialException, OSError, termios.error) as e:
            # pyserial raises SerialException (or OSError) when the device vanishes
            self.close()
            raise PortError(f"{self.port_name} stopped working ({e}); check the cable and power, then reconnect") \
                from None
        finally:
            if self._port is not None:
                self._port.is_using = False

    def _timeout_ms(self, tx_bytes: int, rx_bytes: int, n_replies: int) -> float:
        wire = (tx_bytes + rx_bytes) * 10_000.0 / self.baud
        delays = n_replies * (self.return_delay_us / 1000.0 + 0.05)
        return wire + delays + 2.0 * (self._latency_ms or 0.0) + (self._margin_ms or 0.0)

    def _stats(self, dxl_id: int) -> ServoStats:
        s = self.stats.get(dxl_id)
        if s is None:
            s = self.stats[dxl_id] = ServoStats()
        return s

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
            for _ in range(8):  # skip stray replies from other IDs (bounded)
                pkt, res = ph.rxPacket(port, False)
                if res != sdk.COMM_SUCCESS or pkt[P_ID] == expect_id:
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
                data = _params(pkt)
                if len(data) < rx_data and not err & 0x7F:
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
                raise ParameterError(f"servo {dxl_id} is a {f.model}, which felis has no control table for")
        return t

    def register(self, dxl_id: int, model: str, firmware: int | None = None) -> None:
        """Declare a servo's model without pinging it (from a robot description)."""
        self.models[dxl_id] = control_table(model)
        if firmware is not None:
            self.firmware[dxl_id] = firmware

    def item(self, dxl_id: int, name: str) -> Item:
        return self.table(dxl_id).item(name)

    def read_raw(self, dxl_id: int, addr: int, length: int) -> bytes:
        """READ ``length`` bytes at ``addr``; raises on no reply, corrupt reply or status error."""
        _check_id(dxl_id)
        err, data = self._status_of(dxl_id, f"read {length} B at {addr}", P.READ,
                                    [addr & 0xFF, addr >> 8, length & 0xFF, length >> 8], length)
        if err & 0x7F:
            raise ServoStatusError(dxl_id, err, f"read of {length} bytes at address {addr}",
                                   P.describe_status_error(err))
        return bytes(data[:length])

    def read(self, dxl_id: int, name: str, raw: bool = False):
        """Read an item by name: SI units (rad, rad/s, A, V, s, °C; enums as values), or raw."""
        it = self.item(dxl_id, name)
        value = it.decode(self.read_raw(dxl_id, it.addr, it.size))
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

    def check_return_delay(self, ids: Iterable[int]) -> list[tuple[int, float, str]]:
        """Servos whose Return Delay Time is not 0: (id, seconds, fix)."""
        out = []
        for i in ids:
            rdt = self.read(i, "return_delay_time", raw=True)
            if rdt:
                out.append((i, rdt * 2e-6, f"felis torque off --id {i} && felis write {i} return_delay_time 0 --raw"))
        return out

    # ------------------------------------------------------------------ group transfers
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
            d = _params(pkt)
            if i in pending and len(d) >= lengths[i]:
                got[i] = (pkt[8], bytes(d[: lengths[i]]))
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


P_ID = 4  # index of the ID byte in a packet


def _params(pkt: list[int]) -> list[int]:
    """Status parameters (after the error byte), by the LEN field.

    Not ``pkt[9:-2]``: after removing byte stuffing the SDK leaves the list as long as the stuffed
    packet (its tail repeats), so only LEN, which it does update, tells where the parameters end.
    """
    n = (pkt[5] | pkt[6] << 8) - 4  # LEN counts INST, ERR, params, CRC
    return pkt[9: 9 + max(n, 0)]


def _env_margin_ms() -> float:
    text = os.environ["FELIS_TIMEOUT_MARGIN_MS"]
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and 0 <= v <= 1000):
        raise ParameterError(f"FELIS_TIMEOUT_MARGIN_MS must be 0…1000 (ms), got {text!r}")
    return v


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


def candidate_ports() -> list[str]:
    """USB serial devices that might hold a Dynamixel adapter."""
    return sorted(set(glob.glob("/dev/ttyUSB*") + glob.glob("/dev/ttyACM*") + glob.glob("/dev/serial/by-id/*")))


__all__ = ["DynamixelBus", "PortError", "NoReplyError", "CorruptReplyError", "ServoStatusError", "ServoStats",
           "Found", "BlockRead", "SDK_BAUDS", "BAUD_RATES", "baud_code", "check_port_path", "latency_timer_ms",
           "latency_fix", "candidate_ports", "lock_port", "port_holders"]

