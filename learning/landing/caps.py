"""Closed-loop landing behaviours imitated from the library's motions, then evolved over a cap of starts (issue 21).

The shipped policy (`felis.learning.landing.library`) runs an open-loop motion chosen at release; the paper's
controller is a few closed-loop simple behaviours (seed 000 §6.2–6.5, `felis.learning.landing.policy`) that a compose
net dispatches. This module makes such behaviours from the library and measures them:

1. **Imitate** (`record`, `fit`): a library motion is run open loop from its start and, at each 10 ms tick, the
   nets' inputs IT (15) and the motion's joint velocities v (12) are kept; the behaviour's spine, tail and legs units
   (every input, h hidden neurons) are fitted by Adam to v/v_max (their tanh range), least squares.
2. **Evolve** (`evolve`): CMA-ES (`cma`) over the behaviour's weights from the fitted ones, maximising the mean
   score over drops of a cap round the motion's start (`cap_drops`); the score is the per-drop optimum's
   (`felis.learning.landing.optimum.score`: training's landing fitness, 3 more for a landing), every population a
   single batch of the simulation (`run_population`).
3. **Dispatch** (`felis.learning.landing.cap_policy`, the inference side that controllers import: `CapPolicy` for a
   batch, `CapRule` for one cat, the file format): behaviours evolved over caps round K centres; at release each cat
   takes the behaviour whose centre is nearest the up axis its IMU reports, mirrored (`mirror_inputs`,
   `mirror_velocities`) for a start in the other half of the sphere, as the library's shelves are.

`Late` starts any of these k ticks late (the joints held meanwhile): the latency a servo bus adds.

A cap of radius ρ round the unit up axis c: the up axes u with ∠(u, c) ≤ ρ; drawn uniformly over its area, cos ∠
is uniform on [cos ρ, 1]. The up axis of a start (roll r, pitch p) in the body frame is u = (−sin p, cos p sin r,
cos p cos r) (`felis.learning.landing.library`), whatever the yaw.
"""

from __future__ import annotations

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.cap_policy import CapPolicy, genome, nearest_centre, with_genome
from felis.learning.landing.library_build import up_drop
from felis.learning.landing.motion import DT  # the control tick (s): a motion's table has one row a tick
from felis.learning.landing.optimum import evaluate
from felis.learning.landing.policy import KINDS, MAX_SPEED, PARTS, GeneUnit, SimpleBehaviour


def fit(it: np.ndarray, v: np.ndarray, hidden: int, steps: int, seed: int = 0, lr: float = 1e-2):
    """Fit a simple behaviour's units to velocities ``v`` (N, 12; rad/s) at inputs ``it`` (N, 15, or 16 with a clock
    column): spine from the inputs, tail and legs from the inputs and the spine's raw outputs, as
    `felis.learning.landing.policy.SimpleBehaviour` runs them. Returns (policy: inputs (B, n) → velocities (B, 12),
    the RMS error in rad/s, the `SimpleBehaviour` when ``it`` is IT alone, else None)."""
    import torch

    if hidden < 1 or steps < 0:
        raise ParameterError(f"caps: needs hidden ≥ 1 and steps ≥ 0, got {hidden} and {steps}")
    torch.manual_seed(seed)
    x = torch.tensor(it, dtype=torch.float64)
    y = torch.tensor(np.clip(v / MAX_SPEED, -0.995, 0.995))
    n = x.shape[1]
    nets = {p: torch.nn.Sequential(torch.nn.Linear(n + (p != "spine") * 2, hidden), torch.nn.Tanh(),
                                   torch.nn.Linear(hidden, len(KINDS[p].outputs)), torch.nn.Tanh()).double()
            for p in PARTS}

    def forward(x):
        s = nets["spine"](x)
        xs = torch.cat([x, s], 1)
        return torch.cat([s, nets["tail"](xs), nets["legs"](xs)], 1)

    opt = torch.optim.Adam([w for m in nets.values() for w in m.parameters()], lr=lr)
    for _ in range(steps):
        loss = ((forward(x) - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        rms = float(((forward(x) - y) ** 2).mean().sqrt()) * MAX_SPEED

    def policy(inputs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return MAX_SPEED * forward(torch.tensor(inputs, dtype=torch.float64)).numpy()

    behaviour = None
    if n == KINDS["spine"].n_available:
        units = []
        for p in PARTS:
            a, b = nets[p][0], nets[p][2]
            w1 = np.hstack([a.weight.detach().numpy(), a.bias.detach().numpy()[:, None]])
            w2 = np.hstack([b.weight.detach().numpy(), b.bias.detach().numpy()[:, None]])
            units.append(GeneUnit(p, tuple(range(KINDS[p].n_available)), hidden, w1, w2, MAX_SPEED))
        behaviour = SimpleBehaviour(*units).check()
        policy = behaviour.velocities_many  # the paper's behaviour itself, as the controller runs it
    return policy, rms, behaviour


def record(sim, drop, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(IT (N, 15), velocities (N, 12), landed) of the open-loop motion ``x`` on ``drop``, tick by tick."""
    seen = []

    def wrap(policy, rows):
        def recorded(it, t, rows):
            v = policy(it, t, rows)
            seen.append((it[0].copy(), v[0].copy()))
            return v
        return recorded

    ((_, verdict),) = evaluate(sim, [drop], x[None], wrap=wrap)
    return np.array([a for a, _ in seen]), np.array([b for _, b in seen]), bool(verdict.landed)


def cap_drops(u: np.ndarray, deg: float, n: int, height_m: float, rng: np.random.Generator) -> list:
    """``n`` drops (yaw 0, `up_drop`) whose up axes are uniform over the spherical cap of radius ``deg`` round the
    unit vector ``u``: cos of the angle to ``u`` uniform in [cos deg, 1], the direction round it uniform."""
    u = np.asarray(u, dtype=float) / np.linalg.norm(u)
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    c = rng.uniform(np.cos(np.radians(deg)), 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1.0 - c * c)
    ups = c[:, None] * u + s[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return [up_drop(v, height_m) for v in ups]


def cell_drops(centres: np.ndarray, k: int, deg: float, n: int, height_m: float, rng: np.random.Generator) -> list:
    """``n`` drops (yaw 0) of centre ``k``'s cell within ``deg`` of it: starts drawn uniformly over that cap,
    mirrored into u_y ≥ 0, kept when ``k`` is their nearest centre (the starts `CapPolicy` gives its behaviour).
    ParameterError when a few thousand draws do not give ``n`` (a cap that misses the cell)."""
    from felis.learning.landing.library import drop_up

    out: list = []
    for _ in range(64):
        ds = cap_drops(centres[k], deg, max(4 * n, 64), height_m, rng)
        u = np.array([drop_up(d) for d in ds])
        u[:, 1] = np.abs(u[:, 1])
        out += [up_drop(v, height_m) for v in u[nearest_centre(centres, u) == k]]
        if len(out) >= n:
            return out[:n]
    raise ParameterError(f"caps: the cap of {deg:g}° round centre {k} holds fewer than {n} starts of its cell")


class Late:
    """A landing policy started ``ticks`` control ticks late: the joints held (velocity 0) until then, then the
    policy as if released then (an open-loop motion's clock shifted; a behaviour reads the state it finds), as a
    servo bus's latency delays it (`felis.learning.landing.optimum.evaluate`'s ``late_ticks``)."""

    def __init__(self, policy, ticks: int):
        self.policy, self.delay = policy, ticks * DT

    def __call__(self, it: np.ndarray, t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        v = np.zeros((len(it), 12))
        on = t >= self.delay - 1e-9
        if on.any():
            f = getattr(self.policy, "velocities_many", None)
            v[on] = f(it[on]) if callable(f) else self.policy(it[on], t[on] - self.delay, rows[on])
        return v


def run_population(sim, behaviours, drops, late_ticks: int = 0,
                   shift: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(scores, landed), each (len(behaviours), len(drops)): every behaviour closed loop on every drop, one batch
    (each started ``late_ticks`` late, `Late`; with ``shift`` (H, h₁), run shifted as a cap policy's behaviours made
    for h₁ run from H, `felis.learning.landing.cap_policy`); the score is the per-drop optimum's
    (`felis.learning.landing.optimum.score`: training's landing fitness, 3 more for a landing). The drops' up axes
    must have u_y ≥ 0 under ``shift`` (each behaviour runs as a one-centre cap policy, which mirrors the others)."""
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ
    from felis.learning.landing.optimum import score

    P, D = len(behaviours), len(drops)
    policies = list(behaviours)
    if shift is not None:
        policies = [CapPolicy(np.array([[0.0, 1.0, 0.0]]), [b], shift) for b in policies]
    if late_ticks:
        policies = [Late(b, late_ticks) for b in policies]
    ctl = LandingBatch(sim.spec, policies, np.repeat(np.arange(P), D))
    batch = sim.batch.run(list(drops) * P, ctl, sim.standing_waist_m, rate_hz=RATE_HZ, margin_s=MARGIN_S)
    scored = [score(r, sim.standing_waist_m) for r in batch]
    return (np.array([f for f, _ in scored]).reshape(P, D),
            np.array([bool(v.landed) for _, v in scored]).reshape(P, D))


def evolve(sim, start: SimpleBehaviour, drops, generations: int, popsize: int, sigma: float, seed: int = 0,
           shift: tuple[float, float] | None = None):
    """CMA-ES (`cma`) over ``start``'s weights, from them, maximising the mean score over ``drops`` (run shifted with
    ``shift``, `run_population`); the fitted start is scored too and kept if nothing beats it. Returns (best
    behaviour, its mean score, rollouts, the best mean score after each generation)."""
    import cma

    if generations < 1 or popsize < 2 or not sigma > 0:
        raise ParameterError(f"caps: evolution needs generations ≥ 1, popsize ≥ 2, sigma > 0; got {generations}, "
                             f"{popsize}, {sigma}")
    g0 = genome(start)
    best, best_f = start, float(run_population(sim, [start], drops, shift=shift)[0].mean())
    rollouts, history = len(drops), []
    es = cma.CMAEvolutionStrategy(g0, sigma, {"popsize": popsize, "seed": seed + 1, "verbose": -9})
    for _ in range(generations):
        gs = es.ask()
        pop = [with_genome(start, np.asarray(g)) for g in gs]
        f = run_population(sim, pop, drops, shift=shift)[0].mean(axis=1)
        rollouts += f.size * len(drops)
        es.tell(gs, (-f).tolist())
        i = int(np.argmax(f))
        if f[i] > best_f:
            best, best_f = pop[i], float(f[i])
        history.append(round(best_f, 4))
    return best, best_f, rollouts, history


