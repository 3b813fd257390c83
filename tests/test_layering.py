"""The house's layering (``../shared/DESIGN.md``, "Layout"): which package may import which.

Two checks over every module of the ``felis`` package:

- **statically**, every ``import`` in the source — at module level *and* inside functions — resolved to
  an absolute name and checked against the rules below, so a new function-level import that breaks a
  rule fails here;
- **dynamically**, each module of the layers that must stay light (core, scenarios, drivers, controllers
  and the learning inference modules) imported alone in a fresh interpreter (a fork of a clean one),
  and the ``felis`` modules and heavy libraries it pulled in checked against the same rules, so an
  indirect dependency (A imports B imports C) is caught too.

The rules, by layer (a module belongs to the most specific layer whose prefix it has):

    felis core (felis/*.py)        felis core only; numpy, scipy, stdlib
    felis.scenarios                felis core
    felis.logs                     felis core
    felis.drivers                  felis core, felis.drivers
    felis.sim                      felis core, felis.scenarios, felis.sim, felis.drivers.virtual
    felis.controllers              felis core, felis.scenarios, felis.controllers, the inference modules;
                                   no torch, mujoco or dynamixel_sdk
    inference modules              felis core, the other inference modules; numpy; no torch
    the rest of felis.learning     anything but felis.cli
    felis.calib                    felis core, felis.drivers, felis.sim, felis.calib
    felis.testing                  anything but felis.cli (the pytest plugin: robots, buses, logs for tests)
    felis.cli                      anything
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# import prefix -> source folder (pyproject.toml's [tool.setuptools.package-dir])
SOURCES = {"felis.drivers": "drivers", "felis.sim": "sim", "felis.controllers": "controllers",
           "felis.learning": "learning", "felis.calib": "calib", "felis": "felis"}
SUBPACKAGES = ("felis.cli", "felis.scenarios", "felis.logs", "felis.drivers", "felis.sim", "felis.controllers",
               "felis.learning", "felis.calib", "felis.testing")
# each skill's inference side: what controllers may import (numpy only; `infer` holds the nets' numpy forward
# passes and weight readers that the solver and the estimator share with training)
INFERENCE = ("felis.learning.landing.policy", "felis.learning.landing.motion", "felis.learning.landing.library",
             "felis.learning.landing.cap_policy", "felis.learning.landing.by_height",
             "felis.learning.landing.by_attitude", "felis.learning.landing.parts",
             "felis.learning.ik.solver",
             "felis.learning.ik.infer", "felis.learning.phase.estimator", "felis.learning.phase.infer",
             "felis.learning.balance.selector")
HEAVY = ("torch", "mujoco", "dynamixel_sdk", "ray", "matplotlib")


def _is(name: str, *prefixes: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _core(name: str) -> bool:
    return (name == "felis" or name.startswith("felis.")) and not _is(name, *SUBPACKAGES)


def layer(module: str) -> str:
    """The layer a felis module belongs to (see the module docstring)."""
    if _is(module, *INFERENCE):
        return "inference"
    for p in SUBPACKAGES:
        if _is(module, p):
            return p
    return "core"


def allowed(module: str, imported: str) -> bool:
    """Whether ``module`` may import ``imported`` (an absolute module name, felis or third party)."""
    lay = layer(module)
    felis = imported == "felis" or imported.startswith("felis.")
    if lay == "felis.cli":
        return True
    if lay in ("felis.learning", "felis.testing"):
        return not _is(imported, "felis.cli")
    if lay in ("core", "felis.scenarios", "felis.logs", "inference") and not felis:
        top = imported.split(".")[0]
        if lay == "felis.logs":
            return True
        return top in sys.stdlib_module_names or top in ("numpy", "scipy")
    if lay == "felis.controllers" and not felis:
        return not _is(imported, *HEAVY)
    if not felis:
        return True
    if _core(imported):
        return True
    rules = {
        "core": (),
        "felis.scenarios": ("felis.scenarios",),
        "felis.logs": ("felis.logs",),
        "felis.drivers": ("felis.drivers",),
        "felis.sim": ("felis.sim", "felis.scenarios", "felis.drivers.virtual"),
        "felis.controllers": ("felis.controllers", "felis.scenarios", *INFERENCE),
        "inference": INFERENCE,
        "felis.calib": ("felis.calib", "felis.drivers", "felis.sim"),
    }[lay]
    # a package's __init__ is loaded whenever a submodule is: importing felis.learning.ik.solver loads
    # felis.learning and felis.learning.ik; those package inits are allowed (they hold docstrings only).
    return _is(imported, *rules) or (imported in _inits_above(rules))


def _inits_above(prefixes: tuple[str, ...]) -> set[str]:
    out = set()
    for p in prefixes:
        parts = p.split(".")
        out.update(".".join(parts[:i]) for i in range(2, len(parts)))
    return out


def modules() -> dict[str, Path]:
    """Every module of the felis package: import name -> source file."""
    out = {}
    for prefix, folder in SOURCES.items():
        base = ROOT / folder
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("").parts
            if prefix == "felis" and rel[0] in ("drivers", "sim", "controllers", "learning", "calib"):
                continue
            if rel[-1] == "__init__":
                rel = rel[:-1]
            if rel and rel[-1] == "__main__":
                continue
            out[".".join((prefix, *rel))] = path
    return out


def imports_of(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in the file, module level and inside functions.

    ``from X import y`` yields ``X.y`` when ``X.y`` is a module of felis, else ``X``."""
    known = MODULES
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            for a in node.names:
                full = f"{base}.{a.name}"
                out.append((node.lineno, full if full in known else base))
    return sorted(set(out))


MODULES = modules()


def test_every_import_follows_the_layering():
    broken = []
    for module, path in MODULES.items():
        for line, name in imports_of(module, path):
            if name == "__future__":
                continue
            if not allowed(module, name):
                broken.append(f"{path.relative_to(ROOT)}:{line}: {module} ({layer(module)}) imports {name}")
    assert not broken, "imports against DESIGN.md's layering:\n" + "\n".join(broken)


def test_the_layering_rules_catch_what_they_should():
    # the test's own rules, on names that break them (so this file cannot pass by allowing everything)
    assert not allowed("felis.controllers.landing", "felis.sim.robot")
    assert not allowed("felis.controllers.arm_track", "felis.learning.ik.data")
    assert not allowed("felis.controllers.pose", "torch")
    assert not allowed("felis.learning.ik.solver", "felis.learning.ik.net")
    assert not allowed("felis.learning.ik.infer", "felis.controllers.arm_posture")
    assert not allowed("felis.learning.ik.solver", "torch")
    assert not allowed("felis.drivers.virtual.server", "felis.sim.robot")
    assert not allowed("felis.drivers.dynamixel.bus", "felis.scenarios")
    assert not allowed("felis.loop", "felis.drivers.dynamixel.bus")
    assert not allowed("felis.hal", "mujoco")
    assert not allowed("felis.scenarios.drop", "felis.sim.robot")
    assert not allowed("felis.sim.robot", "felis.controllers.pose")
    assert not allowed("felis.learning.landing.train", "felis.cli.output")
    assert not allowed("felis.testing.runner", "felis.cli.episode")
    assert allowed("felis.controllers.landing", "felis.learning.landing.policy")
    assert allowed("felis.sim.servo_in_loop", "felis.drivers.virtual.server")
    assert allowed("felis.learning.landing.train", "felis.sim.robot")
    assert allowed("felis.cli.main", "felis.learning.landing.train")
    assert allowed("felis.testing.resources", "felis.sim.servo_in_loop")


_PROBE = r"""
import json, os, sys
mods, HEAVY = json.loads(sys.argv[1]), tuple(json.loads(sys.argv[2]))
import numpy  # every layer may use it (not in HEAVY): loaded once here, each fork need not
out = {}
for m in mods:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            __import__(m)
            res = sorted(k for k in sys.modules if k == "felis" or k.startswith("felis.")
                         or k.split(".")[0] in HEAVY)
        except Exception as e:
            res = {"error": f"{type(e).__name__}: {e}"}
        with os.fdopen(w, "w") as f:
            json.dump(res, f)
        os._exit(0)
    os.close(w)
    with os.fdopen(r) as f:
        out[m] = json.load(f)
    os.waitpid(pid, 0)
print(json.dumps(out))
"""


def _light(module: str) -> bool:
    return layer(module) in ("core", "felis.scenarios", "felis.drivers", "felis.controllers", "inference")


@pytest.mark.timeout(300)
def test_light_layers_import_alone_without_breaking_the_layering():
    mods = sorted(m for m in MODULES if _light(m))
    assert len(mods) > 30
    res = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(mods), json.dumps(HEAVY)], capture_output=True,
                         text=True, timeout=280, cwd=ROOT, env={"PATH": "/usr/bin:/bin", "MUJOCO_GL": "egl"})
    assert res.returncode == 0, res.stderr[-2000:]
    loaded = json.loads(res.stdout)
    broken = []
    for m in mods:
        got = loaded[m]
        assert not isinstance(got, dict), f"import {m}: {got['error']}"
        bad = [n for n in got if n != m and not _is(n, m) and not allowed(m, n) and not _inits_of(m, n)]
        if bad:
            broken.append(f"{m} ({layer(m)}) loads {', '.join(bad)}")
    assert not broken, "imported alone, these modules load what their layer may not:\n" + "\n".join(broken)


def _inits_of(module: str, name: str) -> bool:
    """``name`` is a package above ``module`` (loaded whenever the module is)."""
    return module.startswith(name + ".")
