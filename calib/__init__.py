"""Calibration (`felis.calib`): motor set-up, joint calibration, system identification. Not built yet."""
