"""The fault plan of the virtual bus (`felis.drivers.virtual.faultplan`): the spec parser and its checks, every
error one line. How the bus applies the faults is tested in test_virtual_bus.py and test_virtual_watchdog.py."""

from __future__ import annotations

import pytest

from felis.drivers.virtual import FaultPlan, parse_fault_plan
from felis.errors import ParameterError


def test_parse_fault_plan():
    f = parse_fault_plan("drop=0.01,corrupt=0.001,delay_ms=5,remove=3,hwerror=5:overload,close_after=2.5,seed=0")
    assert f == FaultPlan(drop=0.01, corrupt=0.001, delay_ms=5, remove=(3,), hwerror={5: 0x20}, close_after=2.5, seed=0)
    f = parse_fault_plan("remove=3+4, remove=9, hwerror=5:overload+overheating, hwerror=6:0x01")
    assert f.remove == (3, 4, 9) and f.hwerror == {5: 0x24, 6: 0x01}
    assert parse_fault_plan("") == FaultPlan()
    for spec, key in (("dorp=0.1", "dorp"), ("drop=2", "drop"), ("delay_ms=x", "delay_ms"), ("remove=300", "remove"),
                      ("hwerror=5", "hwerror"), ("hwerror=5:gremlins", "gremlins"), ("seed", "seed")):
        with pytest.raises(ParameterError, match=key) as e:
            parse_fault_plan(spec)
        assert "\n" not in str(e.value)


def test_parse_timed_faults():
    f = parse_fault_plan("reboot=3@1.5,reboot=5@2,torque_off=7@0.25")
    assert f.reboot == ((3, 1.5), (5, 2.0)) and f.torque_off == ((7, 0.25),)
    for bad in ("reboot=3", "reboot=3@-1", "reboot=300@1", "torque_off=x@1", "reboot=3@nan"):
        with pytest.raises(ParameterError, match="fault spec") as e:
            parse_fault_plan(bad)
        assert "\n" not in str(e.value)
