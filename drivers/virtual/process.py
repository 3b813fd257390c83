"""The virtual bus in a child process: `spawn` / `VirtualBusProcess` in the parent, `main` / `serve` in the child.

A client and the bus then do not share a GIL (benchmarks, demos, the hardware code path under test).
The parent checks what it can (the fault spec, the IMU mount) and starts ``python -m ENTRY OPTIONS_JSON``:
ENTRY is ``felis.drivers.virtual`` (this module's `main`, standalone servos) or, when the servos are backed
by the simulation or a simulation option is given, ``felis.sim.servo_in_loop`` (whose own entry builds the
MuJoCo backend and then runs this module's `main`): the drivers name the simulation's entry as text and
never import it. The child builds the bus from the JSON options and prints, each line flushed::

    port: <device path>
    imu: <device path>            (when the robot has an IMU and the simulation backs it)
    <one summary line>

then serves until SIGINT, SIGTERM or SIGHUP, stops cleanly and prints its counters to stderr. Options it
refuses (a `felis.errors.FelisError`) are one ``error: <message>`` line on stderr and exit code 1; a
ParameterError is also printed as ``error: ParameterError: <message>`` on stdout, and the parent raises it
as the same ParameterError (e.g. a drop the simulation checks); any other failure is a CommError.
"""

from __future__ import annotations

import collections
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence

from felis.drivers.virtual.faultplan import parse_fault_plan
from felis.drivers.virtual.imu import check_imu_mount
from felis.drivers.virtual.server import VirtualBus
from felis.errors import CommError, FelisError, ParameterError
from felis.rotations import ypr_from_quat

ENTRY = "felis.drivers.virtual"  # `python -m` this package: `main` with standalone servos
SIM_ENTRY = "felis.sim.servo_in_loop"  # the simulation's entry: builds the MuJoCo backend, then runs `main`
SWITCH_INTERVAL_S = 0.0005  # the server thread shares the GIL with a simulation and an IMU thread


# ----------------------------------------------------------------------------------------- the parent
def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the parent dies, even by SIGKILL (Linux ``PR_SET_PDEATHSIG``),
    so a killed `felis run --port virtual` leaves no virtual bus behind. Elsewhere a no-op."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


class VirtualBusProcess:
    """A virtual bus in a child process: ``python -m ENTRY OPTIONS_JSON`` (module doc); see `spawn`.

    ``port``, ``imu_port`` and ``summary`` are the lines the child printed; `stop` ends it.
    """

    def __init__(self, entry: str, options: Mapping[str, object], timeout: float = 20.0):
        env = dict(os.environ)
        env.setdefault("MUJOCO_GL", "egl")
        self.proc = subprocess.Popen([sys.executable, "-m", entry, json.dumps(dict(options))],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, preexec_fn=_die_with_parent)
        self._stderr: collections.deque[str] = collections.deque(maxlen=200)
        self._lines: collections.deque[str] = collections.deque()
        self._got_line = threading.Condition()
        self._eof = False
        self._readers = [threading.Thread(target=self._drain_stdout, daemon=True),
                         threading.Thread(target=self._drain_stderr, daemon=True)]
        for t in self._readers:
            t.start()
        self.port = ""
        self.imu_port: str | None = None
        self.summary = ""
        try:
            self._handshake(timeout)
        except BaseException:
            self._kill()
            raise

    def _drain_stdout(self) -> None:
        for line in self.proc.stdout:
            with self._got_line:
                self._lines.append(line.rstrip("\n"))
                self._got_line.notify_all()
        with self._got_line:
            self._eof = True
            self._got_line.notify_all()

    def _drain_stderr(self) -> None:
        for line in self.proc.stderr:
            self._stderr.append(line.rstrip("\n"))

    def _next_line(self, deadline: float) -> str | None:
        with self._got_line:
            while not self._lines and not self._eof:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._got_line.wait(left)
            return self._lines.popleft() if self._lines else None

    def _handshake(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            line = self._next_line(deadline)
            if line is None:
                self._fail("exited" if self._eof else f"printed no port within {timeout:g} s")
            if line.startswith("error: ParameterError: "):  # the child refused its options: the same error here
                raise ParameterError(line[len("error: ParameterError: "):])
            if line.startswith("port: "):
                self.port = line[6:].strip()
            elif line.startswith("imu: "):
                self.imu_port = line[5:].strip()
            elif self.port:
                self.summary = line
                return

    def _fail(self, what: str) -> None:
        self._kill()
        for t in self._readers:
            t.join(timeout=1.0)
        tail = " | ".join(list(self._stderr)[-5:]) or "(no stderr)"
        raise CommError(f"virtual bus process {what} (exit code {self.proc.returncode}); stderr: {tail}")

    def _kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()

    @property
    def stderr(self) -> str:
        """What the child wrote to stderr so far (its statistics after `stop`)."""
        return "\n".join(self._stderr)

    def stop(self) -> int:
        """SIGTERM, wait up to 5 s, then SIGKILL; returns the exit code (idempotent)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._kill()
        for t in self._readers:
            t.join(timeout=2.0)
        return self.proc.returncode

    def __enter__(self) -> VirtualBusProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def spawn(robot: str, *, sim: bool = False, baud: int = 1_000_000, wire_time: bool = False,
          faults: str | None = None, seed: int = 0, timeout: float = 20.0,
          servo_params: str | os.PathLike | None = None, fixed_base: bool = False,
          imu_mount: Sequence[float] | None = None, imu_drift: Sequence[float] | None = None,
          drop: Sequence[float] | None = None) -> VirtualBusProcess:
    """Run a virtual bus for ``robot`` in a child process; raises CommError if it does not come up.

    ``servo_params`` (a servo parameter file, `felis.sim.servo_file`) and ``fixed_base`` apply to the
    simulation (``sim=True``); so do ``imu_mount`` (unit quaternion w, x, y, z), ``imu_drift`` (rad/s) and
    ``drop`` (height m, roll°, pitch°, yaw°: held in the air until torque first comes on), as in
    `felis.sim.servo_in_loop.virtual_bus`. The fault spec and the IMU mount are checked here; what only the
    simulation can check (a drop, the options that need it) is checked by the child, whose ParameterError is
    raised here the same.
    """
    if faults:
        parse_fault_plan(faults)  # fail here, with the parser's message, rather than in the child
    check_imu_mount(imu_mount, imu_drift)
    options: dict[str, object] = {"robot": str(robot), "baud": baud, "wire_time": wire_time, "faults": faults,
                                  "seed": seed}
    simulated = sim or servo_params is not None or fixed_base or imu_mount is not None or imu_drift is not None \
        or drop is not None
    if simulated:
        options.update(sim=sim, servo_params=None if servo_params is None else os.fspath(servo_params),
                       fixed_base=fixed_base, imu_mount=_floats(imu_mount), imu_drift=_floats(imu_drift),
                       drop=_floats(drop))
    return VirtualBusProcess(SIM_ENTRY if simulated else ENTRY, options, timeout=timeout)


def _floats(values: Sequence[float] | None) -> list[float] | str | None:
    """Numbers for the JSON options; what is not a sequence of numbers goes as its repr, for the child's check
    to name."""
    if values is None:
        return None
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        return repr(values)


# ----------------------------------------------------------------------------------------- the child
def main(argv: Sequence[str] | None = None,
         build: Callable[[Mapping[str, object]], VirtualBus] | None = None) -> int:
    """The child: build the bus from the JSON options (``argv[0]``; `bus_from_options` unless ``build`` is
    given), print the port lines and serve (module doc). Returns the exit code."""
    argv = sys.argv[1:] if argv is None else argv
    options = json.loads(argv[0])
    try:
        bus = (build or bus_from_options)(options)
    except FelisError as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        print(f"error: {type(e).__name__}: {e}", flush=True)
        return 1
    return serve(bus, summary(bus, options))


def bus_from_options(options: Mapping[str, object]) -> VirtualBus:
    """A standalone bus (no simulation) from `spawn`'s JSON options."""
    return VirtualBus.for_robot(options["robot"], baud=options["baud"], wire_time=options["wire_time"],
                                faults=options["faults"] or None, seed=options["seed"])


def serve(bus: VirtualBus, summary_line: str) -> int:
    """Start ``bus``, print ``port:`` (and ``imu:``) and the summary line, serve until SIGINT, SIGTERM or SIGHUP,
    stop, print the counters to stderr; returns 0.

    Python's thread switch interval is lowered to 0.5 ms: the server thread shares the GIL with the
    simulation and IMU threads, and a reply must not wait the default 5 ms for it.
    """
    # The handler only appends to a list: an Event.set() there would take the lock that the main thread's
    # own Event.wait() may hold when the signal lands, and a second signal would then deadlock the process.
    stop: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: stop.append(signum))
                for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        bus.start()
        print(f"port: {bus.port}", flush=True)
        if bus.imu_port:
            print(f"imu: {bus.imu_port}", flush=True)
        print(summary_line, flush=True)
        while not stop:
            time.sleep(0.05)
    finally:
        bus.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        print(f"virtual bus stopped: {bus.stats.summary()}", file=sys.stderr, flush=True)
    return 0


def summary(bus: VirtualBus, options: Mapping[str, object], *, imu_mount_text: str | None = None,
            imu_drift_text: str | None = None) -> str:
    """One line: robot, servos, baud, backing, timing, faults (as ``felis virtual-bus`` prints it).

    ``imu_mount_text`` (roll,pitch,yaw degrees) and ``imu_drift_text`` (rad/s), when given, are printed as
    written instead of the numbers in ``options``: ``felis virtual-bus`` echoes its arguments.
    """
    servos = bus.servos
    models = sorted({s.model for s in servos})
    ids = sorted(s.id for s in servos)
    id_text = f"{ids[0]}…{ids[-1]}" if ids == list(range(ids[0], ids[-1] + 1)) else ", ".join(map(str, ids))
    backing = "backed by MuJoCo" if options.get("sim") else "standalone dynamics"
    if options.get("fixed_base"):
        backing += " (fixed base)"
    if options.get("servo_params"):
        backing += f" with servo parameters from {options['servo_params']}"
    if options.get("imu_mount") is not None:
        if imu_mount_text is None:
            yaw, pitch, roll = ypr_from_quat(options["imu_mount"])
            imu_mount_text = ",".join(f"{math.degrees(a):.12g}" for a in (roll, pitch, yaw))
        backing += f", IMU mounted at roll,pitch,yaw {imu_mount_text}°"
    if options.get("imu_drift") is not None:
        if imu_drift_text is None:
            imu_drift_text = ",".join(repr(float(v)) for v in options["imu_drift"])
        backing += f", IMU drifting {imu_drift_text} rad/s"
    drop = options.get("drop")
    if drop is not None:
        backing += (f", held {drop[0]:g} m up at roll {drop[1]:g}° pitch {drop[2]:g}° yaw {drop[3]:g}° "
                    "until torque comes on")
    timing = "wire time modelled" if options.get("wire_time") else "replies at once"
    faults = f"faults {options['faults']}" if options.get("faults") else "no faults"
    return (f"virtual bus: {bus.spec.name}, {len(servos)} × {'/'.join(models)} (IDs {id_text}) at {options['baud']} "
            f"bps, {backing}, {timing}, {faults}; stop with Ctrl-C or SIGTERM")
