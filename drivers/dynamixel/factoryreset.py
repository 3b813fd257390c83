"""FACTORY_RESET (Protocol 2.0 instruction 0x06): a servo's control table back to factory values, and a ping
where it must answer afterwards.

The parameter says what survives (e-Manual, Protocol 2.0 "Factory Reset"): 0xFF everything is reset (ID 1,
the model's factory baud rate: 57600 bps on the X series), 0x01 all but the ID, 0x02 all but the ID and the
baud rate. The servo answers with its old ID at its old baud rate, then restarts with the new ones; it
refuses the reset while torque is on (Access Error). `KEEP` maps the operator's words (``--keep``) to the
parameter; `where_after` says at which (ID, baud) the servo answers afterwards, and `factory_reset` sends the
instruction, then pings there until the servo is back (it is deaf while it restarts).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from felis.drivers.dynamixel import protocol as P
from felis.drivers.dynamixel.bus import Found
from felis.drivers.dynamixel.controltable import ControlTable
from felis.errors import CommError, CorruptReplyError, NoReplyError, ServoStatusError

KEEP = {"none": 0xFF, "id": 0x01, "id+baud": 0x02}
FACTORY_ID = 1
RESTART_S = 2.0  # how long to keep pinging while the servo restarts


@dataclass(frozen=True)
class ResetResult:
    """Where the servo answers after the reset, and how it answered."""

    option: int
    id: int
    baud: int
    found: Found
    reply_lost: bool  # the status to the instruction itself was lost (the reset was judged by the ping)


def where_after(table: ControlTable, dxl_id: int, baud: int, keep: str) -> tuple[int, int]:
    """(ID, baud) the servo answers at after a reset keeping ``keep`` (`KEEP`)."""
    option = KEEP[keep]
    new_id = dxl_id if option in (0x01, 0x02) else FACTORY_ID
    new_baud = baud if option == 0x02 else table.baud_rates[table.item("baud_rate").default]
    return new_id, new_baud


def factory_reset(bus, dxl_id: int, keep: str) -> ResetResult:
    """Send FACTORY_RESET to ``dxl_id`` (torque must be off) and ping it where it must answer afterwards.

    The bus is left at the baud rate the servo now has. ServoStatusError when the servo refuses (torque on);
    CommError when it answers nowhere afterwards."""
    table = bus.table(dxl_id)
    option = KEEP[keep]
    new_id, new_baud = where_after(table, dxl_id, bus.baud, keep)
    lost = False
    try:
        err, _ = bus._status_of(dxl_id, "factory reset", P.FACTORY_RESET, [option], 0, retries=0)
        if err & 0x7F:
            raise ServoStatusError(dxl_id, err, "factory reset", P.describe_status_error(err))
    except (NoReplyError, CorruptReplyError):
        lost = True  # judged by the ping below: the reset may have happened
    bus.set_baud(new_baud)
    bus.models.pop(dxl_id, None)
    deadline = time.monotonic() + RESTART_S
    while True:
        found = bus.try_ping(new_id, retries=0)
        if found is not None or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    if found is None:
        raise CommError(f"servo {dxl_id}: no answer as ID {new_id} at {new_baud} bps after the factory reset"
                        + (" (nor to the reset itself)" if lost else "") + "; `felis scan` shows where it is")
    return ResetResult(option, new_id, new_baud, found, lost)
