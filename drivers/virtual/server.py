"""The virtual bus on a pseudo-terminal (`VirtualBus`): servos by ID, a server thread that parses what the
client writes, dispatches it and writes the replies (at once, or when the wire would deliver them),
fault injection (`felis.drivers.virtual.faultplan`) and counters (`BusStats`).

``VirtualBus.for_robot`` builds the servos of a robot description, ``VirtualBus.for_models`` one servo of each
given model (any supported X-series model); a `HornBackend` may drive their horns
(servo-in-the-loop, `felis.sim.servo_in_loop`) and feed an emulated IMU on a second pty (`VirtualImu`).

Wire
----
The client's baud rate is read from the pty master (``TCGETS2``: the slave's c_ospeed, custom rates
included; else ``tcgetattr`` and the standard B-constants; ▸ a rate that cannot be read counts as
"unknown" and every servo answers). A servo only hears packets sent at its own baud rate, so a scan
across rates finds each servo at its own. A partial packet followed by a 50 ms gap is discarded,
as a servo's receiver does. ▸ Servos that share an ID (factory-new ones: ID 1) answer in the same
slot and collide: the line is a wired-AND of both with their start bits a byte apart, so the client
gets one garbled packet (`_collide`), as on a real bus. ▸ In a SYNC_READ / BULK_READ the listed
servos that are present answer in list order and a missing one is simply skipped (the SDK then times out on it); in a
FAST_SYNC_READ / FAST_BULK_READ the header announces every listed servo, the present ones append
their segments and a missing one leaves the packet short (the SDK reports COMM_RX_CORRUPT).
SYNC_WRITE / BULK_WRITE with a malformed parameter block are ignored as a whole.

Timing: ``wire_time=False`` writes all replies to a packet at once, as soon as it is parsed (Return
Delay Time not modelled). ``wire_time=True`` models a half-duplex wire at the client's baud, 10 bits
per byte: a request occupies the wire for len·10/baud from when it is read (or from when the wire is
free), each replying servo waits its Return Delay Time (addr 9, ×2 µs) after the previous byte, then
its reply occupies len·10/baud; each reply is written when its last byte would have arrived. Replies
due later go into a schedule that the server thread keeps while it goes on reading: it polls until
0.3 ms before the next one is due, then spins on ``time.perf_counter`` and writes it. ▸ A fast-read
packet waits for the first servo's Return Delay Time only.

Faults (`FaultPlan`, `parse_fault_plan`): drop a fraction of replies, corrupt a fraction (one random byte
XOR-ed with a random non-zero mask), delay the replies to each request by N ms, remove servos
(silent: they neither answer nor act), raise hardware errors, close the port (to a client the device
vanishes, as an unplugged adapter) now or after N s. ▸ Delayed replies are scheduled, not slept on:
the bus keeps serving meanwhile, so a reply can arrive after the client gave up on it (its next
transaction then flushes or skips the stale packet), as with a slow adapter. ▸ A dropped reply still
occupies the wire in wire-time mode. All draws come from one seeded RNG, so a run is reproducible for
a given seed and packet sequence.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import heapq
import itertools
import math
import os
import random
import select
import struct
import sys
import termios
import threading
import time
import tty
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from felis.drivers.dynamixel import protocol as P
from felis.drivers.imu import SensorMount
from felis.drivers.virtual.backend import BackendFactory, HornBackend
from felis.drivers.virtual.dispatch import dispatch
from felis.drivers.virtual.faultplan import FaultPlan, parse_fault_plan
from felis.drivers.virtual.imu import VirtualImu
from felis.drivers.virtual.memory import BUS_WATCHDOG, TORQUE_ENABLE
from felis.drivers.virtual.packets import Reply
from felis.drivers.virtual.servo import CENTRE, Mount, VirtualServo
from felis.errors import ParameterError
from felis.servos import RAD_PER_TICK
from felis.spec import RobotSpec, load_spec

GAP_S = 0.05  # inter-byte gap after which a partial packet is dropped
SPIN_S = 0.0003  # wire-time: sleep until this long before a reply is due, then spin
HOUSEKEEPING_S = 0.001  # the server thread checks the servos' own clocks (Bus Watchdog, timed faults) this often

_TCGETS2 = 0x802C542A  # _IOR('T', 0x2A, struct termios2), Linux
_TERMIOS2 = struct.Struct("<IIIIB19sII")
_BOTHER = 0o010000
_B_RATES = {getattr(termios, f"B{r}"): r for r in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000,
                                                   576000, 921600, 1000000, 1152000, 2000000, 2500000, 3000000,
                                                   3500000, 4000000) if hasattr(termios, f"B{r}")}


@dataclass
class BusStats:
    """Counters of a `VirtualBus` (read them any time; the server thread updates them)."""

    packets: int = 0  # instruction packets parsed
    replies: int = 0  # status packets written (a fast read's one packet counts once)
    dropped: int = 0  # replies dropped by fault injection
    corrupted: int = 0  # replies corrupted by fault injection
    crc_errors: int = 0  # packets received with a bad CRC
    garbage_bytes: int = 0  # bytes discarded by the parser (noise, partial packets after a gap)
    baud_mismatch: int = 0  # packets no servo heard because none listens at the client's baud
    overflows: int = 0  # replies (partly) lost because the client did not read and the pty was full
    sim_lag_s: float = 0.0  # simulated time skipped because the simulation fell behind the wall clock
    instructions: collections.Counter = field(default_factory=collections.Counter)  # name -> count
    watchdog_trips: list = field(default_factory=list)  # (servo ID, s from its last packet to the trip)
    timed_faults: list = field(default_factory=list)  # (kind, servo ID) of the reboot/torque_off faults applied

    def as_dict(self) -> dict[str, object]:
        d = {k: v for k, v in self.__dict__.items() if k != "instructions"}
        d["instructions"] = dict(self.instructions)
        return d

    def summary(self) -> str:
        inst = ", ".join(f"{k} {v}" for k, v in sorted(self.instructions.items()))
        return (f"{self.packets} packets ({inst or 'none'}), {self.replies} replies, {self.dropped} dropped, "
                f"{self.corrupted} corrupted, {self.crc_errors} CRC errors, {self.garbage_bytes} garbage bytes, "
                f"{self.baud_mismatch} at a baud no servo uses, {self.overflows} overflows"
                + (f", simulation lagged {self.sim_lag_s:.3f} s" if self.sim_lag_s else "")
                + ("; bus watchdog tripped: " + ", ".join(f"ID {i} after {dt:.3f} s" for i, dt in self.watchdog_trips)
                   if self.watchdog_trips else "")
                + ("; faults applied: " + ", ".join(f"{k} ID {i}" for k, i in self.timed_faults)
                   if self.timed_faults else ""))


def client_baud(master_fd: int, buf: bytearray | None = None) -> int | None:
    """The baud rate the client set on the pty's slave side, read through the master (None if unknown)."""
    buf = buf if buf is not None else bytearray(_TERMIOS2.size)
    try:
        fcntl.ioctl(master_fd, _TCGETS2, buf)
        ospeed = _TERMIOS2.unpack_from(buf)[-1]
        if ospeed:
            return ospeed
    except OSError:
        pass
    try:
        speed = termios.tcgetattr(master_fd)[5]
    except termios.error:
        return None
    return None if speed == _BOTHER else _B_RATES.get(speed)



class VirtualBus:
    """Servos on a pseudo-terminal (module doc). ``bus.port`` is the device path a client opens.

    Args:
        servos: the servos on the bus (more with `add_servo`).
        wire_time: model the wire's timing (module doc); may be changed while running.
        faults: a `FaultPlan` or a spec string for `parse_fault_plan`.
        seed: seed of the fault RNG (``FaultPlan.seed`` overrides it).

    ``start()`` / ``stop()`` or ``with VirtualBus(...) as bus:``; ``stop()`` joins every thread
    and closes every file descriptor.
    """

    def __init__(self, servos: Iterable[VirtualServo] = (), *, wire_time: bool = False,
                 faults: FaultPlan | str | None = None, seed: int = 0):
        self.wire_time = wire_time
        self.faults = parse_fault_plan(faults) if isinstance(faults, str) else (faults or FaultPlan())
        self.seed = seed
        self.rng = random.Random(self.faults.seed if self.faults.seed is not None else seed)
        self.stats = BusStats()
        self.lock = threading.RLock()
        self._servos: list[VirtualServo] = []
        self._removed: set[int] = set()  # id(servo) of removed servos
        self._listening: list[VirtualServo] = []
        for s in servos:
            self.add_servo(s)
        self._reader = P.PacketReader()  # the server thread's (`_serve`); housekeeping asks it what is half read
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self.imu_port: str | None = None
        self._fds_lock = threading.Lock()
        self._fds_open = True
        self._wake_r, self._wake_w = os.pipe()
        self._halt = False
        self._server: threading.Thread | None = None
        self._started = False
        self._stopped = False
        self._bus_free = 0.0
        self._due: list[tuple[float, int, bytes, int]] = []  # scheduled replies: (time, seq, bytes, count)
        self._seq = itertools.count()
        self._close_deadline: float | None = None
        self._timed: list[tuple[str, int, float]] = []  # reboot/torque_off faults still to apply
        self._tc_buf = bytearray(_TERMIOS2.size)
        self.spec: RobotSpec | None = None  # set by for_robot
        self.backend: HornBackend | None = None  # set by for_robot(backend=…)
        self.imu: VirtualImu | None = None  # set by for_robot when the backend has an IMU

    # -------------------------------------------------------------- servos
    def add_servo(self, servo: VirtualServo) -> VirtualServo:
        with self.lock:
            self._servos.append(servo)
            self._relist()
        return servo

    def _relist(self) -> None:
        self._listening = [s for s in self._servos if id(s) not in self._removed]

    @property
    def servos(self) -> list[VirtualServo]:
        """Every servo, removed ones included, in the order added."""
        return list(self._servos)

    def servo(self, dxl_id: int) -> VirtualServo:
        """The servo with this ID (present or removed)."""
        for s in self._servos:
            if s.id == dxl_id:
                return s
        raise ParameterError(f"virtual bus has no servo with ID {dxl_id}; IDs: "
                             f"{', '.join(str(s.id) for s in self._servos) or 'none'}")

    def remove_servo(self, dxl_id: int | VirtualServo) -> None:
        """The servo vanishes from the bus (unplugged): it neither hears nor answers until `restore_servo`.

        Takes an ID or the `VirtualServo` itself (needed when several servos share an ID, as factory-new
        ones do).
        """
        with self.lock:
            self._removed.add(id(self._find(dxl_id)))
            self._relist()

    def restore_servo(self, dxl_id: int | VirtualServo) -> None:
        """Plug a removed servo back in (by ID or the `VirtualServo` itself)."""
        with self.lock:
            self._removed.discard(id(self._find(dxl_id)))
            self._relist()

    def _find(self, servo: int | VirtualServo) -> VirtualServo:
        if isinstance(servo, VirtualServo):
            if not any(s is servo for s in self._servos):
                raise ParameterError(f"{servo!r} is not on this virtual bus")
            return servo
        return self.servo(servo)

    def raise_hardware_error(self, dxl_id: int, bits_or_names: int | str | Iterable[str | int]) -> None:
        """Set Hardware Error Status bits on a servo (``"overload"``, ``["overheating", "overload"]``, 0x20)."""
        with self.lock:
            self.servo(dxl_id).raise_hardware_error(bits_or_names)

    def set_faults(self, faults: FaultPlan | str) -> None:
        """Replace the faults; removals, hardware errors and close_after take effect now if running."""
        faults = parse_fault_plan(faults) if isinstance(faults, str) else faults
        with self.lock:
            self.faults = faults
            if faults.seed is not None:
                self.rng = random.Random(faults.seed)
            if self._started:
                self._apply_start_faults()

    def _apply_start_faults(self) -> None:
        f = self.faults
        for dxl_id in f.remove:
            self.remove_servo(dxl_id)
        for dxl_id, bits in f.hwerror.items():
            self.raise_hardware_error(dxl_id, bits)
        if f.close_after is not None:
            self._close_deadline = time.perf_counter() + f.close_after
            self._wake()
        self._timed = [("reboot", i, t) for i, t in f.reboot] + [("torque_off", i, t) for i, t in f.torque_off]
        for _, i, _ in self._timed:
            self.servo(i)  # an unknown ID is one line now, not a silent no-op later

    def housekeeping(self) -> None:
        """What happens on the servos' own clocks, between packets: Bus Watchdog trips and timed faults
        (called by the server thread and a backend's thread, bus lock held). The Bus Watchdog is not judged
        while the host's bytes wait unread (on the pty, or a packet half read): they arrived before now, and a
        server thread starved of CPU must not blame its own delay on the host."""
        armed = [s for s in self._listening if s.mem[BUS_WATCHDOG] and not s.watchdog_tripped]
        if armed and not self._input_waiting():
            for s in armed:
                delay = s.check_watchdog()
                if delay is not None:
                    self.stats.watchdog_trips.append((s.id, delay))
        if self._timed:
            left = []
            for kind, i, t in self._timed:
                s = self.servo(i)
                if s.torque_on_at is None or s.clock() - s.torque_on_at < t:
                    left.append((kind, i, t))
                elif kind == "reboot":
                    s._reboot(b"")
                    self.stats.timed_faults.append((kind, i))
                else:
                    s.set("torque_enable", 0)
                    self.stats.timed_faults.append((kind, i))
            self._timed = left

    def _input_waiting(self) -> bool:
        """The host's bytes are on the pty, unread, or a packet is half read."""
        if self._reader.pending:
            return True
        p = select.poll()
        try:
            p.register(self._master, select.POLLIN)
            return any(ev & select.POLLIN for _, ev in p.poll(0))
        except (OSError, ValueError):  # closed
            return False

    def _busy(self) -> bool:
        """Something on the servos' clocks is pending (an armed Bus Watchdog, a timed fault)."""
        return bool(self._timed) or any(s.mem[BUS_WATCHDOG] and s.mem[TORQUE_ENABLE] and not s.watchdog_tripped
                                        for s in self._listening)

    # -------------------------------------------------------------- dispatch
    def dispatch(self, pkt: P.Packet | bytes, baud: int | None = None) -> list[bytes]:
        """The status packets the servos send back to one packet (no faults, no I/O); for tests."""
        packets = P.PacketReader().feed(pkt) if isinstance(pkt, bytes | bytearray) else [pkt]
        out = []
        for p in packets:
            with self.lock:
                out += [r for _, r in dispatch(self._hearing(baud), p)]
        return out

    def _hearing(self, baud: int | None) -> list[VirtualServo]:
        if baud is None:
            return self._listening
        return [s for s in self._listening if s.baud_bps == baud]

    # -------------------------------------------------------------- lifecycle
    def start(self) -> VirtualBus:
        if self._stopped:
            raise RuntimeError("a stopped VirtualBus cannot be restarted")
        if self._started:
            return self
        self._started = True
        with self.lock:
            self._apply_start_faults()
        self._server = threading.Thread(target=self._serve_guarded, name=f"virtual-bus {self.port}", daemon=True)
        self._server.start()
        if self.imu is not None:
            self.imu.start()
        if self.backend is not None:
            self.backend.start()
        return self

    def stop(self) -> None:
        """Stop every thread, close the ports (idempotent)."""
        self._stopped = True
        self._halt_server()
        self._close_fds()
        if self.imu is not None:
            self.imu.stop()
        if self.backend is not None:
            self.backend.stop()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def close_port(self) -> None:
        """The port vanishes (pty closed): clients get I/O errors, as when a USB adapter is unplugged."""
        self._halt_server()
        self._close_fds()

    def __enter__(self) -> VirtualBus:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def port_open(self) -> bool:
        return self._fds_open

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def _halt_server(self) -> None:
        self._halt = True
        self._wake()
        if self._server is not None and self._server is not threading.current_thread():
            self._server.join(timeout=5.0)

    def _close_fds(self) -> None:
        with self._fds_lock:
            if self._fds_open:
                self._fds_open = False
                for fd in (self._master, self._slave):
                    with contextlib.suppress(OSError):
                        os.close(fd)

    # -------------------------------------------------------------- server thread
    def _serve_guarded(self) -> None:
        try:
            self._serve()
        except Exception as e:  # noqa: BLE001 - a server bug must not hang clients: report and close the port
            print(f"virtual bus: server stopped: {type(e).__name__}: {e}", file=sys.stderr)
            self._close_fds()

    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        reader = self._reader = P.PacketReader()
        last_byte = last_housekeeping = 0.0
        while not self._halt:
            self._flush_due()
            with self.lock:
                t = time.perf_counter()
                if t - last_housekeeping >= HOUSEKEEPING_S:  # not after every packet of a busy bus
                    self.housekeeping()
                    last_housekeeping = t
                busy = self._busy()
            timeout = self._poll_timeout(reader.pending, last_byte)
            events = poller.poll(min(timeout, 5) if busy else timeout)
            now = time.perf_counter()
            if self._close_deadline is not None and now >= self._close_deadline:
                self._close_fds()
                return
            got = False
            for fd, ev in events:
                if fd == self._wake_r:
                    with contextlib.suppress(OSError):
                        os.read(self._wake_r, 4096)
                    continue
                if ev & (select.POLLERR | select.POLLNVAL):
                    return
                try:
                    data = os.read(self._master, 65536)
                except BlockingIOError:
                    continue
                except OSError:
                    return
                got, last_byte = True, now
                for pkt in reader.feed(data):
                    self._process(pkt, now)
            # The gap is judged by silence seen while waiting, not by when bytes are read: a server
            # thread that was starved of CPU must not tear a packet whose rest was already waiting.
            if not got and reader.pending and time.perf_counter() - last_byte >= GAP_S:
                reader.reset()
            self.stats.garbage_bytes = reader.dropped

    def _poll_timeout(self, pending: int, last_byte: float) -> int:
        """Milliseconds poll may sleep: until a partial packet expires, the port closes, or (less the spin
        margin, rounded down) the next scheduled reply is due."""
        now = time.perf_counter()
        ms = 1000
        if pending:
            ms = min(ms, math.ceil((last_byte + GAP_S - now) * 1000.0))
        if self._close_deadline is not None:
            ms = min(ms, math.ceil((self._close_deadline - now) * 1000.0))
        if self._due:
            ms = min(ms, math.floor((self._due[0][0] - SPIN_S - now) * 1000.0))
        return max(0, ms)

    def _process(self, pkt: P.Packet, t_rx: float) -> None:
        stats = self.stats
        stats.packets += 1
        stats.instructions[P.INSTRUCTIONS.get(pkt.inst, f"0x{pkt.inst:02X}")] += 1
        if not pkt.crc_ok:
            stats.crc_errors += 1
        baud = client_baud(self._master, self._tc_buf)
        with self.lock:
            servos = self._hearing(baud)
            if not servos and self._listening:
                stats.baud_mismatch += 1
            replies = dispatch(servos, pkt) if servos else []
        if self.wire_time:
            self._emit_timed(len(pkt.raw), replies, t_rx, baud or 1_000_000)
        elif replies:
            self._emit(replies, t_rx)

    def _faulted(self, data: bytes) -> bytes | None:
        f, rng = self.faults, self.rng
        if f.drop and rng.random() < f.drop:
            self.stats.dropped += 1
            return None
        if f.corrupt and rng.random() < f.corrupt:
            b = bytearray(data)
            b[rng.randrange(len(b))] ^= rng.randrange(1, 256)
            self.stats.corrupted += 1
            return bytes(b)
        return data

    def _emit(self, replies: list[Reply], t_rx: float) -> None:
        """All replies to one packet in one write: now, or ``delay_ms`` after the request arrived."""
        out = [r for _, data in replies if (r := self._faulted(data)) is not None]
        if not out:
            return
        if self.faults.delay_ms:
            self._schedule(t_rx + self.faults.delay_ms / 1000.0, b"".join(out), len(out))
        else:
            self._write(b"".join(out), len(out))

    def _emit_timed(self, request_len: int, replies: list[Reply], t_rx: float, baud: int) -> None:
        """Wire-time mode: each reply is scheduled for when its last byte would arrive (module doc)."""
        byte_s = 10.0 / baud
        end = max(t_rx, self._bus_free) + request_len * byte_s
        if replies and self.faults.delay_ms:
            end += self.faults.delay_ms / 1000.0
        for delay, data in replies:
            end += delay + len(data) * byte_s
            out = self._faulted(data)
            if out is not None:
                self._schedule(end, out, 1)
        self._bus_free = end

    def _schedule(self, t: float, data: bytes, n_replies: int) -> None:
        heapq.heappush(self._due, (t, next(self._seq), data, n_replies))

    def _flush_due(self) -> None:
        """Write every scheduled reply due within the spin margin, each at its time (spinning on the clock)."""
        due = self._due
        while due:
            t = due[0][0]
            if t - time.perf_counter() > SPIN_S:
                return
            while time.perf_counter() < t:
                pass
            _, _, data, n = heapq.heappop(due)
            self._write(data, n)

    def _write(self, data: bytes, n_replies: int) -> None:
        self.stats.replies += n_replies  # counted first: a client may look as soon as the bytes arrive
        try:
            while data:
                n = os.write(self._master, data)
                data = data[n:]
        except BlockingIOError:
            self.stats.overflows += 1
        except OSError:  # the port was closed under us
            self.stats.replies -= n_replies

    # -------------------------------------------------------------- robots
    @classmethod
    def for_models(cls, models: Iterable[str | int], *, baud: int = 1_000_000, first_id: int = 1,
                   **options) -> VirtualBus:
        """One standalone servo per entry of ``models`` (names or Model Numbers, any supported model), IDs
        ``first_id``, ``first_id + 1``, … in order, at ``baud``; ``options`` as for the constructor. An
        unsupported model is a one-line ParameterError naming it."""
        servos = [VirtualServo(m, first_id + k, baud) for k, m in enumerate(models)]
        return cls(servos, **options)

    @classmethod
    def for_robot(cls, spec_or_name: RobotSpec | str, *, baud: int = 1_000_000, wire_time: bool = False,
                  faults: FaultPlan | str | None = None, seed: int = 0,
                  mount_offsets: Mapping[str, float] | None = None, backend: BackendFactory | None = None,
                  imu_mount: SensorMount | None = None) -> VirtualBus:
        """One servo per joint of a robot description (ID, model and mounting from it), at ``baud``,
        Return Delay Time 0, Min/Max Position Limit at the description's joint limits (as `felis check-eeprom`
        expects of a set-up robot). ``mount_offsets`` (joint -> rad) simulates an uncalibrated assembly.

        ``backend(bus)`` builds what drives the horns (`HornBackend`; `felis.sim.servo_in_loop.virtual_bus`
        backs them with the MuJoCo model); when it has an IMU, a `VirtualImu` reports it on ``bus.imu_port``
        through ``imu_mount`` (a mis-mounted, drifting sensor; None: mounted true).
        """
        spec = spec_or_name if isinstance(spec_or_name, RobotSpec) else load_spec(spec_or_name)
        offsets = dict(mount_offsets or {})
        unknown = sorted(set(offsets) - set(spec.names))
        if unknown:
            raise ParameterError(f"mount offset for unknown joint {unknown[0]!r}; joints: {', '.join(spec.names)}")
        servos = []
        for j in spec.joints:
            mount = Mount(j.direction, j.zero, j.m_per_rad, float(offsets.get(j.name, 0.0)))
            s = VirtualServo(j.servo, j.servo_id, baud, mount=mount)
            s.set("return_delay_time", 0)
            s.set("operating_mode", j.operating_mode)  # EEPROM as a set-up robot has it (felis check-eeprom)
            limits = sorted(CENTRE + round(Mount(j.direction, j.zero, j.m_per_rad).horn(q) / RAD_PER_TICK)
                            for q in (j.lower, j.upper))  # as a set-up robot holds them (felis check-eeprom)
            s.set("min_position_limit", max(0, limits[0]))
            s.set("max_position_limit", min(4095, limits[1]))
            s.angle = mount.horn(min(max(0.0, j.lower), j.upper))
            s.set("goal_position", s.get("present_position"))
            servos.append(s)
        bus = cls(servos, wire_time=wire_time, faults=faults, seed=seed)
        bus.spec = spec
        if backend is not None:
            try:
                bus.backend = backend(bus)
                if bus.backend.imu_sample is not None:
                    bus.imu = VirtualImu(bus.backend.imu_sample, imu_mount)
                    bus.imu_port = bus.imu.port
            except BaseException:
                bus.stop()
                raise
        return bus
