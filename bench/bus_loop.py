"""Benchmark: the cat's 12-servo bus cycle (one sync read plus one sync write) through felis against the
bare SDK, over the virtual bus's pseudo-terminal. felis reads 13 bytes per servo each tick (Torque Enable,
Hardware Error Status, Bus Watchdog and present current, velocity, position, gathered by Indirect
Addressing); the bare loop reads the 10 bytes of present current, velocity, position, and, as a second
anchor, the same 13-byte block.

The virtual bus runs in its own process (``felis virtual-bus``), so client and servos do not share
a GIL, as with real hardware. Three parts:

(a) wire-time modelling off: cycles/s of ``DynamixelRobot.read() + write()`` against the loop a
    ``dynamixel-sdk`` user writes by hand (``GroupSyncRead`` at 126×10 with 36 ``getData`` calls,
    ``GroupSyncWrite`` at 116×4 with ``changeParam``, torque on as felis's loop has it, so that both loops
    pay for the emulated servos' dynamics, the firmware controller on a one-joint MuJoCo model) in the same
    run; blocks interleaved, ratio =
    median of per-pair ratios. felis is measured with its default (Fast Sync Read) and with plain
    sync read. Goal ≥ 0.8.
(b) wire-time modelling at 4 Mbps, Return Delay 0: felis's achieved rate against the wire ceiling
    of the bytes it puts on the bus per cycle, its 13-byte block included (10 bits per byte;
    ``shared/reference/dynamixel.md``).
    Goal ≥ 0.5.
(c) 1 % of replies dropped: 10 000 cycles, counting crashes (any exception) and stale ticks.

    python bench/bus_loop.py [--seconds S] [--pairs N] [--cycles C] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import dynamixel_sdk as sdk

from felis.drivers.dynamixel.controltable import control_table
from felis.drivers.dynamixel.robot import TICK_ITEMS, DynamixelRobot
from felis.drivers.virtual import spawn
from felis.errors import CommError
from felis.hal import Command
from felis.spec import load_spec

BAUD = 4_000_000


def bare_sdk(port_name: str, ids: list[int], seconds: float, indirect: tuple[int, int, int] | None = None) -> float:
    """Cycles/s of the hand-written SDK loop. ``indirect``: the same 13-byte block felis reads each tick
    (Torque Enable, Hardware Error Status, Bus Watchdog, present current/velocity/position through
    Indirect Addressing; the map is written first), parsed with getData as a user would: ``indirect`` is
    the servo model's (Indirect Address 1, Indirect Data 1, count), `ControlTable.indirect`."""
    port = sdk.PortHandler(port_name)
    port.openPort()
    port.setBaudRate(BAUD)
    ph = sdk.PacketHandler(2.0)
    if indirect:
        amap = sdk.GroupSyncWrite(port, ph, indirect[0], 2 * len(TICK_ITEMS))
        for i in ids:
            amap.addParam(i, [b for a in TICK_ITEMS for b in (a & 0xFF, a >> 8)])
        amap.txPacket()
        base, size = indirect[1], len(TICK_ITEMS)
    else:
        base, size = 126, 10
    cur = base + 3 if indirect else base  # present current, then velocity (+2) and position (+6)
    reader = sdk.GroupSyncRead(port, ph, base, size)
    writer = sdk.GroupSyncWrite(port, ph, 116, 4)
    for i in ids:
        reader.addParam(i)
        writer.addParam(i, [0, 8, 0, 0])
    for i in ids:  # powered, as felis's loop drives them: the emulated servos then move in both loops
        ph.write1ByteTxRx(port, i, 64, 1)
    n = 0
    t0 = time.perf_counter()
    try:
        while time.perf_counter() - t0 < seconds:
            if reader.txRxPacket() != sdk.COMM_SUCCESS:
                continue
            goal = []
            for i in ids:
                if indirect:
                    reader.getData(i, base, 1)
                    reader.getData(i, base + 1, 1)
                    reader.getData(i, base + 2, 1)
                reader.getData(i, cur, 2)
                reader.getData(i, cur + 2, 4)
                goal.append(reader.getData(i, cur + 6, 4))
            for i, g in zip(ids, goal, strict=True):
                writer.changeParam(i, [g & 0xFF, (g >> 8) & 0xFF, (g >> 16) & 0xFF, (g >> 24) & 0xFF])
            writer.txPacket()
            n += 1
    finally:
        rate = n / (time.perf_counter() - t0)
        for i in ids:
            ph.write1ByteTxRx(port, i, 64, 0)
        port.closePort()
    return rate


def felis_cycles(robot: DynamixelRobot, seconds: float | None = None, cycles: int | None = None) -> dict:
    """read()+write() cycles holding the present position; returns rate, stale ticks and crashes."""
    n = stale = failed = crashes = 0
    t0 = time.perf_counter()
    state = robot.read()
    while (seconds is None or time.perf_counter() - t0 < seconds) and (cycles is None or n < cycles):
        try:
            state = robot.read()
            if state.faults.stale is not None and state.faults.stale.any():
                stale += 1
        except CommError:
            failed += 1
        except Exception:  # a crash: the benchmark counts it rather than dying
            crashes += 1
        try:
            robot.write(Command(q=state.q))
        except Exception:
            crashes += 1
        n += 1
    dt = time.perf_counter() - t0
    return {"rate_hz": n / dt, "cycles": n, "stale_ticks": stale, "failed_reads": failed, "crashes": crashes}


def ceiling_hz(n: int, fast: bool, block: int = 10, baud: int = BAUD) -> tuple[float, int]:
    """The wire's cycle rate for a sync read of ``block`` bytes per servo plus a 4-byte sync write."""
    read_req = 14 + n
    replies = 8 + n * (block + 4) if fast else n * (11 + block)
    write = 14 + n * (1 + 4)  # goals only (no velocity limits in these commands): 4 bytes per servo
    total = read_req + replies + write
    return baud / (10.0 * total), total


def part_a(spec, seconds: float, pairs: int) -> dict:
    ids = [j.servo_id for j in spec.joints]
    out: dict = {}
    with spawn(spec.name, baud=BAUD) as vb:
        for label, fast in (("fast_sync_read", True), ("sync_read", False)):
            ratios, ratios13, bare_rates, bare13_rates, felis_rates = [], [], [], [], []
            for _ in range(pairs):
                b = bare_sdk(vb.port, ids, seconds)
                with DynamixelRobot(spec, vb.port, BAUD, fast_sync_read=fast) as robot:
                    robot.arm()
                    f = felis_cycles(robot, seconds)["rate_hz"]
                b13 = bare_sdk(vb.port, ids, seconds, indirect=control_table(spec.joints[0].servo).indirect)
                bare_rates.append(b)
                bare13_rates.append(b13)
                felis_rates.append(f)
                ratios.append(f / b)
                ratios13.append(f / b13)
            out[label] = {"ratio": statistics.median(ratios), "felis_hz": statistics.median(felis_rates),
                          "bare_sdk_hz": statistics.median(bare_rates),
                          "ratio_same_block": statistics.median(ratios13),
                          "bare_sdk_same_block_hz": statistics.median(bare13_rates)}
    return out


def part_b(spec, seconds: float) -> dict:
    out = {}
    with spawn(spec.name, baud=BAUD, wire_time=True) as vb:
        for label, fast in (("fast_sync_read", True), ("sync_read", False)):
            with DynamixelRobot(spec, vb.port, BAUD, fast_sync_read=fast) as robot:
                robot.arm()
                r = felis_cycles(robot, seconds)
                block = robot.tick_block_bytes
            ceil, nbytes = ceiling_hz(spec.n, fast, block)
            out[label] = {"rate_hz": r["rate_hz"], "ceiling_hz": ceil, "bytes_per_cycle": nbytes,
                          "ratio": r["rate_hz"] / ceil}
    return out


def part_c(spec, cycles: int) -> dict:
    with spawn(spec.name, baud=BAUD, faults="drop=0.01,seed=1") as vb:
        with DynamixelRobot(spec, vb.port, BAUD) as robot:
            robot.arm()
            r = felis_cycles(robot, cycles=cycles)
            r["retries"] = int(sum(s.retries for s in robot.bus.stats.values()))
            r["timeouts"] = int(sum(s.timeouts for s in robot.bus.stats.values()))
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.5, help="seconds per measurement block")
    ap.add_argument("--pairs", type=int, default=3, help="interleaved bare/felis pairs in (a)")
    ap.add_argument("--cycles", type=int, default=10_000, help="cycles in (c)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    spec = load_spec("cat")
    res = {"servos": spec.n, "baud": BAUD,
           "a_no_wire_time": part_a(spec, args.seconds, args.pairs),
           "b_wire_time_4mbps": part_b(spec, args.seconds * 2),
           "c_one_percent_dropped": part_c(spec, args.cycles)}
    if args.json:
        print(json.dumps(res, indent=2))
        return
    a, b, c = res["a_no_wire_time"], res["b_wire_time_4mbps"], res["c_one_percent_dropped"]
    print(f"bus loop, {spec.n} servos, sync read 126×10 + sync write per cycle, pty, bus in its own process")
    for k, v in a.items():
        print(f"(a) no wire time, felis {k}: {v['felis_hz']:.0f} cycles/s vs bare SDK {v['bare_sdk_hz']:.0f} "
              f"cycles/s: ratio {v['ratio']:.2f} (goal ≥ 0.8); vs bare SDK reading felis's 13-byte block "
              f"{v['bare_sdk_same_block_hz']:.0f} cycles/s: ratio {v['ratio_same_block']:.2f}")
    for k, v in b.items():
        print(f"(b) wire time at 4 Mbps, RDT 0, felis {k}: {v['rate_hz']:.0f} Hz vs ceiling {v['ceiling_hz']:.0f} Hz "
              f"({v['bytes_per_cycle']} bytes/cycle): ratio {v['ratio']:.2f} (goal ≥ 0.5)")
    print(f"(c) 1% dropped replies: {c['cycles']} cycles, {c['crashes']} crashes, {c['stale_ticks']} stale ticks, "
          f"{c['failed_reads']} reads with no servo answering, {c['retries']} retries, {c['timeouts']} timeouts; "
          f"{c['rate_hz']:.0f} cycles/s")


if __name__ == "__main__":
    main()
