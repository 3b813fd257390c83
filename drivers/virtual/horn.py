"""The horn of an emulated servo (`HornModel`, inherited by `VirtualServo`): how the horn angle shows in the
control table, how the horn moves on its own, and the Bus Watchdog that stops it; `Mount` maps the horn to
its joint.

Position frame: the horn angle θ (rad, 0 at the centre tick 2048, positive counter-clockwise) gives

    Present Position = 2048 + s·round(θ / (2π/4096)) + Homing Offset      s = −1 if Drive Mode bit 0 else +1

and Goal Position is read in the same frame. Present Velocity = s·ω in 0.229 rpm units; Present
Current = s·τ / kt in the model's current unit with kt = stall torque / stall current (XL330 1.47 A,
XM430 2.3 A); the XL430's address 126 is Present Load = s·τ / stall torque in 0.1 %. Moving = 1 while
|Present Velocity| > Moving Threshold. Present Input Voltage is the datasheet's nominal supply,
Present Temperature a constant 32 °C, Realtime Tick counts milliseconds mod 32768.

Standalone dynamics (no simulation), updated lazily from the wall clock whenever the servo is accessed:
with torque on in a position mode (3, 4, 5) the horn follows the goal θg with first-order dynamics
(τ = 50 ms) capped at v_max = no-load speed (or Profile Velocity when non-zero and lower)::

    dθ/dt = clip((θg − θ)/τ, −v_max, v_max)

integrated exactly over the elapsed time (a linear, rate-limited phase, then the exponential);
in velocity mode (1) ω follows Goal Velocity with the same τ. Torque (and so current) is the position
controller's stiffness times the error, kp = stall·(P/128)·(4096/2π)/885 N·m/rad (as `felis.sim.servo`),
clipped at the stall torque. Torque off: the horn stays where it is.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

from felis.drivers.dynamixel.controltable import CENTRE_TICK
from felis.drivers.virtual.memory import (
    BUS_WATCHDOG,
    DRIVE_MODE,
    GOAL_POSITION,
    GOAL_VELOCITY,
    HOMING_OFFSET,
    MOVING,
    MOVING_THRESHOLD,
    OPERATING_MODE,
    POSITION_MODES,
    POSITION_P,
    PRESENT_CURRENT,
    PROFILE_VELOCITY,
    REALTIME_TICK,
    TORQUE_ENABLE,
    WATCHDOG_ERROR,
    WATCHDOG_UNIT_S,
)
from felis.servos import PWM_LIMIT, RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, TICKS_PER_REV, ServoModel

TAU_S = 0.05  # first-order time constant of the standalone horn
CENTRE = CENTRE_TICK

_PRESENT = struct.Struct("<hii")  # present current/load, velocity, position (at `PRESENT_CURRENT`)
I32 = struct.Struct("<i")
U16 = struct.Struct("<H")


@dataclass(frozen=True)
class Mount:
    """How a servo horn drives its joint: θ = direction·q/m_per_rad + zero + offset (rad)."""

    direction: int = 1
    zero: float = 0.0
    m_per_rad: float = 1.0
    offset: float = 0.0

    def horn(self, q: float) -> float:
        """Joint position (rad or m) → horn angle θ (rad around tick 2048)."""
        return self.direction * q / self.m_per_rad + self.zero + self.offset

    def joint(self, theta: float) -> float:
        """Horn angle θ → joint position."""
        return self.direction * (theta - self.zero - self.offset) * self.m_per_rad


class HornModel:
    """The horn of `VirtualServo` (module doc): its state, the present items it shows, its standalone dynamics
    and the Bus Watchdog. The servo's ``__init__`` and ``_boot`` set these attributes."""

    mem: bytearray
    datasheet: ServoModel
    mount: Mount
    clock: Callable[[], float]
    external: bool
    revision: int
    _theta: float
    _omega: float
    _torque: float
    _t: float
    _t0: float
    _last_rx: float
    _kt: float | None
    _current_unit: float | None

    def _cache_settings(self) -> None:
        """Items the dynamics read on every access, decoded once per change (the hot path)."""
        mem = self.mem
        self._s = -1 if mem[DRIVE_MODE] & 1 else 1
        self._homing = I32.unpack_from(mem, HOMING_OFFSET)[0]
        self._moving_threshold = I32.unpack_from(mem, MOVING_THRESHOLD)[0]
        stall = self.datasheet.stall_torque
        self._kp = stall * (U16.unpack_from(mem, POSITION_P)[0] / 128.0) * (TICKS_PER_REV / (2.0 * math.pi)) \
            / PWM_LIMIT


    # -------------------------------------------------------------- horn and frames
    @property
    def angle(self) -> float:
        """Horn angle θ (rad around the centre tick)."""
        self._advance()
        return self._theta

    @angle.setter
    def angle(self, theta: float) -> None:
        self._advance()
        self._theta = float(theta)
        self._omega = self._torque = 0.0
        self._refresh()

    @property
    def q(self) -> float:
        """The horn angle as a joint position, through the mounting."""
        return self.mount.joint(self.angle)

    def goal_angle(self) -> float:
        """Goal Position as a horn angle (rad)."""
        return self._s * (I32.unpack_from(self.mem, GOAL_POSITION)[0] - CENTRE - self._homing) * RAD_PER_TICK

    def profile_speed(self) -> float:
        """Profile Velocity as horn speed (rad/s); 0 = unlimited."""
        return I32.unpack_from(self.mem, PROFILE_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT

    def set_present(self, theta: float, omega: float, torque: float) -> None:
        """Horn state from outside (simulation): angle (rad), speed (rad/s), torque (N·m)."""
        self._theta, self._omega, self._torque = theta, omega, torque
        self._t = self.clock()
        self._refresh()

    def _refresh(self) -> None:
        """Present items from the horn state."""
        mem, s = self.mem, self._s
        pos = CENTRE + s * round(self._theta / RAD_PER_TICK) + self._homing
        vel = s * round(self._omega / RAD_S_PER_VELOCITY_UNIT)
        if self._kt is not None:
            cur = round(s * self._torque / self._kt / self._current_unit)
        else:
            cur = round(s * 1000.0 * self._torque / self.datasheet.stall_torque)
        _PRESENT.pack_into(mem, PRESENT_CURRENT, max(-32768, min(32767, cur)), vel, max(-2**31, min(2**31 - 1, pos)))
        mem[MOVING] = 1 if abs(vel) > self._moving_threshold else 0
        U16.pack_into(mem, REALTIME_TICK, int((self._t - self._t0) * 1000.0) & 0x7FFF)


    # -------------------------------------------------------------- standalone dynamics
    def _advance(self) -> None:
        """Bring the horn to now and refresh the present items (a simulated horn is published instead)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        if not self.external:
            self._integrate()
            self._refresh()


    # -------------------------------------------------------------- Bus Watchdog
    def heard(self) -> None:
        """An instruction packet for this servo (its ID or broadcast) arrived: the Bus Watchdog restarts
        (after a trip that was already due, which a late packet does not undo)."""
        if self.mem[BUS_WATCHDOG]:
            self.check_watchdog()
        self._last_rx = self.clock()

    def check_watchdog(self, now: float | None = None) -> float | None:
        """Trip the Bus Watchdog if it is due (module doc). Returns the time from the last packet to the
        trip when it trips now, else None. A standalone horn is integrated up to the trip instant."""
        wd = self.mem[BUS_WATCHDOG]
        if not 1 <= wd <= 127 or not self.mem[TORQUE_ENABLE]:
            return None
        now = self.clock() if now is None else now
        due = self._last_rx + wd * WATCHDOG_UNIT_S
        if now < due:
            return None
        if not self.external:
            self._integrate(due)  # the horn moved under its last goal until the trip
        mem = self.mem
        pos = CENTRE + self._s * round(self._theta / RAD_PER_TICK) + self._homing
        I32.pack_into(mem, GOAL_POSITION, pos)  # stop: hold where it is
        I32.pack_into(mem, GOAL_VELOCITY, 0)
        if not self.external:
            self._theta = self._s * (pos - CENTRE - self._homing) * RAD_PER_TICK
            self._omega = self._torque = 0.0
        mem[BUS_WATCHDOG] = WATCHDOG_ERROR
        self.revision += 1
        return (due if not self.external else now) - self._last_rx

    @property
    def watchdog_tripped(self) -> bool:
        return self.mem[BUS_WATCHDOG] == WATCHDOG_ERROR


    # -------------------------------------------------------------- standalone dynamics
    def _integrate(self, until: float | None = None) -> None:
        """Standalone dynamics: exact integration over the time elapsed since the last access (or up to
        ``until``)."""
        now = self.clock() if until is None else until
        dt = now - self._t
        self._t = now
        if self.external or dt <= 0.0:
            return
        mem = self.mem
        mode = mem[OPERATING_MODE]
        if not mem[TORQUE_ENABLE] or mode not in POSITION_MODES and mode != 1:
            self._omega = self._torque = 0.0
            return
        vmax = self.datasheet.no_load_speed
        if mode == 1:
            target = self._s * I32.unpack_from(mem, GOAL_VELOCITY)[0] * RAD_S_PER_VELOCITY_UNIT
            self._velocity_step(max(-vmax, min(vmax, target)), dt)
            return
        goal = self.goal_angle()
        if self._theta == goal and not self._omega:
            self._torque = 0.0
            return  # at rest on the goal
        profile = self.profile_speed()
        if 0.0 < profile < vmax:
            vmax = profile
        self._position_step(goal, vmax, dt)

    def _position_step(self, goal: float, vmax: float, dt: float) -> None:
        e = goal - self._theta
        band = vmax * TAU_S  # error below which the first-order law is not rate-limited
        sign = 1.0 if e >= 0 else -1.0
        if abs(e) > band:
            t1 = (abs(e) - band) / vmax
            if dt <= t1:
                e -= sign * vmax * dt
                self._omega = sign * vmax
                self._theta = goal - e
                self._torque = self._stiff_torque(e)
                return
            e, dt = sign * band, dt - t1
        e *= math.exp(-dt / TAU_S)
        if abs(e) < 1e-9:  # arrived (far below a tick): rest exactly on the goal
            e = 0.0
        self._theta = goal - e
        self._omega = e / TAU_S
        self._torque = self._stiff_torque(e)

    def _velocity_step(self, target: float, dt: float) -> None:
        k = math.exp(-dt / TAU_S)
        self._theta += target * dt + (self._omega - target) * TAU_S * (1.0 - k)
        self._omega = target + (self._omega - target) * k
        stall = self.datasheet.stall_torque
        self._torque = stall * (target - self._omega) / max(self.datasheet.no_load_speed, 1e-9)

    def _stiff_torque(self, error: float) -> float:
        stall = self.datasheet.stall_torque
        return max(-stall, min(stall, self._kp * error))
