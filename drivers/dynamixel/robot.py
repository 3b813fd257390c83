"""`DynamixelRobot`: the HAL `Robot` on real (or virtual) Dynamixel servos.

Units: radians and SI above this class; ticks only inside it. For joint i with description fields
direction ``d``, zero ``z`` (rad around tick 2048) and transmission ``m`` (``felis.spec``), and a
calibration with direction ``c`` and offset ``o`` (rad; identity until calibration exists)::

    horn angle  a = c·(d·q/m + z) + o = k·q + b,   k = c·d/m,   b = c·z + o
    ticks       = 2048 + a / (2π/4096)
    q           = (a − b) / k,   dq = ω_horn / k,   effort = τ_horn · k

so a calibrated joint has the same zero and sign as the MJCF model. Effort comes from Present
Current (× stall torque / stall current) or, on XL430, Present Load (fraction of stall torque).

Per tick: one sync read (Fast Sync Read where the firmware has it) of a 13-byte block that Indirect
Addressing gathers at Indirect Data 1 (`TICK_ITEMS`): Torque Enable (64), Hardware Error Status (70),
Bus Watchdog (98) and Present Current/Load, Velocity, Position (126, 10 bytes); and one sync write of
Profile Velocity + Goal Position (address 112, 8 bytes, contiguous) when the command carries velocity
limits (so they cost no extra packet), else of Goal Position alone (address 116, 4 bytes). The map is
written at connect (read back; a servo whose torque was on gets it when arming, with torque briefly
off). So every tick knows, per servo: whether torque is still on (a servo switched off from elsewhere,
or one that rebooted after a power dip: its RAM, the map included, is back to factory values and its
block reads as zeros: ``State.faults.torque_off`` / ``rebooted``), its hardware error bits
(``State.faults.hardware``) and whether its Bus Watchdog tripped (``State.faults.watchdog``). The loop
stops the run on each, naming the joint. A servo that did not answer keeps its last values and is
marked in ``State.faults.stale``; if none answered, ``read()`` raises `CommError` (the loop holds the
last command and counts it). IMU (``imu_port``): each tick's
``State.imu`` is `ImuReader.read` (latest orientation and rate, the accelerometer's mean since the last
tick); when the sensor has gone quiet (no frame for ``IMU_MAX_AGE_S``) or its port failed, ``State.imu`` is
None rather than a frozen reading: a controller never steers by an orientation that stopped updating.

Operating mode and gains: every joint's servo must be in the description's operating mode (3 position,
4 extended position, 5 current-based position; an EEPROM item, fixed with `felis check-eeprom`); connect
writes the description's Position P/I/D Gain and Feedforward 1st/2nd Gain (RAM; the model's factory values
where the description gives none) and, in mode 5, Goal Current (the description's, at most the servo's Current
Limit; default: that limit), and reads them back.

``arm()`` reads the present positions, writes them as goals, then enables torque and reads Torque
Enable back: no jump at start-up, and a servo that refuses torque (hardware-error shutdown) is an
error naming it. Torque goes off on ``disarm()``, ``close()`` and on any unhandled exception, and is
read back (``torque_off_verified``: True when every servo that answered reads 0).

Deadman (``bus_watchdog_s``, default `BUS_WATCHDOG_S` = 0.1 s): the first goal write after arming sets
every servo's Bus Watchdog (item 98, units of 20 ms). If the host then goes silent (SIGKILL, a hung or
dead host, a pulled USB cable), each servo stops where it is within that time: it holds its present
position and refuses goal writes (the item reads −1) until cleared. Disarming clears it (writes 0), and
connecting clears one that a killed run left tripped (with a warning). ``bus_watchdog_s=None``
disables it. ``$FELIS_BUS_WATCHDOG_MS`` (20…2540 ms) sets the default for every run on a host that cannot keep
0.1 s (a slow single-board computer, a loaded test machine: `make test` sets 1 s); the servos still stop that long
after the host's last packet.
"""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from felis.drivers.dynamixel.bus import CorruptReplyError, DynamixelBus, NoReplyError, ServoStatusError
from felis.drivers.dynamixel.controltable import STATE_BLOCK, address, control_table, span
from felis.drivers.imu import apply_mounting
from felis.errors import CalibrationError, CommError, DescriptionError, ParameterError
from felis.hal import Command, Faults, Imu, RobotBase, State
from felis.servos import RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, STALL_CURRENT_A, hardware_error_names, servo_model
from felis.spec import RobotSpec

_GOAL_BLOCK = span("profile_velocity", "goal_position")  # Profile Velocity (4) + Goal Position (4)
_GOAL = span("goal_position", "goal_position")  # Goal Position alone
_TORQUE_ENABLE = address("torque_enable")
_HW_ERROR = address("hardware_error_status")
_BUS_WATCHDOG = address("bus_watchdog")
_HOMING_OFFSET = address("homing_offset")
_OPERATING_MODE = address("operating_mode")
_P_GAIN = address("position_p_gain")  # the same address on every X-series model (84)
_GAIN_ITEMS = ("position_p_gain", "position_i_gain", "position_d_gain", "feedforward_1st_gain", "feedforward_2nd_gain")
_BLOCK_DTYPE = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])
# what one tick reads per servo, gathered by Indirect Addressing: addresses in order, then the layout
TICK_ITEMS = (_TORQUE_ENABLE, _HW_ERROR, _BUS_WATCHDOG, *range(STATE_BLOCK[0], STATE_BLOCK[0] + STATE_BLOCK[1]))
_TICK_DTYPE = np.dtype([("torque", "u1"), ("hw", "u1"), ("watchdog", "u1"), ("current", "<i2"),
                        ("velocity", "<i4"), ("position", "<i4")])
BUS_WATCHDOG_S = 0.1  # the deadman: servos stop this long after the host's last packet
CHECK_RETRIES = 2  # extra tries of the one-off reads that check the servos (connecting, torque read-back)
SETUP_RETRIES = 4  # extra tries of a read every servo must answer (arming): one-off, so a noisy bus gets more
WATCHDOG_TRIPPED = 0xFF  # Bus Watchdog reads -1 once tripped
BUS_WATCHDOG_ENV = "FELIS_BUS_WATCHDOG_MS"


def default_bus_watchdog_s(environ=None) -> float:
    """The deadman time a run arms (module doc): `BUS_WATCHDOG_S`, or ``$FELIS_BUS_WATCHDOG_MS`` where set (20…2540
    ms, the item's range; rounded to its 20 ms units when written). A bad value is a `ParameterError` naming it."""
    text = (os.environ if environ is None else environ).get(BUS_WATCHDOG_ENV, "").strip()
    if not text:
        return BUS_WATCHDOG_S
    try:
        ms = float(text)
    except ValueError:
        ms = math.nan
    if not (math.isfinite(ms) and 20 <= ms <= 127 * 20):
        raise ParameterError(f"{BUS_WATCHDOG_ENV} must be 20…2540 (ms), got {text!r}")
    return ms / 1000.0


IMU_MAX_AGE_S = 0.1  # an IMU reading older than this is none (10 samples at 100 Hz; USB delivers in ~16 ms bursts)


@dataclass(frozen=True)
class Calibration:
    """Host-side corrections from a calibration file (`felis.calib.calfile.CalibrationFile.for_robot`).

    Joints: ``a = direction·(servo angle from the description) + offset``; with the joint zeros held in
    the servos' Homing Offset (what `felis calibrate` writes) ``direction`` is all ones and ``offset`` zero.
    IMU: ``imu_rotation`` is the sensor's orientation in the body frame (unit quaternion w, x, y, z),
    ``gyro_bias`` the sensor-frame rate it reports at rest (rad/s); None = identity / zero.
    """

    direction: np.ndarray  # ±1 per joint
    offset: np.ndarray  # rad per joint
    imu_rotation: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    homing: np.ndarray | None = None  # Homing Offset (ticks) each servo must hold; checked on connect
    tick_range: tuple[np.ndarray, np.ndarray] | None = None  # Min/Max Position Limit (ticks): goals clip to it

    @staticmethod
    def identity(n: int) -> Calibration:
        return Calibration(np.ones(n), np.zeros(n))


class DynamixelRobot(RobotBase):
    """A robot description driven over one Dynamixel bus (and, for the cat, an RVC IMU port).

    Args:
        spec: the robot description.
        port: serial device of the Dynamixel bus.
        baud: the servos' baud rate.
        calibration: per-joint direction and offset, and the IMU's mounting rotation and gyro bias (applied to
            every IMU reading: `felis.drivers.imu.apply_mounting`); identity when None.
        imu_port: serial device of the BNO08x in UART-RVC mode (only if the description has an IMU).
        bus: an already-built `DynamixelBus` (tests, custom timeouts); ``port``/``baud`` are then ignored.
        retries: extra sync reads per tick for servos that did not answer.
        bus_watchdog_s: the deadman time (module doc): ``"default"`` is `default_bus_watchdog_s` (0.1 s unless
            ``$FELIS_BUS_WATCHDOG_MS``), None turns it off (a leader arm moved by hand).
    """

    realtime = True

    def __init__(self, spec: RobotSpec, port: str, baud: int = 1_000_000, *, calibration: Calibration | None = None,
                 imu_port: str | None = None, bus: DynamixelBus | None = None, retries: int = 1,
                 fast_sync_read: bool = True, hardware_poll_s: float = 0.5,
                 bus_watchdog_s: float | Literal["default"] | None = "default", imu_required: bool = False):
        super().__init__(spec)
        if bus_watchdog_s == "default":
            bus_watchdog_s = default_bus_watchdog_s()
        elif bus_watchdog_s is not None and not 0.02 <= bus_watchdog_s <= 127 * 0.02:
            raise ValueError(f"bus_watchdog_s must be within 0.02…2.54 s (or None), got {bus_watchdog_s}")
        self.bus = bus or DynamixelBus(port, baud, retries=retries, fast_sync_read=fast_sync_read)
        self.ids = [j.servo_id for j in spec.joints]
        self.imu_port = imu_port
        self.imu = None
        self.imu_required = imu_required
        self.calibration = calibration or Calibration.identity(spec.n)
        self.hardware_poll_s = hardware_poll_s
        self.warnings: list[str] = []
        n = spec.n
        cal = self.calibration
        d = np.array([j.direction for j in spec.joints], float)
        z = np.array([j.zero for j in spec.joints], float)
        m = np.array([j.m_per_rad for j in spec.joints], float)
        self._k = cal.direction * d / m
        self._b = cal.direction * z + cal.offset
        self._tick_lo, self._tick_hi = cal.tick_range if cal.tick_range is not None else (0, 4095)
        models = [servo_model(j.servo) for j in spec.joints]
        # raw Present Current/Load unit -> horn torque (N·m)
        self._torque_per_unit = np.array([
            (mdl.stall_torque / STALL_CURRENT_A[mdl.name]) * control_table(mdl.name).items["present_current"].scale
            if "present_current" in control_table(mdl.name).items else mdl.stall_torque * 0.001
            for mdl in models])
        self._q = np.zeros(n)
        self._dq = np.zeros(n)
        self._effort = np.zeros(n)
        self._hw = np.zeros(n, dtype=np.int32)
        self._alert_at = np.full(n, -np.inf)
        self._torque = np.zeros(n, dtype=bool)
        self._t0 = time.monotonic()
        self._profile_set = False  # a nonzero Profile Velocity was written: the next write must reset it
        self._p_described = np.array([int(j.pid[0]) if j.pid[0] is not None
                                      else control_table(j.servo).item("position_p_gain").default
                                      for j in spec.joints], dtype=np.int64)  # Position P Gain as described
        self._p_sent = self._p_described  # what the servos hold; this very object: P as described (Command.stiffness)
        self.bus_watchdog_s = bus_watchdog_s
        self._deadman_on = False  # the Bus Watchdog is set on the servos
        self._indirect: dict[int, tuple[int, int]] = {}  # servo ID -> (Indirect Address 1, Indirect Data 1)
        self._mapped = np.zeros(n, dtype=bool)  # the tick map is in place on this servo
        self._torque_lost = np.zeros(n, dtype=bool)
        self._rebooted = np.zeros(n, dtype=bool)
        self._tripped = np.zeros(n, dtype=bool)
        self.torque_off_verified: bool | None = None  # after disarm/close: every answering servo read 0

    # ------------------------------------------------------------------ conversions
    def q_to_ticks(self, q: np.ndarray) -> np.ndarray:
        a = self._k * np.asarray(q, float) + self._b
        return np.clip(np.rint(2048.0 + a / RAD_PER_TICK), self._tick_lo, self._tick_hi).astype(np.int64)

    def ticks_to_q(self, ticks: np.ndarray) -> np.ndarray:
        a = (np.asarray(ticks, float) - 2048.0) * RAD_PER_TICK
        return (a - self._b) / self._k

    # ------------------------------------------------------------------ lifecycle
    def _connect(self) -> None:
        bus = self.bus
        bus.open()
        missing, wrong = [], []
        for k, j in enumerate(self.spec.joints):
            try:
                f = bus.ping(j.servo_id, retries=CHECK_RETRIES)
            except (NoReplyError, CorruptReplyError):
                if k == 0:
                    self._not_a_bus()
                missing.append(f"{j.name} (ID {j.servo_id})")
                continue
            if f.model != j.servo:
                wrong.append(f"{j.name}: ID {j.servo_id} is a {f.model}, the description says {j.servo}")
        if missing:
            raise CommError(f"{len(missing)} of {self.spec.n} servos do not answer at {bus.baud} bps on "
                            f"{bus.port_name}: {', '.join(missing)}; check power and cabling, or `felis scan`")
        if wrong:
            raise DescriptionError(self.spec.source, "servo", "; ".join(wrong))
        modes = bus.sync_read(self.ids, _OPERATING_MODE, 1, fast=False, retries=CHECK_RETRIES)
        wrong_mode = [f"{j.name} (ID {j.servo_id}) is in mode {modes.data[j.servo_id][0]}, the description says "
                      f"{j.operating_mode}" for j in self.spec.joints
                      if modes.data[j.servo_id] is not None and modes.data[j.servo_id][0] != j.operating_mode]
        if wrong_mode:
            raise CommError(f"servos in the wrong operating mode: {'; '.join(wrong_mode)}; fix: `felis check-eeprom "
                            "--robot NAME` (writes it), or `felis torque off` then `felis write ID operating_mode N`")
        self._write_controller()
        self._p_sent = self._p_described
        if self.calibration.homing is not None:
            res = bus.sync_read(self.ids, _HOMING_OFFSET, 4, fast=False, retries=CHECK_RETRIES)
            held = {i: int.from_bytes(b, "little", signed=True) for i, b in res.data.items() if b is not None}
            differ = [f"{j.name} (ID {j.servo_id}) holds {held[j.servo_id]}, the file {int(h)}"
                      for j, h in zip(self.spec.joints, self.calibration.homing, strict=True)
                      if j.servo_id in held and held[j.servo_id] != int(h)]
            if differ:
                raise CalibrationError(f"Homing Offset differs from the calibration file: {'; '.join(differ)}; "
                                       "see `felis calibration diff` and resolve with `felis calibration apply`")
        self._clear_watchdog(warn=True)
        self._install_map()
        for i, secs, fix in bus.check_return_delay(self.ids, CHECK_RETRIES):
            self.warnings.append(f"servo {i}: Return Delay Time {secs * 1e6:.0f} µs slows every read; fix: {fix}")
        lat = bus.latency_warning()
        if lat:
            self.warnings.append(lat)
        if self.imu_port and self.spec.sensors.imu:
            self._open_imu()
        self._t0 = time.monotonic()
        self._read_block(require_all=True)

    def _write_controller(self) -> None:
        """The description's controller gains (and Goal Current in mode 5) into each servo's RAM, read back. Its
        reads get `CHECK_RETRIES`, as the connection's pings and sync reads, not the bus's one: a loaded host (the
        virtual bus's emulator descheduled) can miss a reply twice while connecting."""
        bus = self.bus
        read = functools.partial(bus.read, raw=True, retries=CHECK_RETRIES)
        for j in self.spec.joints:
            table = control_table(j.servo)
            values = dict(zip(_GAIN_ITEMS, (*j.pid, *j.feedforward), strict=True))
            want = {n: int(v if v is not None else table.item(n).default) for n, v in values.items()}
            if j.operating_mode == 5 and "goal_current" in table.items:
                item = table.item("goal_current")
                amps = j.goal_current
                limit = int(read(j.servo_id, "current_limit"))  # the servo's own (EEPROM) cap
                want["goal_current"] = min(limit, round(amps / item.scale)) if amps is not None else limit
            for name, raw in want.items():
                if read(j.servo_id, name) != raw:
                    bus.write(j.servo_id, name, raw, raw=True)
                    back = read(j.servo_id, name)
                    if back != raw:
                        raise CommError(f"{j.name} (ID {j.servo_id}): {name} reads {back} after writing {raw}")

    def _not_a_bus(self) -> None:
        """The first servo did not answer: is this port streaming something else (the IMU)?"""
        self.bus.check_quiet(0.15)

    def _open_imu(self) -> None:
        """Open the IMU and wait for its first frame: silent or speaking another protocol is a refusal when the
        controller needs the IMU (``imu_required``), else a warning (the run goes on without orientation)."""
        from felis.drivers.imu import ImuReader

        self.imu = ImuReader(self.imu_port)
        wait = getattr(self.imu, "wait_first", None)
        if wait is None:
            return
        try:
            wait(0.5)
        except CommError as e:
            if self.imu_required:
                self.imu.close()
                self.imu = None
                raise
            self.warnings.append(f"{e}; running without IMU readings")

    def _arm(self) -> None:
        bus = self.bus
        self._read_block(require_all=True)  # goal = present: no jump when torque comes on
        ticks = self.q_to_ticks(self._q)
        bus.sync_write(*_GOAL_BLOCK, {i: _goal_bytes(0, t) for i, t in zip(self.ids, ticks, strict=True)})
        self._profile_set = False
        if not self._mapped.all() and self._indirect:  # torque was on at connect: map with torque off
            bus.sync_write(_TORQUE_ENABLE, 1, {i: b"\x00" for i, m in zip(self.ids, self._mapped, strict=True)
                                               if not m})
            self._install_map()
        self._torque_lost[:] = self._rebooted[:] = self._tripped[:] = False
        self._deadman_on = False
        self._set_torque(np.ones(self.spec.n, dtype=bool))
        back = self._torque_enable()
        silent = [f"{j.name} (ID {j.servo_id})" for j in self.spec.joints if back[j.servo_id] is None]
        if silent:  # not known to be on, nor off: say so, not "did not come on"
            raise CommError(f"could not read Torque Enable back from {', '.join(silent)} after arming "
                            f"(no valid reply on {bus.port_name}); torque is being switched off")
        refused = [f"{j.name} (ID {j.servo_id})" for j in self.spec.joints if back[j.servo_id] != 1]
        if refused:
            hw = []
            for j in self.spec.joints:
                if f"{j.name} (ID {j.servo_id})" in refused:
                    try:
                        _, names = bus.hardware_error(j.servo_id)
                        if names:
                            hw.append(f"{j.name}: {'+'.join(names)}")
                    except CommError:
                        pass
            detail = f" (hardware error: {', '.join(hw)}; `felis reboot ID` clears it)" if hw else ""
            raise CommError(f"torque did not come on for {', '.join(refused)}{detail}")

    def _set_torque(self, mask: np.ndarray) -> None:
        self.bus.sync_write(_TORQUE_ENABLE, 1, {i: bytes((int(on),)) for i, on in zip(self.ids, mask, strict=True)})
        self._torque = np.array(mask, dtype=bool)

    def _disarm(self) -> None:
        if self.bus.is_open:
            self._safe_off()

    def _close(self) -> None:
        try:
            if self.bus.is_open:
                try:
                    self._safe_off()
                except CommError:
                    pass  # the port is gone: nothing more we can do (the Bus Watchdog stops the servos)
        finally:
            self.bus.close()
            if self.imu is not None:
                self.imu.close()
                self.imu = None

    def _safe_off(self) -> None:
        """Torque off, the deadman cleared, and Torque Enable read back (``torque_off_verified``).

        A servo that still reads 1 gets the write again (a lost sync write); one that does not answer
        leaves the result unverified. The Bus Watchdog goes back to 0 after torque is off, which also
        clears a tripped one for the next run."""
        self.torque_off_verified = None
        off = np.zeros(self.spec.n, dtype=bool)
        self._set_torque(off)
        if self._deadman_on or self._tripped.any():
            self.bus.sync_write(_BUS_WATCHDOG, 1, {i: b"\x00" for i in self.ids})
            self._deadman_on = False
        for _ in range(3):
            back = self._torque_enable()
            on = [i for i in self.ids if back[i]]
            if not on:
                self.torque_off_verified = None not in back.values()
                return
            self.bus.sync_write(_TORQUE_ENABLE, 1, {i: b"\x00" for i in on})
        self.torque_off_verified = False

    def _torque_enable(self) -> dict[int, int | None]:
        """Torque Enable of every servo, by sync read; a servo whose reply was lost or corrupt is asked
        again on its own (up to 3 times); None where no valid reply came."""
        res = self.bus.sync_read(self.ids, _TORQUE_ENABLE, 1, fast=False, retries=CHECK_RETRIES)
        out = {i: (None if res.data[i] is None else res.data[i][0]) for i in self.ids}
        for i in [i for i, v in out.items() if v is None]:
            for _ in range(3):
                try:
                    out[i] = self.bus.read_raw(i, _TORQUE_ENABLE, 1)[0]
                    break
                except ServoStatusError:
                    continue
                except CommError as e:
                    if e.fatal:
                        return out
        return out

    # ------------------------------------------------------------------ fail-safe set-up
    def _clear_watchdog(self, warn: bool) -> None:
        """Bus Watchdog to 0 on every servo; a tripped one (a run that was killed) is a warning."""
        res = self.bus.sync_read(self.ids, _BUS_WATCHDOG, 1, fast=False, retries=CHECK_RETRIES)
        tripped = [f"{j.name} (ID {j.servo_id})" for j in self.spec.joints
                   if res.data[j.servo_id] is not None and res.data[j.servo_id][0] == WATCHDOG_TRIPPED]
        set_ = [i for i in self.ids if res.data[i] is not None and res.data[i][0]]
        if set_:
            self.bus.sync_write(_BUS_WATCHDOG, 1, {i: b"\x00" for i in set_})
        if tripped and warn:
            self.warnings.append(f"Bus Watchdog had stopped {', '.join(tripped)}: the last run ended without "
                                 "closing (killed, or the host hung); cleared")

    def _install_map(self) -> None:
        """Write the tick's Indirect Address map (`TICK_ITEMS`) and read it back, per servo.

        Servos whose model has no Indirect Addressing, or whose map did not take (torque on: the map is
        written while arming, torque briefly off), are read the plain way until it does."""
        want = b"".join(int(a).to_bytes(2, "little") for a in TICK_ITEMS)
        self._indirect = {}
        for j in self.spec.joints:
            ind = getattr(control_table(j.servo), "indirect", None)
            if ind is None or ind[2] < len(TICK_ITEMS):
                self._indirect = {}
                return
            self._indirect[j.servo_id] = (ind[0], ind[1])
        starts = {a for a, _ in self._indirect.values()}
        if len(starts) != 1 or len({d for _, d in self._indirect.values()}) != 1:
            self._indirect = {}  # mixed layouts: one sync read cannot cover them
            return
        addr = starts.pop()
        res = self.bus.sync_read(self.ids, addr, len(want), fast=False, retries=CHECK_RETRIES)
        todo = [i for i in self.ids if res.data[i] != want]
        if todo:
            self.bus.sync_write(addr, len(want), {i: want for i in todo})
            res = self.bus.sync_read(self.ids, addr, len(want), fast=False, retries=CHECK_RETRIES)
        self._mapped = np.array([res.data[i] == want for i in self.ids])

    @property
    def tick_block_bytes(self) -> int:
        """Bytes read per servo each tick: the Indirect Addressing block (`TICK_ITEMS`) where every servo
        has it mapped, else the plain present current/velocity/position block."""
        mapped = bool(self._indirect) and bool(self._mapped.all())
        return _TICK_DTYPE.itemsize if mapped else STATE_BLOCK[1]

    # ------------------------------------------------------------------ tick
    def _read_block(self, require_all: bool = False) -> np.ndarray:
        ids = self.ids
        mapped = bool(self._indirect) and bool(self._mapped.all())
        retries = SETUP_RETRIES if require_all else None
        if mapped:
            data_addr = next(iter(self._indirect.values()))[1]
            res = self.bus.sync_read(ids, data_addr, _TICK_DTYPE.itemsize, retries=retries)
        else:
            res = self.bus.sync_read(ids, *STATE_BLOCK, retries=retries)
        stale = np.array([res.data[i] is None for i in ids])
        if stale.all() or (require_all and stale.any()):
            names = [f"{j.name} (ID {j.servo_id})" for j, s in zip(self.spec.joints, stale, strict=True) if s]
            raise CommError(f"no valid reply from {', '.join(names)} on {self.bus.port_name} (lost or corrupt, "
                            "retried)")
        ok_all = not stale.any()
        ok = slice(None) if ok_all else ~stale  # a slice where every servo answered: views, no masks
        data = res.data
        raw = np.frombuffer(b"".join(data[i] for i in ids) if ok_all else
                            b"".join(data[i] for i, s in zip(ids, stale, strict=True) if not s),
                            dtype=_TICK_DTYPE if mapped else _BLOCK_DTYPE)
        good, raw_good = ok, raw
        if mapped:
            torque = raw["torque"] != 0
            self._torque_lost[ok] = self._torque[ok] & ~torque
            self._tripped[ok] = raw["watchdog"] == WATCHDOG_TRIPPED
            self._hw[ok] = raw["hw"]
            if torque.all():
                self._rebooted[ok] = False
            else:
                # a rebooted servo's RAM is back to factory values: its Indirect Addresses point at the data
                # area itself, which reads as zeros, so its whole block is zero (position 0 included)
                reboot = ~torque & (raw["position"] == 0) & (raw["velocity"] == 0) & (raw["current"] == 0)
                self._rebooted[ok] = self._torque[ok] & reboot
                if reboot.any():  # its block holds no position: keep the last one
                    good = ~stale
                    good[~stale] = ~reboot
                    raw_good = raw[~reboot]
        self._q[good] = ((raw_good["position"] - 2048.0) * RAD_PER_TICK - self._b[good]) / self._k[good]
        self._dq[good] = raw_good["velocity"] * RAD_S_PER_VELOCITY_UNIT / self._k[good]
        self._effort[good] = raw_good["current"] * self._torque_per_unit[good] * self._k[good]
        if res.errors and not mapped:  # the plain block carries no error bits: poll on the Alert flag
            now = time.monotonic()
            for idx, i in enumerate(ids):
                err = res.errors.get(i, 0)
                if err & 0x80:
                    if now - self._alert_at[idx] >= self.hardware_poll_s:
                        self._alert_at[idx] = now
                        try:
                            self._hw[idx] = self.bus.hardware_error(i)[0]
                        except CommError:
                            pass
                elif i in res.errors:
                    self._hw[idx] = 0
        return stale

    def _read(self) -> State:
        stale = self._read_block()
        imu = None
        if self.imu is not None and not self.imu.stale(IMU_MAX_AGE_S):
            imu = self.imu.read()  # accel: the mean since the previous tick
            cal = self.calibration
            if imu is not None and (cal.imu_rotation is not None or cal.gyro_bias is not None):
                imu = apply_mounting(imu, cal.imu_rotation, cal.gyro_bias)  # sensor frame -> body frame
        return State(t=time.monotonic() - self._t0, q=self._q.copy(), dq=self._dq.copy(), effort=self._effort.copy(),
                     imu=imu if isinstance(imu, Imu) else None,
                     faults=Faults(hardware=self._hw.copy(), comm_errors=self.bus.failed_transactions,
                                   stale=stale, torque_off=self._torque_lost.copy(), rebooted=self._rebooted.copy(),
                                   watchdog=self._tripped.copy()))

    def _write(self, command: Command) -> Command:
        q = np.asarray(command.q, float)
        if q.shape != (self.spec.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"command must be {self.spec.n} finite joint targets")
        torque = command.torque
        if torque is not None:
            torque = np.asarray(torque, dtype=bool)
            if not np.array_equal(torque, self._torque):
                self._set_torque(torque)
        elif not self._torque.all():
            self._set_torque(np.ones(self.spec.n, dtype=bool))
        ticks = self.q_to_ticks(q)
        if not self._deadman_on and self.bus_watchdog_s is not None and self._torque.any():
            units = max(1, min(127, round(self.bus_watchdog_s / 0.02)))
            self.bus.sync_write(_BUS_WATCHDOG, 1, {i: bytes((units,)) for i in self.ids})
            self._deadman_on = True
        if command.dq_max is None and not self._profile_set:  # goals only: 4 bytes per servo
            raw = ticks.astype("<i4").tobytes()
            self.bus.sync_write(*_GOAL, {i: raw[4 * k: 4 * k + 4] for k, i in enumerate(self.ids)})
        else:  # Profile Velocity + Goal Position in one 8-byte block (0 = unlimited)
            if command.dq_max is None:
                prof = np.zeros(self.spec.n, dtype=np.int64)
            else:
                dq_max = np.asarray(command.dq_max, float)
                v = np.abs(np.nan_to_num(dq_max * self._k, nan=0.0, posinf=0.0)) / RAD_S_PER_VELOCITY_UNIT
                prof = np.where(np.isfinite(dq_max), np.clip(np.ceil(v), 1, 32767), 0).astype(np.int64)
            buf = np.empty(self.spec.n, dtype=[("prof", "<u4"), ("goal", "<u4")])
            buf["prof"], buf["goal"] = prof, ticks
            raw = buf.tobytes()
            self.bus.sync_write(*_GOAL_BLOCK, {i: raw[8 * k: 8 * k + 8] for k, i in enumerate(self.ids)})
            self._profile_set = bool(prof.any())
        stiffness = self._write_stiffness(command.stiffness)
        return Command(q=self.ticks_to_q(ticks), dq_max=command.dq_max, torque=torque, stiffness=stiffness)

    def _write_stiffness(self, stiffness) -> np.ndarray | None:
        """`felis.hal.Command.stiffness` as Position P Gain = round(P·s) (RAM), one sync write of the joints whose
        gain changes (none on most ticks); None puts the described gains back."""
        if stiffness is None:
            if self._p_sent is self._p_described:  # the hot path: nothing to do on a tick without compliance
                return None
            p = self._p_described
        else:
            s = np.asarray(stiffness, dtype=float)
            if s.shape != (self.spec.n,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
                raise ValueError(f"stiffness must be {self.spec.n} finite fractions > 0")
            p = np.maximum(1, np.rint(self._p_described * np.minimum(s, 1.0))).astype(np.int64)
        changed = np.flatnonzero(p != self._p_sent)
        if changed.size:
            self.bus.sync_write(_P_GAIN, 2, {self.ids[k]: int(p[k]).to_bytes(2, "little") for k in changed})
        self._p_sent = p
        return None if stiffness is None else p / self._p_described

    def _advance(self, dt: float) -> None:
        """Hardware moves on its own; the loop's wall clock paces the ticks."""

    def hardware_errors(self) -> dict[str, list[str]]:
        """Joints with hardware errors, by name (from the last read)."""
        return {j.name: hardware_error_names(int(b)) for j, b in zip(self.spec.joints, self._hw, strict=True) if b}


def _goal_bytes(profile: int, ticks: int) -> bytes:
    return int(profile).to_bytes(4, "little") + int(ticks).to_bytes(4, "little", signed=True)


