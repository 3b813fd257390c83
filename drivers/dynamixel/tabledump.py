"""A servo's whole control table as data: read it (`read_table`), save and load it (`TableDump`,
`load_dump`), compare two (`restore_plan`) and write the differences back (`apply_plan`).

Reading: the items of the model's table (`felis.drivers.dynamixel.controltable`, found by ping) are read
in contiguous blocks (`blocks`: items closer than `MAX_GAP` bytes share one READ of at most `MAX_BLOCK`
bytes, gap bytes read and ignored), 3 or 4 READs for a whole X-series table instead of ~90.

The file (JSON, ``schema`` = `SCHEMA`): model name and number, firmware, ID, baud rate, time (UTC, ISO
8601), felis version, and per item its address, size, area (EEPROM/RAM), access (R/RW), raw value,
value in SI units (`Item.to_si`: rad, rad/s, A, V, s, °C; enumerations as their value) and unit.

Restoring writes only writable items whose raw value differs, and never these (`KEPT`): the ID, baud rate
and protocol (the target keeps its own address on the bus, so a dump of ID 3 restores onto ID 5 and the
servo stays ID 5 at its baud rate; `felis set-id` / `set-baud` change those), Torque Enable (restoring
settings never powers a joint), and the Indirect Data items (views of the items their Indirect Address
names: those items, and the Indirect Addresses, are restored themselves). Order (`restore_plan`): EEPROM
items by address (Operating Mode and the limits before the goals they bound), then RAM by address, then
Status Return Level and Bus Watchdog last (a lower return level would silence the acknowledgements of
the writes after it; a watchdog acts only while torque is on). EEPROM items need torque off
(e-Manual: Access Error otherwise); the caller decides what to do when it is on. A servo whose Status
Return Level is below 2 does not acknowledge writes: `apply_plan` first sets it to 2 unacknowledged and
checks it by reading (level 1 answers reads), then writes the dumped level last. Every written item is read
back (the whole table, in blocks) and reported as it is; a dumped level of 0 (pings only) is written after the
read-back and judged by its acknowledgement.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field
from pathlib import Path

import felis
from felis.drivers.dynamixel.controltable import EEPROM_END, ControlTable, Item, control_table
from felis.errors import CommError, CorruptReplyError, NoReplyError, ParameterError, ServoStatusError
from felis.files import read_json

SCHEMA = "felis.control-table/1"
MAX_BLOCK = 128  # bytes per READ: well inside the SDK's and the servos' packet buffers
MAX_GAP = 24  # reserved bytes read (and ignored) rather than starting another READ
KEPT = {"id": "the target keeps its ID (`felis set-id` changes it)",
        "baud_rate": "the target keeps its baud rate (`felis set-baud` changes it)",
        "protocol_type": "the bus speaks Protocol 2.0",
        "torque_enable": "restoring settings never powers a joint"}
LAST = ("status_return_level", "bus_watchdog")  # written after everything else, in this order


@dataclass(frozen=True)
class DumpedItem:
    """One item of a dump: where it is, what it is, its raw value and that value in SI units."""

    name: str
    addr: int
    size: int
    area: str
    access: str
    raw: int
    value: object
    unit: str

    def as_dict(self) -> dict:
        return {"name": self.name, "addr": self.addr, "size": self.size, "area": self.area, "access": self.access,
                "raw": self.raw, "value": self.value, "unit": self.unit}


@dataclass(frozen=True)
class TableDump:
    """A servo's whole control table at one moment (module doc)."""

    model: str
    model_number: int
    firmware: int
    id: int
    baud: int
    time: str
    felis_version: str
    items: dict[str, DumpedItem] = field(default_factory=dict)

    @property
    def table(self) -> ControlTable:
        return control_table(self.model_number)

    def raw(self, name: str) -> int:
        return self.items[name].raw

    def as_dict(self) -> dict:
        return {"schema": SCHEMA, "model": self.model, "model_number": self.model_number, "firmware": self.firmware,
                "id": self.id, "baud": self.baud, "time": self.time, "felis_version": self.felis_version,
                "items": [it.as_dict() for it in self.items.values()]}


def dumped(it: Item, raw: int) -> DumpedItem:
    value = it.to_si(raw)
    if isinstance(value, float) and not it.unit and value.is_integer():
        value = int(value)  # counts, flags, gains: no unit, no fraction
    elif isinstance(value, float):
        value = round(value, 9)  # SI of a raw integer: 9 digits keep it exact enough and the file readable
    return DumpedItem(it.name, it.addr, it.size, it.area, it.access, raw, value, it.unit)


def blocks(table: ControlTable, max_block: int = MAX_BLOCK, max_gap: int = MAX_GAP) -> list[tuple[int, int]]:
    """(address, length) of the READs that cover every item: items in address order, a new block when the
    next item starts more than ``max_gap`` bytes after the block or would make it longer than ``max_block``."""
    out: list[list[int]] = []
    for it in sorted(table.items.values(), key=lambda i: i.addr):
        end = it.addr + it.size
        if out and it.addr - out[-1][1] <= max_gap and end - out[-1][0] <= max_block:
            out[-1][1] = max(out[-1][1], end)
        else:
            out.append([it.addr, end])
    return [(a, e - a) for a, e in out]


def read_table(bus, dxl_id: int) -> TableDump:
    """Ping ``dxl_id`` (its model and firmware), then read its whole control table in `blocks`."""
    found = bus.ping(dxl_id)
    table = bus.table(dxl_id)
    mem = bytearray(table.size)
    for addr, length in blocks(table):
        mem[addr:addr + length] = bus.read_raw(dxl_id, addr, length)
    items = {it.name: dumped(it, it.decode(mem[it.addr:it.addr + it.size]))
             for it in sorted(table.items.values(), key=lambda i: i.addr)}
    now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    return TableDump(table.model, table.model_number, found.firmware, dxl_id, bus.baud, now, felis.__version__, items)


# ------------------------------------------------------------------------------------------ the file
def load_dump(path: str | os.PathLike) -> TableDump:
    """A dump file, checked whole: schema, a model felis knows, every item of that model's table at its
    address and size with an integer raw value that fits it (writable items: within their range). Any fault
    is one ParameterError line naming the file and what is wrong."""
    path = Path(path)
    doc = read_json(path, "control-table dump", ParameterError, hint=" (write one with `felis dump --out FILE`)")

    def bad(what: str) -> ParameterError:
        return ParameterError(f"{path}: not a felis control-table dump: {what}")

    if not isinstance(doc, dict):
        raise bad("expected a JSON object")
    if doc.get("schema") != SCHEMA:
        raise bad(f"schema is {doc.get('schema')!r}, expected {SCHEMA!r}")
    for key, kind, what in (("model_number", int, "a number"), ("firmware", int, "a number"), ("id", int, "a number"),
                            ("baud", int, "a number"), ("model", str, "text"), ("items", list, "a list")):
        if not isinstance(doc.get(key), kind) or isinstance(doc.get(key), bool):
            raise bad(f"'{key}' is missing or not {what}")
    try:
        table = control_table(doc["model_number"])
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None
    items: dict[str, DumpedItem] = {}
    for k, entry in enumerate(doc["items"]):
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise bad(f"items[{k}] has no name")
        name = entry["name"]
        it = table.items.get(name)
        if it is None:
            raise bad(f"item {name!r} is not in the {table.model}'s control table")
        raw = entry.get("raw")
        if not isinstance(raw, int) or isinstance(raw, bool):
            raise bad(f"{name}: raw value {raw!r} is not an integer")
        if entry.get("addr") != it.addr or entry.get("size") != it.size:
            raise bad(f"{name} is at {entry.get('addr')}+{entry.get('size')}, "
                      f"the {table.model}'s at {it.addr}+{it.size}")
        if it.writable and not (it.lo <= raw <= it.hi and (it.values is None or raw in it.values)):
            raise bad(f"{name}: raw value {raw} is outside {it.lo}…{it.hi}")
        try:
            it.encode(raw)
        except OverflowError:
            raise bad(f"{name}: raw value {raw} does not fit {it.size} byte(s)") from None
        items[name] = dumped(it, raw)
    missing = [n for n in table.items if n not in items]
    if missing:
        raise bad(f"{len(missing)} item(s) of the {table.model} missing ({', '.join(missing[:4])}"
                  f"{' …' if len(missing) > 4 else ''})")
    return TableDump(table.model, table.model_number, doc["firmware"], doc["id"], doc["baud"], str(doc.get("time", "")),
                     str(doc.get("felis_version", "")), {n: items[n] for n in table.items})


# ------------------------------------------------------------------------------------------ restoring
@dataclass(frozen=True)
class Change:
    """One item to write: its value now on the servo and in the dump (raw)."""

    item: Item
    current: int
    dumped: int

    @property
    def eeprom(self) -> bool:
        return self.item.addr < EEPROM_END

    def as_dict(self) -> dict:
        it = self.item
        return {"item": it.name, "addr": it.addr, "area": it.area, "current": self.current, "dumped": self.dumped,
                "current_value": dumped(it, self.current).value, "dumped_value": dumped(it, self.dumped).value,
                "unit": it.unit}


def restorable(it: Item) -> bool:
    """Whether restore writes this item when it differs (module doc: writable, not `KEPT`, not Indirect Data)."""
    return it.writable and it.name not in KEPT and not it.name.startswith("indirect_data_")


def restore_plan(current: TableDump, dump: TableDump) -> list[Change]:
    """The writes that bring ``current`` to ``dump``, in the order they must go (module doc). ParameterError
    (one line naming both) when the dump is of another model."""
    if current.model_number != dump.model_number:
        raise ParameterError(f"the dump is of a {dump.model} (model {dump.model_number}); servo {current.id} is a "
                             f"{current.model} (model {current.model_number}): restore a dump onto the same model")
    table = current.table
    changes = [Change(it, current.raw(it.name), dump.raw(it.name)) for it in table.items.values()
               if restorable(it) and current.raw(it.name) != dump.raw(it.name)]

    def key(c: Change) -> tuple:
        name = c.item.name
        return (2, LAST.index(name)) if name in LAST else (0 if c.eeprom else 1, c.item.addr)

    return sorted(changes, key=key)


def kept_differences(current: TableDump, dump: TableDump) -> list[Change]:
    """`KEPT` items that differ (reported, never written)."""
    table = current.table
    return [Change(table.items[n], current.raw(n), dump.raw(n)) for n in KEPT
            if n in table.items and current.raw(n) != dump.raw(n)]


@dataclass
class RestoreResult:
    """What `apply_plan` did: items whose write was refused (item name -> why) and, after reading the table
    back, the planned items that now hold the dumped value and those that do not."""

    after: TableDump
    restored: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.failed


def apply_plan(bus, dxl_id: int, plan: list[Change], current: TableDump) -> RestoreResult:
    """Write ``plan`` (from `restore_plan`) to servo ``dxl_id``, then read the whole table back and judge
    every planned item by what it now holds. A write the servo refuses (a status error) is recorded and the
    rest go on; a servo that stops answering ends it (CommError)."""
    refused: dict[str, str] = {}
    srl = current.table.items.get("status_return_level")
    if srl is not None and current.raw(srl.name) < 2 and plan:
        _unacknowledged(bus, dxl_id, srl, 2)
    # a dumped level 0 answers pings only: the table is read back before it is written, and it is judged by its ack
    silent = [c for c in plan if c.item.name == "status_return_level" and c.dumped == 0]
    for c in [c for c in plan if c not in silent]:
        _write(bus, dxl_id, c, refused)
    after = read_table(bus, dxl_id)
    for c in silent:
        if _write(bus, dxl_id, c, refused):
            after.items[c.item.name] = dumped(c.item, c.dumped)
    result = RestoreResult(after)
    for c in plan:
        now = after.raw(c.item.name)
        if now == c.dumped:
            result.restored.append(c.item.name)
        else:
            why = refused.get(c.item.name, "the write was acknowledged")
            result.failed[c.item.name] = f"reads {now}, dumped {c.dumped} ({why})"
    return result


def _write(bus, dxl_id: int, c: Change, refused: dict[str, str]) -> bool:
    """Write one planned item; a status error is recorded in ``refused`` (False), not raised."""
    it = c.item
    try:
        bus.write_raw(dxl_id, it.addr, it.encode(c.dumped), f"write {it.name} = {c.dumped}")
        return True
    except ServoStatusError as e:
        refused[it.name] = str(e)
        return False


def _unacknowledged(bus, dxl_id: int, it: Item, raw: int) -> None:
    """Write an item to a servo that does not acknowledge writes (Status Return Level < 2), then read it."""
    try:
        bus.write_raw(dxl_id, it.addr, it.encode(raw), f"write {it.name} = {raw}")
    except (NoReplyError, CorruptReplyError):
        pass  # expected: the level in force when the write arrived says no status
    if bus.read(dxl_id, it.name, raw=True) != raw:
        raise CommError(f"servo {dxl_id}: could not set {it.name} to {raw} to have the writes acknowledged")
