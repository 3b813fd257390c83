"""Dynamixel backend (`felis.drivers`): bus driver, control tables, virtual bus, hardware `Robot`.

Not built yet: see the Dynamixel-layer issue. Encoder ticks exist only inside this package.
"""
