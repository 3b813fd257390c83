"""Dynamixel backend (`felis.drivers`): control tables, Protocol 2.0 packets, the bus driver on the
unmodified ``dynamixel-sdk``, the virtual bus (servos emulated byte for byte on a pseudo-terminal), the
BNO08x UART-RVC IMU, and the hardware `Robot`. Nothing here imports the simulation: a virtual bus backed
by MuJoCo is built by `felis.sim.servo_in_loop` through the `felis.drivers.virtual.HornBackend` seam.

Encoder ticks exist only inside this package; everything it hands upward is SI and radians.

    dynamixel/controltable.py  item name -> address, size, access, area, default, range, SI conversion
    dynamixel/protocol.py      CRC-16, byte stuffing, packet building and incremental parsing
    dynamixel/bus.py           DynamixelBus: ping, scan, read/write by name, retries, guards
    dynamixel/port.py          the bus's serial port: exclusive open, its holder, timeouts, the SDK busy flag
    dynamixel/group.py         sync / fast-sync / bulk transfers, per-servo counters
    dynamixel/robot.py         DynamixelRobot: the HAL on a bus (+ IMU)
    virtual/                   VirtualServo, dispatch, FaultPlan, VirtualBus (pty), VirtualImu, spawn (child process)
    imu/                       RVC frame codec and parser, ImuReader, RvcEmulator, apply_mounting, SensorMount
    framing.py                 skip_to_header: the resynchronising step of the packet reader and the RVC parser
    ports.py                   open_ports: the one port opener (a device, ``virtual`` or $FELIS_PORT; the IMU's port)
"""
