"""``felis dump``, ``felis restore`` and ``felis factory-reset`` through the real ``dynamixel-sdk`` over a pty
against the virtual bus (in this process); the commands run in process through `felis.cli.main.main`,
and as a subprocess where a terminal or the one-line error contract on a real process is the point.

Checked: dump -> change every writable item -> restore -> dump gives the dumped table back (ID and baud
rate kept by the target); the dump reads in a few block reads; refusals are one line and write nothing
(a dump of another model, malformed dumps, an ID that does not answer, no confirmation: declined on a
terminal or no terminal, torque on); factory-reset resets the items and keeps ID/baud per ``--keep``.
"""

from __future__ import annotations

import json
import os

import pytest

from felis.cli.main import main
from felis.drivers.dynamixel.bus import DynamixelBus
from felis.drivers.dynamixel.controltable import control_table
from felis.drivers.dynamixel.tabledump import KEPT, blocks, load_dump, restorable
from felis.drivers.virtual import VirtualBus
from felis.errors import ParameterError

BAUD = 1_000_000
MODEL = "XL330-M288-T"


@pytest.fixture(autouse=True)
def margin(monkeypatch):
    # the virtual bus serves from this process's thread: the margin the other bus tests allow on a loaded machine
    monkeypatch.setenv("FELIS_TIMEOUT_MARGIN_MS", "100")


def cli(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def bus(vb, baud: int = BAUD) -> DynamixelBus:
    return DynamixelBus(vb.port, baud, timeout_margin_ms=40, retries=2)


def other_values(table) -> dict[str, int]:
    """Another valid raw value for every restorable item, and for ID and baud rate: the limits and the goals
    they bound chosen to fit together (the goal checks of an X-series servo)."""
    fixed = {"min_position_limit": 100, "max_position_limit": 4000, "goal_position": 1000, "velocity_limit": 400,
             "goal_velocity": 12, "current_limit": 1000, "goal_current": 50, "temperature_limit": 60,
             "max_voltage_limit": 65, "min_voltage_limit": 40, "secondary_id": 100, "status_return_level": 1,
             "bus_watchdog": 5, "operating_mode": 4, "homing_offset": 100, "drive_mode": 1, "led": 1,
             "id": 5, "baud_rate": 2}
    out = {}
    for it in table.items.values():
        if not (restorable(it) or it.name in ("id", "baud_rate")):
            continue
        if it.name in fixed:
            out[it.name] = fixed[it.name]
        elif it.name.startswith("indirect_address_"):
            out[it.name] = 64 + int(it.name.rsplit("_", 1)[1])  # RAM addresses
        else:
            out[it.name] = it.lo + 1 if it.default == it.lo else it.lo
        it.check(out[it.name])
    return out


def restorable_items(doc: dict) -> dict[str, int]:
    table = control_table(doc["model_number"])
    return {i["name"]: i["raw"] for i in doc["items"] if restorable(table.items[i["name"]])}


def test_dump_change_every_writable_item_restore_gives_the_dump_back(tmp_path, capsys):
    table = control_table(MODEL)
    assert len(blocks(table)) <= 3  # a whole table in a few READs, not one per item (92 items)
    with VirtualBus.for_models([MODEL], baud=BAUD) as vb:
        first, trace = tmp_path / "first.json", tmp_path / "dump.trace"
        rc, out, err = cli(capsys, "dump", "--id", "1", "--port", vb.port, "--out", str(first), "--trace", str(trace))
        assert rc == 0, err
        assert "goal_position" in out and "EEPROM" in out and "rad" in out
        reads = [ln for ln in trace.read_text().splitlines() if " TX 1 READ " in ln]
        assert len(reads) == len(blocks(table)), reads
        doc = json.loads(first.read_text())
        assert doc["schema"] == "felis.control-table/1" and doc["model"] == MODEL and doc["model_number"] == 1200
        assert {"firmware", "id", "baud", "time", "felis_version"} <= set(doc)
        assert len(doc["items"]) == len(table.items)
        by_name = {i["name"]: i for i in doc["items"]}
        assert by_name["operating_mode"]["value"] == "position" and by_name["baud_rate"]["value"] == BAUD
        assert by_name["goal_position"]["unit"] == "rad" and by_name["present_position"]["access"] == "R"

        # every writable item to another valid value (EEPROM with torque off), the ID and baud rate too
        values = other_values(table)
        servo = vb.servo(1)
        assert servo.get("torque_enable") == 0
        order = sorted(values, key=lambda n: (n in ("status_return_level", "id", "baud_rate"), table.items[n].addr))
        with bus(vb) as b:
            for name in order:
                it = table.items[name]
                if name == "status_return_level" or name in ("id", "baud_rate"):
                    servo.set(name, values[name])  # these change how it answers: set on the servo itself
                else:
                    b.write_raw(1, it.addr, it.encode(values[name]))
        new_id, new_baud = 5, 115200
        assert servo.id == new_id and servo.baud_bps == new_baud
        changed = {n: servo.get(n) for n in values}
        assert all(changed[n] != by_name[n]["raw"] for n in values), "every item changed"

        rc, out, err = cli(capsys, "restore", str(first), "--id", str(new_id), "--baud", str(new_baud), "--port",
                           vb.port, "--yes", "--json")
        assert rc == 0, err
        res = json.loads(out)
        assert not res["failed"] and len(res["restored"]) == len(values) - 2
        assert {k["item"] for k in res["kept"]} == {"id", "baud_rate"}

        second = tmp_path / "second.json"
        rc, _, err = cli(capsys, "dump", "--id", str(new_id), "--baud", str(new_baud), "--port", vb.port, "--out",
                         str(second), "--json")
        assert rc == 0, err
        again = json.loads(second.read_text())
        assert restorable_items(again) == restorable_items(doc)
        kept = {i["name"]: i["raw"] for i in again["items"] if i["name"] in KEPT}
        assert kept["id"] == new_id and kept["baud_rate"] == 2 and kept["torque_enable"] == 0
        revision = servo.revision
        rc, out, err = cli(capsys, "restore", str(second), "--port", vb.port, "--baud", str(new_baud))
        assert rc == 0 and "nothing to write: servo 5 already holds the dump's settings" in out, err
        assert servo.revision == revision


def test_restore_refusals_are_one_line_and_write_nothing(tmp_path, capsys):
    with VirtualBus.for_models([MODEL, "XM430-W350-T"], baud=BAUD) as vb:
        dump = tmp_path / "d.json"
        assert cli(capsys, "dump", "--id", "1", "--port", vb.port, "--out", str(dump), "--json")[0] == 0
        servo = vb.servo(1)
        servo.set("position_p_gain", 123)
        servo.set("return_delay_time", 17)
        revision = servo.revision

        def refused(*argv, fragments=()):
            rc, out, err = cli(capsys, "restore", *argv, "--port", vb.port)
            lines = [ln for ln in err.splitlines() if ln.strip()]
            assert rc != 0 and len(lines) == 1 and lines[0].startswith("error: "), (rc, err)
            for f in fragments:
                assert f in lines[0], lines[0]
            assert servo.revision == revision and servo.get("position_p_gain") == 123  # nothing written

        refused(str(dump), "--id", "2", "--yes", fragments=("XL330-M288-T", "XM430-W350-T", "same model"))
        refused(str(dump), "--id", "9", "--yes", fragments=("servo 9 did not answer",))
        bad = tmp_path / "bad.json"
        bad.write_text("{ not json")
        refused(str(bad), "--yes", fragments=("bad.json", "not JSON"))
        doc = json.loads(dump.read_text())
        for mutate, fragment in ((lambda d: d.update(schema="x"), "schema"),
                                 (lambda d: d["items"].pop(), "missing"),
                                 (lambda d: d["items"][7].update(raw=99999), "outside"),
                                 (lambda d: d["items"][3].update(raw="7"), "not an integer")):
            broken = json.loads(json.dumps(doc))
            mutate(broken)
            bad.write_text(json.dumps(broken))
            refused(str(bad), "--yes", fragments=("bad.json", fragment))
            with pytest.raises(ParameterError):
                load_dump(bad)
        # no terminal to ask on and no --yes (pytest's captured stdin is not a terminal)
        refused(str(dump), fragments=("confirm with --yes",))
        # torque on, EEPROM item (return delay) differs: refused without --yes
        servo.set("torque_enable", 1)
        revision = servo.revision
        refused(str(dump), fragments=("torque is on", "return_delay_time", "felis torque off --id 1"))
        # --dry-run shows the diff and writes nothing
        rc, out, err = cli(capsys, "restore", str(dump), "--port", vb.port, "--dry-run", "--json")
        assert rc == 0, err
        assert {c["item"] for c in json.loads(out)["changes"]} == {"position_p_gain", "return_delay_time"}
        assert servo.revision == revision
        # --yes with torque on: the RAM items only, the EEPROM one reported as left, exit 1
        rc, out, err = cli(capsys, "restore", str(dump), "--port", vb.port, "--yes", "--json")
        assert rc == 1 and "1 EEPROM item(s) left" in err
        assert json.loads(out)["restored"] == ["position_p_gain"]
        dumped_p = next(i["raw"] for i in doc["items"] if i["name"] == "position_p_gain")
        assert servo.get("position_p_gain") == dumped_p != 123 and servo.get("return_delay_time") == 17
        assert servo.get("torque_enable") == 1


def test_restore_asks_on_a_terminal_and_no_writes_nothing(tmp_path, capsys, monkeypatch):
    with VirtualBus.for_models([MODEL], baud=BAUD) as vb:
        servo = vb.servo(1)
        dump = tmp_path / "d.json"
        assert cli(capsys, "dump", "--id", "1", "--port", vb.port, "--out", str(dump), "--json")[0] == 0
        servo.set("position_p_gain", 321)
        master, slave = os.openpty()  # standard input is a terminal, and the operator answers n
        with open(slave, encoding="utf-8", closefd=True) as tty:
            monkeypatch.setattr("sys.stdin", tty)
            os.write(master, b"n\n")
            rc, out, err = cli(capsys, "restore", str(dump), "--port", vb.port)
        os.close(master)
        assert rc == 1 and "position_p_gain" in out  # the diff first
        prompt, answer = err.split("[y/N] ", 1)  # the terminal echoes the operator's Enter; a pipe does not
        assert prompt == "write 1 item(s) to servo 1? "
        assert answer.strip() == "error: restore of 1 item(s) to servo 1 refused: not confirmed"
        assert servo.get("position_p_gain") == 321


def test_restore_to_a_silent_status_level_reads_back_first(tmp_path, capsys):
    with VirtualBus.for_models([MODEL], baud=BAUD) as vb:
        dump = tmp_path / "d.json"
        assert cli(capsys, "dump", "--id", "1", "--port", vb.port, "--out", str(dump), "--json")[0] == 0
        doc = json.loads(dump.read_text())
        for item in doc["items"]:  # a servo that answers pings only, and another gain
            item["raw"] = {"status_return_level": 0, "position_i_gain": 7}.get(item["name"], item["raw"])
        dump.write_text(json.dumps(doc))
        rc, out, err = cli(capsys, "restore", str(dump), "--port", vb.port, "--yes", "--json")
        assert rc == 0, err
        assert json.loads(out)["restored"] == ["position_i_gain", "status_return_level"]
        assert vb.servo(1).get("status_return_level") == 0 and vb.servo(1).get("position_i_gain") == 7


@pytest.mark.parametrize("keep, where", [("id+baud", (3, BAUD)), ("none", (1, 57600))])
def test_factory_reset_resets_the_items_and_keeps_per_keep(tmp_path, capsys, keep, where):
    with VirtualBus.for_models([MODEL], baud=BAUD, first_id=3) as vb:
        servo = vb.servo(3)
        table = servo.table
        for name, raw in (("position_p_gain", 123), ("return_delay_time", 0), ("homing_offset", 50),
                          ("operating_mode", 4), ("led", 1), ("profile_velocity", 30)):
            servo.set(name, raw)
        servo.set("torque_enable", 1)
        rc, _, err = cli(capsys, "factory-reset", "--id", "3", "--keep", keep, "--yes", "--port", vb.port)
        assert rc == 1 and "torque is on" in err and servo.get("position_p_gain") == 123
        servo.set("torque_enable", 0)
        rc, _, err = cli(capsys, "factory-reset", "--id", "3", "--keep", keep, "--port", vb.port)
        assert rc == 1 and "confirm with --yes" in err and servo.get("position_p_gain") == 123
        rc, out, err = cli(capsys, "factory-reset", "--id", "3", "--keep", keep, "--yes", "--port", vb.port, "--json")
        assert rc == 0, err
        res = json.loads(out)
        assert (res["new_id"], res["new_baud"]) == where and res["verified"] and res["not_factory"] == []
        assert (servo.id, servo.baud_bps) == where
        for it in table.items.values():
            if it.writable and it.name not in ("id", "baud_rate", "goal_position"):
                assert servo.get(it.name) == it.default, it.name


def test_factory_reset_refuses_to_land_on_a_used_address(tmp_path, capsys):
    with VirtualBus.for_models([MODEL, MODEL], baud=57600, first_id=1) as vb:
        rc, _, err = cli(capsys, "factory-reset", "--id", "2", "--keep", "none", "--yes", "--baud", "57600",
                         "--port", vb.port)
        assert rc == 1 and "ID 1 at 57600 bps" in err
        assert vb.servo(2).id == 2
