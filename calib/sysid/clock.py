"""The emulator's clock for system identification: `StepClock`, a simulated clock a virtual bus's servos run on.

A virtual servo's standalone dynamics are stepped lazily from its ``clock`` whenever a packet reaches it
(`felis.drivers.virtual.horn`). On the wall clock, when a goal takes effect depends on when the bus's server
thread gets to the packet, which the host cannot observe: on a loaded machine that timing jitter ends up in
the recording. On a `StepClock` time stands still between the recorder's ticks: every packet of tick k is
handled at exactly t_k, the goal written at t_k acts from t_k, the state read at t_k is the state at t_k, and
`felis.calib.sysid.record` (``clock=``) advances the clock by 1/rate after each tick. The recording is then a
deterministic function of the packets, whatever the load, and its times are the emulator's own.
"""

from __future__ import annotations


class StepClock:
    """A clock that moves only when told: ``clock()`` is the time (s), ``advance(dt)`` moves it on.

    Time is kept as whole microseconds so that k steps of 1/rate land exactly on the servos' 1 ms physics grid.
    """

    def __init__(self, start: float = 0.0):
        self._us = round(start * 1e6)

    def __call__(self) -> float:
        return self._us * 1e-6

    def advance(self, dt: float) -> None:
        if not dt >= 0:
            raise ValueError(f"a clock only moves forward, got dt = {dt}")
        self._us += round(dt * 1e6)

    def drive(self, servos) -> StepClock:
        """Run ``servos`` (virtual servos, e.g. ``bus.servos``) on this clock from now on; returns the clock."""
        for s in servos:
            s.use_clock(self)
        return self
