"""Other buildable cats for the landing design study (issue 21, item 6): servos from the same family, the
supply voltage, the paw.

A `Design` changes the described cat (`felis/robots/cat.toml`, `sim/models/cat.xml`) in three ways only:

* **servos per group** (``spine``, ``tail``, ``legs``): another model of the family
  (`felis.servos.SERVOS`): its stall torque τ_s, no-load speed ω₀, factory gains, armature and friction go
  into the MuJoCo servo (`felis.sim.servo.servo_params`), and the joint's ``max_velocity`` (the safety
  layer's per-tick step and the optimum's joint speed) becomes its ω₀;
* **supply voltage** V: a DC motor's stall torque and no-load speed both scale with V, so τ_s and ω₀ are the
  datasheet's figures times V / V_nominal (the XL330 and XC330 run on 3.7–6 V; `VOLTS_MAX`);
* **paw contact**: the time constant τ of the feet's contact with the floor (`sim/models/cat.xml`: 2 ms, moulded
  rubber; a paw carrying a quarter of the cat is a spring of k ≈ (M/4)/τ², docs/landing.md; `paw_edit`), and the
  **physics step** the design is simulated at (`timestep_s`; the model's is 0.5 ms, which resolves the 2 ms
  paw's impact: ≤ τ/4).

``4ms-paw`` is the cat as described until 2026-11-29, bit for bit: 4 ms paws at a 1 ms step (every figure measured
on "the described cat" before then is its); the study's other designs (``fast-limbs``, ``strong-spine``, ``6V``,
``soft-rubber-paw``) change that cat, since the study was measured on it, and run the library with the vote taken
on it (``landing_library_4ms-paw.json``). ``soft-rubber-paw`` (3 ms) is the contact the 2 ms paw made before
`paw_edit` gave the feet priority over the floor (MuJoCo averaged its 2 ms with the floor's 4 ms): every "rubber
paw" figure measured before 2026-11-28 is its, bit for bit. ``cat+fast-limbs``, ``cat+strong-spine``,
``cat+fast-limbs+strong-spine`` and ``cat+6V`` make the same servo changes to the described cat. A design's
``base`` is the cat it changes, which the study reads it against.

Masses stay the model's: an XC330 is 5 g heavier than an XL330 (23 g against 18 g), 1 % of the cat per
servo, which the study ignores. `DESIGNS` holds the study's designs, `design_sim` builds the batch simulation
of one (`felis.learning.landing.evaluate.BatchLandingSim`), `design_timestep` the physics step it runs at,
`design_library` the motion library that ``--policy library`` runs on it (the shipped motions with the vote taken
on that cat), and `joint_speeds` gives the per-joint speed the
optimum's motions run at (`felis.learning.landing.optimum.motion_table`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from felis.errors import ParameterError
from felis.servos import SERVOS, servo_model
from felis.spec import RobotSpec, load_spec

VOLTS_MAX = {"XL330": 6.0, "XC330": 6.0}  # the families' maximum supply (ROBOTIS e-Manual: 3.7–6.0 V)


@dataclass(frozen=True)
class Design:
    """One buildable variant of the cat (module doc). Unset fields keep the description's."""

    name: str
    summary: str
    servos: dict[str, str] = field(default_factory=dict)  # group → servo model
    volts: float | None = None  # supply voltage for every servo (None: each model's nominal)
    paw_tau_s: float | None = None  # the feet's contact time constant (None: the model's)
    timestep_s: float | None = None  # its physics step (None: the model's)
    library: str | None = None  # its own motion library (a votes file in learning/weights/): --policy library on it
    base: str = "cat"  # the design it changes, which the study reads it against (same drops, same run)

    def check(self, spec: RobotSpec) -> None:
        for group, model in self.servos.items():
            if group not in spec.groups:
                raise ParameterError(f"design {self.name}: the cat has no group {group!r} "
                                     f"(it has {', '.join(spec.groups)})")
            if model not in SERVOS:
                raise ParameterError(f"design {self.name}: unknown servo model {model!r}")
            m = SERVOS[model]
            if m.stall_torque is None or m.no_load_speed is None or m.voltage is None:
                raise ParameterError(f"design {self.name}: {model} has no datasheet figures to model it with")
        if self.volts is not None:
            for j in spec.joints:
                model = self.model_of(j.name, spec)
                top = VOLTS_MAX.get(model[:5])
                if top is None or not (3.7 <= self.volts <= top):
                    raise ParameterError(f"design {self.name}: {model} runs on 3.7–{top or 0:g} V, "
                                         f"not {self.volts:g} V")
        if self.paw_tau_s is not None and not (math.isfinite(self.paw_tau_s) and 0.0005 <= self.paw_tau_s <= 0.1):
            raise ParameterError(f"design {self.name}: paw τ must be within 0.5–100 ms, got {self.paw_tau_s}")
        if self.timestep_s is not None and not (math.isfinite(self.timestep_s) and 0 < self.timestep_s <= 0.01):
            raise ParameterError(f"design {self.name}: a physics step must be within (0, 10] ms, got {self.timestep_s}")

    def model_of(self, joint: str, spec: RobotSpec) -> str:
        for group, model in self.servos.items():
            if joint in spec.groups.get(group, ()):
                return model
        return next(j.servo for j in spec.joints if j.name == joint)


# The 4 ms-paw cat at 1 ms: the cat as described until 2026-11-29 and the base of the design study (measured on it).
_OLD = {"paw_tau_s": 0.004, "timestep_s": 0.001, "library": "landing_library_4ms-paw.json", "base": "4ms-paw"}
_FAST_LIMBS = {"legs": "XL330-M077-T", "tail": "XL330-M077-T"}
_STRONG_SPINE = {"spine": "XC330-M181-T"}

DESIGNS: dict[str, Design] = {d.name: d for d in (
    Design("cat", "as described: XL330-M288-T everywhere at 5 V, moulded-rubber paws τ = 2 ms, 0.5 ms step"),
    Design("4ms-paw", "the cat as described until 2026-11-29: 4 ms paws (k ≈ 15 kN/m), 1 ms step", **_OLD),
    Design("fast-limbs", "4ms-paw with XL330-M077-T on legs and tail (383 rpm, 0.215 N·m)", servos=_FAST_LIMBS,
           **_OLD),
    Design("strong-spine", "4ms-paw with XC330-M181-T on the spine (129 rpm, 0.60 N·m)", servos=_STRONG_SPINE,
           **_OLD),
    Design("fast-limbs+strong-spine", "4ms-paw with both of the above", servos={**_FAST_LIMBS, **_STRONG_SPINE},
           **_OLD),
    Design("6V", "4ms-paw with XL330-M288-T at its 6 V maximum (×1.2 speed and stall torque)", volts=6.0, **_OLD),
    Design("soft-rubber-paw", "4ms-paw with soft rubber paws (Shore ≈ 30A), τ = 3 ms (k ≈ 27 kN/m)",
           **{**_OLD, "paw_tau_s": 0.003}),
    # the same changes of the described cat (2 ms paws at 0.5 ms), read against it
    Design("cat+fast-limbs", "cat with XL330-M077-T on legs and tail (383 rpm, 0.215 N·m)", servos=_FAST_LIMBS),
    Design("cat+strong-spine", "cat with XC330-M181-T on the spine (129 rpm, 0.60 N·m)", servos=_STRONG_SPINE),
    Design("cat+fast-limbs+strong-spine", "cat with both of the above", servos={**_FAST_LIMBS, **_STRONG_SPINE}),
    Design("cat+6V", "cat with XL330-M288-T at its 6 V maximum (×1.2 speed and stall torque)", volts=6.0),
)}


def get_design(name: str) -> Design:
    try:
        return DESIGNS[name]
    except KeyError:
        raise ParameterError(f"unknown design {name!r}; designs: {', '.join(DESIGNS)}") from None


def design_timestep(design: Design | str) -> float:
    """The physics step ``design`` runs at (s): its own, else the described cat's model's."""
    d = get_design(design) if isinstance(design, str) else design
    if d.timestep_s is not None:
        return d.timestep_s
    from felis.sim.robot import load_model, model_path

    return float(load_model(model_path(load_spec("cat"))).opt.timestep)


def design_library(name: str):
    """The path of design ``name``'s own motion library (the shipped library's motions with their vote taken on
    that cat: `bench/landing_revote.py`), or None: it runs the shipped library."""
    from felis.learning.landing.library import DEFAULT_LIBRARY

    own = get_design(name).library
    return None if own is None else DEFAULT_LIBRARY.parent / own


def design_robot(design: Design, base: RobotSpec | None = None):
    """(spec, servo parameters per joint or None, model edit or None) of ``design``: what `BatchLandingSim`
    takes. Without a voltage the servos are built from the spec's models as for the described cat (so the
    ``cat`` design is the described cat, bit for bit); at another voltage from the scaled figures."""
    from felis.sim.servo import servo_params

    base = base or load_spec("cat")
    design.check(base)
    joints, servo = [], {}
    for j in base.joints:
        m = servo_model(design.model_of(j.name, base))
        if design.volts is not None:
            k = design.volts / m.voltage
            m = replace(m, stall_torque=m.stall_torque * k, no_load_speed=m.no_load_speed * k)
            servo[j.name] = servo_params(m, p_gain=m.position_p_gain, m_per_rad=j.m_per_rad)
        if m.name != j.servo or design.volts is not None:
            j = replace(j, servo=m.name, max_velocity=m.no_load_speed / j.m_per_rad)
        joints.append(j)
    spec = replace(base, joints=tuple(joints))
    edit = None if design.paw_tau_s is None else paw_edit(design.paw_tau_s)
    return spec, servo or None, edit


def paw_edit(tau: float) -> Callable:
    """`mujoco.MjSpec` edit: the contact of every foot geom with the floor gets the time constant ``tau`` (solref
    ``(tau, 1)``, damping ratio 1).

    MuJoCo mixes the solref of two geoms of equal priority (a weighted average, solmix 1 each): a foot of τ against
    the model's 4 ms floor would make a contact of (τ + 4 ms)/2. So each foot also gets priority 1 (the floor and
    every other geom of the cat have 0), and a contact of a foot takes the foot's parameters as they are, friction
    included (the same as the floor's)."""

    def edit(ms) -> None:
        feet = [g for g in ms.geoms if g.name.endswith("_foot")]
        if not feet:
            raise ParameterError("the cat's model has no *_foot geoms: the paw cannot be changed")
        for g in feet:
            g.solref = [tau, 1.0]
            g.priority = 1

    return edit


def design_sim(design: Design | str, *, nthread: int | None = None, timestep: float | None = None,
               sensors: Callable | None = None):
    """`BatchLandingSim` of ``design`` (a `Design` or a name in `DESIGNS`); ``timestep``: its physics step (s;
    default the design's, else the model's); ``sensors``: an `MjSpec` edit adding sensors (after the design's own
    edit, its paws)."""
    from felis.learning.landing.evaluate import BatchLandingSim

    d = get_design(design) if isinstance(design, str) else design
    spec, servo, edit = design_robot(d)

    def edits(ms) -> None:
        if edit is not None:
            edit(ms)
        sensors(ms)

    return BatchLandingSim(spec=spec, servo=servo, nthread=nthread, sensors=edit if sensors is None else edits,
                           timestep=d.timestep_s if timestep is None else timestep)


def joint_speeds(spec: RobotSpec) -> float | np.ndarray:
    """The speed each joint's motion runs at (rad/s): its ``max_velocity``; one number when all are equal (so the
    described cat's motions are computed exactly as before designs existed)."""
    v = spec.max_velocity
    return float(v[0]) if np.all(v == v[0]) else v
