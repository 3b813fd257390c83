"""The serial port of a Dynamixel bus: opened exclusively, watched, and its SDK busy flag kept clear.

`BusPort` is the port half of :class:`felis.drivers.dynamixel.bus.DynamixelBus` (which inherits it): open and
close, baud rate, listening for unprompted bytes (`check_quiet`), the FTDI latency timer, the reply timeout
computed from the bytes on the wire, and every SDK call wrapped by `_call`, which clears the SDK's stuck
``port.is_using`` flag (counted in ``busy_recoveries``) and turns a vanished device into one `PortError`.

Exclusive open: an ``flock(LOCK_EX)`` on the device before the SDK touches it, then ``TIOCEXCL`` on the SDK's
descriptor; a refused open names the holder, found through ``/proc/locks`` (else every process that has the
device open). The module functions check a path before opening it (`check_port_path`), list candidate
adapters (`candidate_ports`) and give the FTDI latency-timer fix (`latency_fix`).

Waiting, not spinning: the SDK opens the port with pyserial's ``timeout=0`` and calls ``readPort`` in a loop until
the reply is whole or its packet timeout passes, so every transaction held a core at 100 % for its whole wait
(a broadcast ping's ~0.8 s per baud rate; on a 2-core host, the core an emulated bus or the control loop needed).
`WaitingPortHandler`, the SDK's port handler with that one method changed, lets the SDK's loop spin for the first
`SPIN_MS` after the request or after the last bytes came (a reply that close behind, or the next servo's reply of
a sync read, is read at once: sleeping and waking cost ~25 µs a wait against the emulated bus's ~150 µs
transaction) and then, while nothing has arrived, waits on the descriptor
(``select``) until the next byte or the packet's deadline: a reply is read as soon as it comes, and the SDK's own
timeout check runs as before (at most `WAIT_CAP_S` late). A USB adapter's replies come after its latency timer
(1 ms at best, 16 ms by default), a missing servo's never: that wait no longer costs a core. The SDK itself is
unmodified.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import glob
import math
import os
import select
import stat
import termios
import threading
import time
from collections.abc import Callable
from typing import Self

import dynamixel_sdk as sdk
import serial

from felis.drivers.dynamixel.protocol import STATUS, PacketReader
from felis.drivers.imu.frames import looks_like_rvc
from felis.errors import CommError, ParameterError, PortError

SPIN_MS = 1.0  # a reply's bytes looked for without sleeping this long after the request or the last bytes
WAIT_CAP_S = 0.005  # the longest one wait for a reply's bytes before the SDK's loop looks at its timeout again


class WaitingPortHandler(sdk.PortHandler):
    """dynamixel-sdk's ``PortHandler`` whose ``readPort`` waits for bytes, `SPIN_MS` after the request and the
    last bytes, instead of returning none at once (module doc). ``packet_timeout`` and ``getTimeSinceStart`` are
    the SDK's: ms since the request was sent."""

    _last_rx = 0.0  # time.perf_counter() of the last read that returned bytes

    def readPort(self, length):
        ser = self.ser
        if ser.in_waiting == 0:
            since_ms = self.getTimeSinceStart()
            left_s = (self.packet_timeout - since_ms) / 1000.0
            if left_s > 0 and since_ms > SPIN_MS and time.perf_counter() - self._last_rx > SPIN_MS / 1000.0:
                select.select([ser.fileno()], [], [], min(left_s, WAIT_CAP_S))
        data = ser.read(length)
        if data:
            self._last_rx = time.perf_counter()
        return data


SDK_BAUDS = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)  # both SDK and servo support


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


def candidate_ports() -> list[str]:
    """USB serial devices that might hold a Dynamixel adapter."""
    return sorted(set(glob.glob("/dev/ttyUSB*") + glob.glob("/dev/ttyACM*") + glob.glob("/dev/serial/by-id/*")))


MARGIN_MS_PTY, MARGIN_MS_USB = 10.0, 4.0  # reply-timeout slack without $FELIS_TIMEOUT_MARGIN_MS
# `--port virtual`: the emulated servos are a process on this host, answering when the scheduler runs them; a
# loaded machine (an optimisation on every core) once ran a connect's pings past the pty's 10 ms
MARGIN_MS_VIRTUAL = 40.0


def env_margin_ms(environ=None) -> float:
    """``$FELIS_TIMEOUT_MARGIN_MS`` (0…1000 ms) as a number; a bad value is a `ParameterError` naming it."""
    text = (os.environ if environ is None else environ)["FELIS_TIMEOUT_MARGIN_MS"]
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and 0 <= v <= 1000):
        raise ParameterError(f"FELIS_TIMEOUT_MARGIN_MS must be 0…1000 (ms), got {text!r}")
    return v


class BusPort:
    """The serial-port half of `DynamixelBus` (module doc); the bus's ``__init__`` sets these attributes."""

    port_name: str
    baud: int
    return_delay_us: float
    busy_recoveries: int
    _port: sdk.PortHandler | None
    _lock_fd: int | None
    _lock: threading.RLock
    _latency_ms: float | None
    _margin_ms: float | None

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def open(self) -> Self:
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
        port = WaitingPortHandler(self.port_name)
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
            self._margin_ms = (env_margin_ms() if os.environ.get("FELIS_TIMEOUT_MARGIN_MS")
                               else MARGIN_MS_PTY if pty else MARGIN_MS_USB)
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

    def __enter__(self) -> Self:
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
        replies = [p for p in PacketReader().feed(data) if p.crc_ok and p.inst == STATUS]
        if replies and sum(len(p.raw) for p in replies) == len(data):  # a bus after all: its answers came late
            ids = ", ".join(str(i) for i in sorted({p.id for p in replies}))
            raise CommError(f"{self.port_name}: {len(replies)} Dynamixel replies (ID {ids}) came after felis had "
                            "given up on them: the servos answer, but slower than the reply timeout (a USB "
                            "adapter's latency timer, a long Return Delay Time, or a host too loaded to read them "
                            "in time)")
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
