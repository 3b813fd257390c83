"""The CLI on servos of any supported model, and one line for a model felis does not support (issue 23).

Reads and writes of every model through the SDK: tests/drivers/test_controltables.py.
"""

from __future__ import annotations

import dataclasses
import json

from test_cli import felis, ok
from test_cli_dxl import one_error_line

from felis.drivers.virtual import VirtualBus

BAUD = 1_000_000


def test_scan_and_info_on_new_models_and_one_line_for_an_unknown_one(tmp_path):
    with VirtualBus.for_models(["XL330-M077-T", "XC330-M181-T", 1120, "XL330-M288-T"], baud=BAUD) as vb:
        odd = vb.servo(4)  # a model no table knows: what it answers to a ping and a read of Model Number
        odd.table = dataclasses.replace(odd.table, model_number=9999)
        odd.set("model_number", 9999)
        info = json.loads(ok(felis(tmp_path, "info", "1", "--port", vb.port, "--json")).stdout)
        assert info["model"] == "XL330-M077-T"
        r = ok(felis(tmp_path, "scan", "--port", vb.port, "--bauds", str(BAUD), "--json"))
        assert [(s["id"], s["model"]) for s in json.loads(r.stdout)] == [
            (1, "XL330-M077-T"), (2, "XC330-M181-T"), (3, "XM540-W270-T"), (4, "unknown (9999)")]
        for cmd in (("info", "4"), ("read", "4", "led")):
            one_error_line(felis(tmp_path, *cmd, "--port", vb.port), "servo 4", "9999", "docs/servos.md")
