"""The virtual bus's fail-safe features, as the e-Manual describes them: Indirect Address / Indirect Data,
the Bus Watchdog (item 98), and the timed faults (a servo that reboots, or whose torque is switched off
elsewhere). Reads and writes go through the unmodified SDK on the pty where the wire matters; the
watchdog's timing runs on an injected clock."""

from __future__ import annotations

import time

import numpy as np
import pytest

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.controltable import control_table
from felis.drivers.dynamixel.robot import TICK_ITEMS, DynamixelRobot
from felis.drivers.virtual import VirtualBus, VirtualServo
from felis.errors import ParameterError
from felis.hal import Command
from felis.sim.servo_in_loop import virtual_bus
from felis.spec import load_spec

BAUD = 1_000_000


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _write(servo: VirtualServo, name: str, raw: int) -> int:
    it = servo.table.item(name)
    return servo.write(it.addr, it.encode(raw))


@pytest.fixture
def cat_bus():
    with VirtualBus.for_robot("cat", baud=BAUD) as vb:
        yield vb


# --------------------------------------------------------------------------------- indirect addressing
@pytest.mark.parametrize("model,count", [("XL330-M288-T", 20), ("XL430-W250-T", 28), ("XM430-W350-T", 28)])
def test_indirect_items_per_model(model, count):
    t = control_table(model)
    assert t.indirect == (168, 224, count)
    assert t.item(f"indirect_address_{count}").addr == 168 + 2 * (count - 1)
    assert t.item(f"indirect_data_{count}").addr == 224 + count - 1
    assert t.item("indirect_address_1").default == 224 and t.item("indirect_address_1").lo == 64


def test_the_tick_block_through_indirect_data_equals_the_direct_reads(cat_bus):
    """Torque Enable, Hardware Error Status, Bus Watchdog and the present block, gathered at Indirect
    Data 1 and read in one sync read (plain and fast) through the SDK, byte for byte as read directly."""
    ids = list(range(1, 13))
    cat_bus.servo(4).angle = 0.3
    cat_bus.servo(5).set("torque_enable", 1)
    with DynamixelBus(cat_bus.port, BAUD) as bus:
        for i in ids:
            bus.ping(i)
        want = b"".join(int(a).to_bytes(2, "little") for a in TICK_ITEMS)
        bus.sync_write(168, len(want), {i: want for i in ids})
        for fast in (False, True):
            res = bus.sync_read(ids, 224, len(TICK_ITEMS), fast=fast)
            for i in ids:
                direct = bus.read_raw(i, 64, 1) + bus.read_raw(i, 70, 1) + bus.read_raw(i, 98, 1) + \
                    bus.read_raw(i, 126, 10)
                assert res.data[i] == direct, (fast, i)
        assert res.data[5][0] == 1 and res.data[4][0] == 0


def test_indirect_writes_act_on_the_target_with_its_rules(cat_bus):
    s = cat_bus.servo(1)
    assert _write(s, "indirect_address_1", 65) == 0  # LED
    assert _write(s, "indirect_data_1", 1) == 0 and s.get("led") == 1
    assert _write(s, "indirect_data_1", 2) == P.DATA_RANGE_ERROR and s.get("led") == 1  # LED is 0/1
    for k, a in enumerate(range(116, 120), start=2):  # Goal Position through four entries
        assert _write(s, f"indirect_address_{k}", a) == 0
    assert s.write(225, (2100).to_bytes(4, "little")) == 0 and s.get("goal_position") == 2100
    assert _write(s, "indirect_address_6", 11) == P.DATA_RANGE_ERROR  # EEPROM (Operating Mode): not allowed
    assert s.get("indirect_data_7") == 0  # an entry still at its factory address (itself) reads 0


@pytest.mark.parametrize("seed", range(5))
def test_any_indirect_map_reads_byte_for_byte_as_its_targets(seed):
    """Random maps (runs, gaps, entries left at the data area itself) and reads at any offset and length
    in the Indirect Data area: each byte is its target's, and 0 where the target is the data area."""
    rng = np.random.default_rng(seed)
    s = VirtualServo("XM430-W350-T", 1, BAUD)
    a0, d0, n = s.indirect
    for k in range(n):
        r = rng.random()
        target = d0 + k if r < 0.2 else int(rng.integers(64, 147)) if r < 0.6 else 64 + k  # itself, random, a run
        assert s.write(a0 + 2 * k, target.to_bytes(2, "little")) == 0, target
    _write(s, "goal_position", 1234)
    _write(s, "led", 1)
    targets = [int.from_bytes(s.read_block(a0 + 2 * k, 2)[1], "little") for k in range(n)]
    for _ in range(50):
        start = int(rng.integers(d0, d0 + n))
        length = int(rng.integers(1, d0 + n - start + 1))
        err, data = s.read_block(start, length)
        want = bytes(0 if d0 <= t < d0 + n else s.read_block(t, 1)[1][0]
                     for t in targets[start - d0: start - d0 + length])
        assert err == 0 and data == want, (start, length)


# --------------------------------------------------------------------------------- Bus Watchdog
def test_bus_watchdog_trips_after_its_time_out_and_not_before():
    clock = Clock()
    s = VirtualServo("XL330-M288-T", 1, BAUD, clock=clock)
    assert _write(s, "torque_enable", 1) == 0
    assert _write(s, "bus_watchdog", 5) == 0  # 100 ms
    clock.t += 0.09
    s.heard()  # a packet: the time-out starts again
    clock.t += 0.09
    assert s.get("bus_watchdog") == 5 and not s.watchdog_tripped
    assert _write(s, "goal_position", 2048 + 1000) == 0  # moving towards it
    clock.t += 0.05
    moving = s.get("present_position")
    assert moving > 2048
    clock.t += 0.5  # silent: tripped 0.1 s after the goal write, holding where it was then
    at_trip = s.get("present_position")
    assert s.get("bus_watchdog") == 0xFF and s.watchdog_tripped
    assert s.get("goal_position") == at_trip and 2048 < at_trip < 2048 + 1000
    clock.t += 0.5
    assert s.get("present_position") == at_trip  # stopped
    assert s.get("torque_enable") == 1  # holding, not limp
    assert _write(s, "goal_position", 2048) == P.DATA_RANGE_ERROR  # goals refused while tripped
    assert _write(s, "goal_velocity", 0) == P.DATA_RANGE_ERROR
    assert _write(s, "bus_watchdog", 5) == P.DATA_RANGE_ERROR  # clear with 0 first
    assert _write(s, "bus_watchdog", 0) == 0 and not s.watchdog_tripped
    assert _write(s, "goal_position", 2048) == 0


def test_bus_watchdog_needs_torque_on():
    clock = Clock()
    s = VirtualServo("XL330-M288-T", 1, BAUD, clock=clock)
    assert _write(s, "bus_watchdog", 5) == 0
    clock.t += 1.0
    assert s.get("bus_watchdog") == 5


def test_a_reboot_clears_the_watchdog_and_the_indirect_map():
    s = VirtualServo("XL330-M288-T", 1, BAUD, clock=Clock())
    _write(s, "indirect_address_1", 64)
    _write(s, "torque_enable", 1)
    _write(s, "bus_watchdog", 5)
    s.handle(P.instruction(1, P.REBOOT))
    assert s.get("bus_watchdog") == 0 and s.get("indirect_address_1") == 224 and s.get("torque_enable") == 0


def test_a_silent_host_stops_the_simulated_robot_within_the_watchdog_time():
    """Servo-in-the-loop: a client arms the cat and commands a move, then goes silent; every servo's Bus
    Watchdog trips within 100 ms (+ one simulation iteration) of its last packet and the joints stop."""
    spec = load_spec("cat")
    with virtual_bus(spec, baud=BAUD, sim=True) as vb:
        with DynamixelRobot(spec, vb.port, BAUD, bus_watchdog_s=0.1) as robot:
            robot.arm()
            q = robot.read().q
            target = spec.pose("stand")
            robot.write(Command(q=q + 0.02 * (target - q)))
            for k in range(1, 20):  # a moving command stream
                time.sleep(0.01)
                robot.read()
                robot.write(Command(q=q + 0.05 * k * (target - q)))
            time.sleep(0.5)  # the host goes silent
            with vb.lock:
                trips = list(vb.stats.watchdog_trips)
                p0 = [s.get("present_position") for s in vb.servos]
            time.sleep(0.3)
            with vb.lock:
                p1 = [s.get("present_position") for s in vb.servos]
            assert sorted(i for i, _ in trips) == list(range(1, 13))
            assert all(0.1 <= dt <= 0.1 + 0.03 for _, dt in trips), trips
            assert np.max(np.abs(np.array(p1) - np.array(p0))) <= 2  # stopped (a tick of settling at most)
            assert "bus watchdog tripped: ID" in vb.stats.summary()


# --------------------------------------------------------------------------------- timed faults
def test_timed_faults_act_after_torque_first_came_on():
    with VirtualBus.for_robot("cat", baud=BAUD, faults="torque_off=2@0.2,reboot=4@0.2") as vb:
        with vb.lock:
            for i in (2, 4):
                vb.servo(i).set("torque_enable", 1)
        time.sleep(0.05)
        assert vb.servo(2).get("torque_enable") == 1
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(vb.stats.timed_faults) < 2:
            time.sleep(0.02)
        assert sorted(vb.stats.timed_faults) == [("reboot", 4), ("torque_off", 2)]
        assert vb.servo(2).get("torque_enable") == 0 and vb.servo(4).get("torque_enable") == 0
        assert vb.servo(4).get("indirect_address_1") == 224  # rebooted: RAM at factory values


def test_a_timed_fault_for_an_unknown_servo_is_one_line():
    with pytest.raises(ParameterError, match="no servo with ID 99"):
        VirtualBus.for_robot("cat", baud=BAUD, faults="reboot=99@1").start()
