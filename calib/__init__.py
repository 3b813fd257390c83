"""Calibration (`felis.calib`): what makes a physical robot match its model.

* `setup`: new servos get their joint's ID and the robot's baud rate, one at a time.
* `joints`: the reference pose gives each servo's Homing Offset, a sweep its range.
* `calfile`: calibration files (per robot id, atomic writes, backups, checks).
* `eeprom`: EEPROM settings and calibration, expected vs held, reconciled on an explicit choice.
* `imu`: the IMU's mounting rotation and gyro bias from a still, level robot.
* `sysid`: the simulated servo model's parameters fitted to recorded responses.
* `operator`: the person at the bench (console, unattended, or a calibration script's callbacks).

The commands (`felis setup-motors`, `calibrate`, `calibration …`, `check-eeprom`, `sysid`) are thin
wrappers; docs/calibration.md is the operator's guide.
"""
