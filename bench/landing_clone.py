"""Can one simple behaviour of the paper's nets reproduce a motion of the library? Regression, not evolution.

The paper's simple behaviours (seed 000 §6.3–6.5, `felis.learning.landing.policy.SimpleBehaviour`: spine, tail and
legs gene units, joint velocities from the 15 inputs IT) are evolved to imitate one motion sample. Evolution is a
search; this bench asks what the best search could give. For each of ``--n`` motions of the shipped shelf that land
their own start when tried (drawn with ``--seed`` among the entries tilted ``--tilt`` flagged landed; a flag is the
build's, so those that do not land on the described cat are skipped), the behaviour's three units (every
input, ``--hidden`` neurons) are fitted by gradient descent (torch, Adam, ``--steps``) to the motion's velocities
at each tick of its fall (outputs against ``v / max speed``, the units' tanh range), then run closed loop from the
motion's start: does it land as the motion does?

- ``--rounds R``: R rounds of DAgger: the states the fitted behaviour visits, labelled with the motion's velocity at
  that tick, join the data and the units are fitted again;
- ``--clock``: time since release as one more input (not in the paper's Table 1, which gives the nets no clock; the
  waist height Sh is their only one, and it barely moves in the first ticks of a fall): whether a clock is what a
  reactive net misses.

    python bench/landing_clone.py [--height 1] [--n 8] [--tilt 50 120] [--hidden 8] [--steps 1500] [--rounds 0] \
        [--clock] [--seed 0] [--json]

About 6 s a motion at the defaults (2 cores; ``--hidden 64`` about 20 s).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.designs import design_sim
from felis.learning.landing.library import load_library
from felis.learning.landing.library_build import tilts_deg, up_drop
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
        raise ParameterError(f"clone: needs hidden ≥ 1 and steps ≥ 0, got {hidden} and {steps}")
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


def closed_loop(sim, drop, policy, clock: bool):
    """(verdict, [(IT, t)] per tick) of ``policy`` driving the cat from ``drop`` (the landing controller's batch)."""
    from felis.controllers.landing import LandingBatch
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ
    from felis.scenarios.verdicts import landing_verdict

    seen = []

    def run(it, t, rows):
        seen.append((it.copy(), t.copy()))
        return policy(np.hstack([it, t[:, None]]) if clock else it)

    (r,) = sim.batch.run([drop], LandingBatch(sim.spec, [run]), sim.standing_waist_m, rate_hz=RATE_HZ,
                         margin_s=MARGIN_S)
    return landing_verdict(r.truth), seen


def clone(sim, drop, x: np.ndarray, hidden: int, steps: int, rounds: int = 0, clock: bool = False,
          seed: int = 0) -> dict:
    """One motion: recorded, fitted, run closed loop (with ``rounds`` of DAgger)."""
    it, v, landed = record(sim, drop, x)
    t = np.arange(len(it)) * DT
    data_x = np.hstack([it, t[:, None]]) if clock else it
    data_y = v
    for r in range(rounds + 1):
        policy, rms, _ = fit(data_x, data_y, hidden, steps, seed)
        verdict, seen = closed_loop(sim, drop, policy, clock)
        if r < rounds:  # DAgger: the visited states, labelled with the motion's velocity at their tick
            its = np.concatenate([a for a, _ in seen])
            ts = np.concatenate([b for _, b in seen])
            k = np.clip(np.rint(ts / DT).astype(int), 0, len(v) - 1)
            data_x = np.concatenate([data_x, np.hstack([its, ts[:, None]]) if clock else its])
            data_y = np.concatenate([data_y, v[k]])
    return {"open_loop_landed": landed, "ticks": len(it), "rms_rad_s": round(rms, 3),
            "clone_landed": bool(verdict.landed), "why": verdict.why or ""}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=float, default=1.0)
    ap.add_argument("--n", type=int, default=8, help="motions to clone (default 8)")
    ap.add_argument("--tilt", type=float, nargs=2, default=[50.0, 120.0], metavar=("LO", "HI"))
    ap.add_argument("--hidden", type=int, default=8, help="hidden neurons per unit (the paper's nets: 8 at most)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--rounds", type=int, default=0, help="DAgger rounds (default 0)")
    ap.add_argument("--clock", action="store_true", help="time since release as one more input")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.n < 1 or args.rounds < 0 or args.hidden < 1 or args.steps < 0:
        ap.error("--n and --hidden must be ≥ 1, --rounds and --steps ≥ 0")
    import torch

    torch.set_num_threads(1)  # small nets: threads cost more than they give
    shelf = load_library().shelf(args.height)
    t = tilts_deg(shelf.up)
    pool = np.flatnonzero(shelf.landed & (t >= args.tilt[0]) & (t < args.tilt[1]))
    if len(pool) < args.n:
        ap.error(f"only {len(pool)} motions of the {args.height:g} m shelf are flagged landed tilted {args.tilt}")
    order = np.random.default_rng(args.seed).permutation(pool)
    sim = design_sim("cat", nthread=1)
    rows, skipped = [], []
    t0 = time.perf_counter()
    try:
        for e in order:
            if len(rows) == args.n:
                break
            row = {"entry": int(e), "tilt_deg": round(float(t[e]), 1),
                   **clone(sim, up_drop(shelf.up[e], args.height), shelf.x[e], args.hidden, args.steps, args.rounds,
                           args.clock, args.seed)}
            if not row["open_loop_landed"]:  # its flag is the build's; on this cat it does not land: not a sample
                skipped.append(int(e))
                continue
            rows.append(row)
            if not args.json:
                print(f"entry {row['entry']} tilted {row['tilt_deg']:.0f}°: fitted to {row['rms_rad_s']:.2f} rad/s "
                      f"RMS, closed loop landed {row['clone_landed']} {row['why']}", flush=True)
    finally:
        sim.close()
    res = {"height_m": args.height, "hidden": args.hidden, "steps": args.steps, "rounds": args.rounds,
           "clock": args.clock, "seed": args.seed, "seconds": round(time.perf_counter() - t0),
           "motions_tried": len(rows) + len(skipped), "skipped_not_landing": skipped,
           "clone_landed": sum(r["clone_landed"] for r in rows), "motions": rows}
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{len(rows)} motions, h={args.hidden}, {args.steps} steps, {args.rounds} DAgger rounds"
          f"{', with a clock' if args.clock else ''}: the fitted behaviour lands {res['clone_landed']} of the "
          f"{len(rows)} drops its motion lands ({len(skipped)} motions skipped: they do not land their start; "
          f"{res['seconds']} s)")


if __name__ == "__main__":
    main()
