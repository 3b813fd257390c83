"""The faults a virtual bus injects (`FaultPlan`) and the spec text that names them (`parse_fault_plan`).

Lost replies, corrupted bytes (one random byte XOR-ed with a random non-zero mask), delayed replies,
vanished servos, hardware errors raised at start, a vanished port (now or after N s), and, timed from
when a servo's torque first came on, a brown-out reboot or torque switched off from elsewhere. The bus
draws every random choice from one seeded RNG (`felis.drivers.virtual.server.VirtualBus`), so a run is
reproducible for a given seed and packet sequence. A `FaultPlan` checks itself when built: the one
validator for a fault spec, whether it comes from the CLI, `spawn` or a test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from felis.drivers.dynamixel import protocol as P
from felis.drivers.virtual.memory import hardware_bits
from felis.errors import ParameterError


@dataclass
class FaultPlan:
    """Injected faults (module doc; how the bus applies them: `felis.drivers.virtual.server`). Rates and delay
    may be changed while the bus runs."""

    drop: float = 0.0  # fraction of replies lost
    corrupt: float = 0.0  # fraction of replies with one byte flipped
    delay_ms: float = 0.0  # extra delay before the replies to each request
    remove: tuple[int, ...] = ()  # servo IDs absent from the start
    hwerror: dict[int, int] = field(default_factory=dict)  # ID -> Hardware Error Status bits raised at start
    close_after: float | None = None  # s after start() at which the port vanishes
    seed: int | None = None  # overrides the bus's seed
    reboot: tuple[tuple[int, float], ...] = ()  # (ID, s after its torque first came on): a brown-out reboot
    torque_off: tuple[tuple[int, float], ...] = ()  # (ID, s after torque first came on): switched off elsewhere

    def __post_init__(self):
        for name in ("drop", "corrupt"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise ParameterError(f"faults: {name}={v!r} must be a fraction in 0…1")
        if not (isinstance(self.delay_ms, int | float) and 0.0 <= self.delay_ms <= 10_000):
            raise ParameterError(f"faults: delay_ms={self.delay_ms!r} must be in 0…10000 ms")
        if self.close_after is not None and not (isinstance(self.close_after, int | float) and self.close_after >= 0):
            raise ParameterError(f"faults: close_after={self.close_after!r} must be ≥ 0 s")
        self.remove = tuple(int(i) for i in self.remove)
        self.hwerror = {int(k): hardware_bits(v) for k, v in self.hwerror.items()}
        for name in ("reboot", "torque_off"):
            timed = tuple((int(i), float(t)) for i, t in getattr(self, name))
            for i, t in timed:
                if not (0 <= i <= P.MAX_ID and math.isfinite(t) and t >= 0):
                    raise ParameterError(f"faults: {name}={i}@{t} needs a servo ID and a time ≥ 0 s")
            setattr(self, name, timed)


_FAULT_KEYS = ("drop", "corrupt", "delay_ms", "remove", "hwerror", "close_after", "seed", "reboot", "torque_off")


def parse_fault_plan(spec: str) -> FaultPlan:
    """``"drop=0.01,corrupt=0.001,delay_ms=5,remove=3,hwerror=5:overload,close_after=2.5,seed=0"`` → `FaultPlan`.

    ``remove`` and ``hwerror`` may repeat; several IDs or error names join with ``+``
    (``remove=3+4``, ``hwerror=5:overload+overheating``, ``hwerror=5:0x24``). ``reboot=ID@T`` (the servo
    reboots, as after a brown-out) and ``torque_off=ID@T`` (its torque is switched off, as from another
    program) act T s after torque first came on at that servo; both may repeat. Empty spec: no faults.
    """
    kw: dict[str, object] = {"remove": [], "hwerror": {}, "reboot": [], "torque_off": []}
    for part in (s.strip() for s in spec.split(",")):
        if not part:
            continue
        key, sep, value = (x.strip() for x in part.partition("="))
        if key not in _FAULT_KEYS:
            raise ParameterError(f"fault spec: unknown key {key!r}; known: {', '.join(_FAULT_KEYS)}")
        if not sep or not value:
            raise ParameterError(f"fault spec: {key!r} needs a value ({key}=…)")
        try:
            _parse_fault_value(kw, key, value)
        except ValueError:
            raise ParameterError(f"fault spec: bad value for {key!r}: {value!r}") from None
    for key in ("remove", "reboot", "torque_off"):
        kw[key] = tuple(kw[key])  # type: ignore[arg-type]
    try:
        return FaultPlan(**kw)  # type: ignore[arg-type]
    except ParameterError as e:
        raise ParameterError(f"fault spec: {e}") from None


def _parse_fault_value(kw: dict, key: str, value: str) -> None:
    if key in ("drop", "corrupt", "delay_ms", "close_after"):
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(value)
        kw[key] = v
    elif key == "seed":
        kw[key] = int(value, 0)
    elif key == "remove":
        kw[key].extend(_servo_id(x) for x in value.split("+"))
    elif key in ("reboot", "torque_off"):
        sid, at, t = value.partition("@")
        seconds = float(t)
        if not at or not math.isfinite(seconds) or seconds < 0:
            raise ValueError(value)
        kw[key].append((_servo_id(sid), seconds))
    else:
        sid, colon, bits = value.partition(":")
        if not colon:
            raise ValueError(value)
        dxl_id = _servo_id(sid)
        kw[key][dxl_id] = kw[key].get(dxl_id, 0) | hardware_bits(bits)


def _servo_id(text: str) -> int:
    v = int(text.strip(), 0)
    if not 0 <= v <= P.MAX_ID:
        raise ValueError(text)
    return v

