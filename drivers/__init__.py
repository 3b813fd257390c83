"""Dynamixel backend (`felis.drivers`): control tables, Protocol 2.0 packets, the bus driver on the
unmodified ``dynamixel-sdk``, the virtual bus (servos emulated byte for byte on a pseudo-terminal,
optionally backed by MuJoCo), the BNO08x UART-RVC IMU, and the hardware `Robot`.

Encoder ticks exist only inside this package; everything it hands upward is SI and radians.

    controltable.py   item name -> address, size, access, area, default, range, SI conversion
    protocol.py       CRC-16, byte stuffing, packet building and incremental parsing
    bus.py            DynamixelBus: ping, scan, read/write by name, sync/fast-sync/bulk, retries, guards
    virtual.py        VirtualServo, VirtualBus (pty server, faults, wire time, MuJoCo backing), spawn()
    imu.py            RVC frame codec and parser, ImuReader, RvcEmulator, apply_mounting, SensorMount
    robot.py          DynamixelRobot: the HAL on a bus (+ IMU)
"""
