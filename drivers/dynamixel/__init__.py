"""Real Dynamixel servos (`felis.drivers.dynamixel`): Protocol 2.0 on the unmodified ``dynamixel-sdk``.

    controltable.py  item name -> address, size, access, area, default, range, SI conversion
    protocol.py      CRC-16, byte stuffing, packet building and incremental parsing
    port.py          BusPort: the serial port (exclusive open, its holder, timeouts, the SDK busy flag)
    group.py         GroupTransfers: sync / fast-sync / bulk transfers, per-servo counters (ServoStats)
    bus.py           DynamixelBus: ping, scan, read/write by name, retries, guards
    robot.py         DynamixelRobot: the HAL on a bus (+ IMU)
    tabledump.py     a servo's whole control table: read in blocks, save/load (JSON), diff, restore
    factoryreset.py  FACTORY_RESET (keep ID / ID+baud / nothing), then the ping where the servo answers
    trace.py         PacketTrace / TracedBus: every packet, timed and decoded, from the SDK port's bytes
"""
