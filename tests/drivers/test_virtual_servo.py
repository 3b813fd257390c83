"""One emulated servo on its own, no pty (`felis.drivers.virtual.servo`, `.horn`, `.instructions`, `.dispatch`).

Checked: the horn's standalone dynamics (rate-limited then first-order, Profile Velocity, torque off holds),
the position frame (Drive Mode, Homing Offset), the XL430's Present Load; hypothesis fuzzing of the packet
parser and of the dispatcher (never an exception, replies always valid packets).
"""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from felis.drivers.dynamixel import protocol as P
from felis.drivers.virtual import VirtualServo, dispatch
from felis.servos import RAD_PER_TICK, RAD_S_PER_VELOCITY_UNIT, SERVOS

BAUD = 1_000_000
XL330, XM430, XL430 = "XL330-M288-T", "XM430-W350-T", "XL430-W250-T"
TORQUE, PROFILE_VELOCITY, GOAL_POSITION = 64, 112, 116


# ------------------------------------------------------------------------------------------- dynamics
class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_standalone_dynamics_follow_the_goal():
    """The firmware's controller on the bare horn (`felis.drivers.virtual.horn`; its step responses, profiles and
    modes are tested in tests/sim/test_servo_controller.py)."""
    clock = FakeClock()
    s = VirtualServo(XL330, 1, BAUD, clock=clock)
    vmax = SERVOS[XL330].no_load_speed
    goal = 2048 + 1024  # +90°
    assert s.write(GOAL_POSITION, goal.to_bytes(4, "little")) == 0
    clock.t = 1.0
    assert s.get("present_position") == 2048  # torque off: the horn stays
    assert s.write(TORQUE, b"\x01") == 0
    clock.t = 1.002
    assert 0 < s.get("present_current") <= 1470  # saturated at the stall current at the start
    clock.t = 1.1  # saturated: near the no-load speed
    assert s.get("present_velocity") == pytest.approx(vmax / RAD_S_PER_VELOCITY_UNIT, rel=0.05)
    assert s.get("moving") == 1
    clock.t = 3.0
    assert s.get("present_position") == goal and s.get("moving") == 0
    assert s.get("present_velocity") == 0 and s.get("present_current") == 0
    # Profile Velocity limits the speed (a rectangular profile; the P-only servo lags it by v·b/kp)
    assert s.write(PROFILE_VELOCITY, (100).to_bytes(4, "little")) == 0
    assert s.write(GOAL_POSITION, (2048).to_bytes(4, "little")) == 0
    clock.t = 3.3
    v = 100 * RAD_S_PER_VELOCITY_UNIT
    lag = v * (SERVOS[XL330].stall_torque / vmax) / s.firmware_controller().kp
    assert s.angle == pytest.approx(math.pi / 2 - v * 0.3 + lag, abs=0.01)
    s.write(TORQUE, b"\x00")
    held = s.angle
    clock.t += 1.0
    assert s.angle == held


def test_a_hand_moves_the_horn_only_while_torque_is_off():
    """`hold_by_hand`: the pose a hand gives a torque-off joint shows as Present Position (and its speed as Present
    Velocity); with torque on the servo holds its goal; letting go leaves the horn where the hand left it."""
    from felis.drivers.virtual.horn import Mount

    clock = FakeClock()
    s = VirtualServo(XL330, 1, BAUD, clock=clock, mount=Mount(direction=-1))
    s.hold_by_hand(0.5)
    assert s.q == pytest.approx(0.5, abs=RAD_PER_TICK) and s.get("present_position") == 2048 - round(0.5 / RAD_PER_TICK)
    s.hold_by_hand(lambda t: 0.2 * t)  # 0.2 rad/s of joint
    clock.t = 1.0
    assert s.q == pytest.approx(0.2, abs=RAD_PER_TICK)
    assert s.get("present_velocity") == round(-0.2 / RAD_S_PER_VELOCITY_UNIT)
    assert s.write(GOAL_POSITION, s.get("present_position").to_bytes(4, "little")) == 0
    assert s.write(TORQUE, b"\x01") == 0
    clock.t = 3.0
    assert s.q == pytest.approx(0.2, abs=2 * RAD_PER_TICK)  # held at its goal, the hand ignored
    assert s.write(TORQUE, b"\x00") == 0
    clock.t = 3.5
    assert s.q == pytest.approx(0.7, abs=RAD_PER_TICK)  # the hand again
    s.hold_by_hand(None)
    clock.t = 5.0
    assert s.q == pytest.approx(0.7, abs=RAD_PER_TICK)
    with pytest.raises(Exception, match="not finite"):
        s.hold_by_hand(math.nan)


def test_position_frame_drive_mode_and_homing_offset():
    s = VirtualServo(XM430, 1, BAUD, clock=FakeClock())
    s.angle = 0.5
    ticks = round(0.5 / RAD_PER_TICK)
    assert s.get("present_position") == 2048 + ticks
    s.set("drive_mode", 1)
    s.set("homing_offset", 100)
    assert s.get("present_position") == 2048 - ticks + 100
    s.set("goal_position", 2048 - ticks + 100)
    assert s.goal_angle() == pytest.approx(0.5, abs=RAD_PER_TICK)


def test_xl430_reports_load():
    clock = FakeClock()
    s = VirtualServo(XL430, 1, BAUD, clock=clock)
    s.write(GOAL_POSITION, (3000).to_bytes(4, "little"))
    s.write(TORQUE, b"\x01")
    clock.t = 0.001
    assert 900 <= s.get("present_load") <= 1000  # saturated: ≈ 100 % of stall, less the back-EMF once moving


# ------------------------------------------------------------------------------------------- fuzzing
def _check_reply(reply: bytes, inst: int) -> None:
    reader = P.PacketReader()
    packets = reader.feed(reply)
    if inst in (P.FAST_SYNC_READ, P.FAST_BULK_READ) and not packets:
        # a fast read missing a listed servo: a packet short of its announced length (module doc)
        assert reply[:5] == P.HEADER + bytes((P.BROADCAST_ID,)) and len(reply) < 7 + (reply[5] | reply[6] << 8)
        return
    assert len(packets) == 1 and reader.pending == 0, reply
    pkt = packets[0]
    assert pkt.crc_ok and pkt.inst == P.STATUS and pkt.raw == reply


_INSTS = st.sampled_from([*P.INSTRUCTIONS, 0x00, 0x07, 0x55, 0xFF])
_IDS = st.sampled_from([1, 2, 3, 4, P.BROADCAST_ID, 0])


def _params():
    addr_len = st.tuples(st.integers(0, 200), st.integers(0, 160)).map(
        lambda t: bytes([t[0] & 0xFF, t[0] >> 8, t[1] & 0xFF, t[1] >> 8]))
    return st.one_of(st.binary(max_size=40),
                     st.tuples(addr_len, st.lists(st.sampled_from([1, 2, 3, 9]), max_size=4)).map(
                         lambda t: t[0] + bytes(t[1])),
                     st.tuples(st.integers(0, 150), st.binary(min_size=1, max_size=12)).map(
                         lambda t: bytes([t[0], 0]) + t[1]))


@st.composite
def _instruction_streams(draw):
    packets = []
    for _ in range(draw(st.integers(1, 4))):
        pkt = bytearray(P.instruction(draw(_IDS), draw(_INSTS), draw(_params())))
        for _ in range(draw(st.integers(0, 2))):  # corruptions
            if draw(st.booleans()):
                i = draw(st.integers(0, len(pkt) - 1))
                pkt[i] ^= draw(st.integers(1, 255))
        packets.append(bytes(pkt))
    return packets


def _fuzz_dispatch(packets: list[bytes]) -> None:
    servos = [VirtualServo(XL330, 1, BAUD, clock=FakeClock()), VirtualServo(XM430, 2, BAUD, clock=FakeClock()),
              VirtualServo(XL430, 3, BAUD, clock=FakeClock(), firmware=40)]
    reader = P.PacketReader()
    for raw_pkt in packets:
        for pkt in reader.feed(raw_pkt):
            for _, reply in dispatch(servos, pkt):
                _check_reply(reply, pkt.inst)


def _fuzz_reader(chunks: list[bytes]) -> None:
    reader = P.PacketReader()
    for c in chunks:
        for pkt in reader.feed(c):
            assert pkt.raw[:4] == P.HEADER and len(pkt.raw) == 7 + (pkt.raw[5] | pkt.raw[6] << 8)


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    cuts = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]


@st.composite
def _valid_stream_with_noise(draw):
    packets = [P.instruction(draw(st.integers(0, 0xFE)), draw(_INSTS), draw(st.binary(max_size=30)))
               for _ in range(draw(st.integers(1, 5)))]
    noise = [draw(st.binary(max_size=8).map(lambda b: bytes(x for x in b if x != 0xFF))) for _ in packets]
    stream = b"".join(n + p for n, p in zip(noise, packets, strict=True))
    return packets, _split(stream, draw(st.lists(st.integers(0, 400), max_size=6)))


def _check_stream(case) -> None:
    packets, chunks = case
    reader = P.PacketReader()
    got = [p.raw for c in chunks for p in reader.feed(c)]
    assert got == packets and reader.pending == 0


_FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_SLOW = settings(max_examples=5000, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_FAST
@given(_instruction_streams())
def test_fuzz_dispatcher(packets):
    _fuzz_dispatch(packets)


@_FAST
@given(st.lists(st.binary(max_size=64), max_size=8))
def test_fuzz_packet_reader_never_raises(chunks):
    _fuzz_reader(chunks)


@_FAST
@given(_valid_stream_with_noise())
def test_fuzz_packet_reader_recovers_packets_from_noise(case):
    _check_stream(case)


@pytest.mark.slow
@_SLOW
@given(_instruction_streams())
def test_fuzz_dispatcher_long(packets):
    _fuzz_dispatch(packets)


@pytest.mark.slow
@_SLOW
@given(st.lists(st.binary(max_size=64), max_size=8))
def test_fuzz_packet_reader_long(chunks):
    _fuzz_reader(chunks)


@pytest.mark.slow
@_SLOW
@given(_valid_stream_with_noise())
def test_fuzz_packet_reader_recovers_long(case):
    _check_stream(case)
