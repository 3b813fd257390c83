"""`felis.drivers.dynamixel`."""
