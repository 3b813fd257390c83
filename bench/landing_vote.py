"""A landing policy by attitude: a vote between whole policies (the motion library, a cap policy) taken on training
drops, chosen at release by the start's up axis (issue 21; `felis.learning.landing.by_attitude`).

Build (``--out FILE``): every part (``--parts``: ``library`` or caps files, the fallback first) is run on ``--drops``
(``random:400``) for each ``--train-seeds`` S from ``--height``; the file keeps each drop's up axis and which parts
landed it. σ is the one of ``--sigmas`` whose vote lands most when each training seed in turn is left out and
voted on by the others (leave-one-seed-out); the file records that table. No evaluation seed is used.

Evaluate (``--policy FILE``): on ``--drops`` (``random:100``) for each ``--seeds`` S (0 and 1 by default) from the
file's height: each part alone and the vote, batched (`felis.learning.landing.by_attitude.ByAttitude`), landed of
the drops by the one verdict, by start tilt; ``--record NAME`` keeps it in the file. ``--compose H`` also runs the
paper's compose net as the dispatcher (eq. 1: a gene unit on Sy1, Sy2 with H hidden neurons, its s1 binned into the
two parts by `dispatch_index`), fitted to the file's training drops (Adam, which part lands where only one does) and
evolved on them from random weights (CMA-ES, 3 restarts); its choice is made at release, so each evaluation drop
lands as its chosen part alone lands it.

    python bench/landing_vote.py --out FILE --height 3 --parts library landing_caps48-3m.json \\
        [--train-seeds 100 101 102 103 104 105] [--drops random:400] [--sigmas 4 6 8 10 12 15 20]
    python bench/landing_vote.py --policy FILE [--drops random:100] [--seeds 0 1] [--record NAME] [--json] \
        [--compose H]

Parts other than ``library`` are caps files in the folder of ``--out``. The build takes about 30 s a training seed
and part on 2 cores from 3 m (400 drops); the evaluation about 30 s a seed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from felis.errors import ParameterError
from felis.learning.landing.by_attitude import FORMAT, Vote, load_vote, vote, vote_batch
from felis.learning.landing.cap_policy import load_cap_policy, load_caps
from felis.learning.landing.designs import design_sim, joint_speeds
from felis.learning.landing.library import LibraryBatch, drop_up, load_library
from felis.scenarios.drop import drops_from


def _run(sim, drops, policy) -> list[bool]:
    from felis.controllers.landing import LandingBatch

    return [bool(o.landed) for o in sim.run(drops, LandingBatch(sim.spec, [policy]))]


def _n_ticks(drops) -> int:
    from felis.learning.landing.evaluate import MARGIN_S, RATE_HZ

    return max(int(round((x.fall_time + MARGIN_S) * RATE_HZ)) for x in drops)


def _part(name: str, folder: Path, lib, sim, drops):
    if name == "library":
        return LibraryBatch(lib, [x.height_m for x in drops], _n_ticks(drops), joint_speeds(sim.spec))
    return load_cap_policy(folder / name)


def loso(ups: list[np.ndarray], landed: list[np.ndarray], sigma: float) -> int:
    """Drops landed, over the training seeds, when each seed's drops are voted on by the other seeds' (σ degrees)."""
    total = 0
    for i in range(len(ups)):
        p = np.vstack([u for j, u in enumerate(ups) if j != i])
        lnd = np.vstack([x for j, x in enumerate(landed) if j != i])
        k = vote(p, lnd, sigma, ups[i])
        total += int(landed[i][np.arange(len(k)), k].sum())
    return total


def build(args) -> None:
    out = Path(args.out)
    folder = out.parent
    for name in args.parts:
        if name != "library":
            if Path(name).name != name:
                raise ParameterError(f"landing vote: --parts {name}: name a caps file in {folder}, not a path")
            load_caps(folder / name)
    if len(args.parts) < 2:
        raise ParameterError("landing vote: --parts needs at least two policies (the fallback first)")
    lib = load_library()
    sim = design_sim("cat")
    t0 = time.perf_counter()
    ups, landed = [], []
    try:
        for s in args.train_seeds:
            drops = drops_from(args.drops, s, args.height)
            cols = [_run(sim, drops, _part(name, folder, lib, sim, drops)) for name in args.parts]
            ups.append(np.array([drop_up(x) for x in drops]))
            landed.append(np.array(cols, dtype=int).T)
            print(f"seed {s}: " + ", ".join(f"{n} {int(c)}" for n, c in zip(args.parts, landed[-1].sum(0),
                                                                              strict=True))
                  + f"; one or another {int(landed[-1].any(1).sum())} of {len(drops)}", flush=True)
    finally:
        sim.close()
    cv = {f"{s:g}": loso(ups, landed, s) for s in args.sigmas}
    sigma = float(args.sigmas[int(np.argmax([cv[f"{s:g}"] for s in args.sigmas]))])
    P, L = np.vstack(ups), np.vstack(landed)
    Vote(P, L, sigma)  # checks
    doc = {"format": FORMAT, "version": 1, "made_by": "python bench/landing_vote.py " + " ".join(args.argv),
           "height_m": args.height, "parts": list(args.parts), "sigma_deg": sigma,
           "training": {"drops": args.drops, "seeds": args.train_seeds,
                        "landed": {n: int(c) for n, c in zip(args.parts, L.sum(0), strict=True)},
                        "one_or_another": int(L.any(1).sum()), "total": len(L),
                        "leave_one_seed_out": cv, "seconds": round(time.perf_counter() - t0)},
           "probes": {"up": [[round(float(x), 9) for x in u] for u in P], "landed": L.tolist()}}
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(json.dumps(doc, separators=(",", ":")))
    tmp.replace(out)
    load_vote(out)
    print(f"{out}: σ = {sigma:g}° (leave-one-seed-out landed: {cv}); {len(L)} probes, "
          f"{doc['training']['seconds']} s")


def compose_inputs(u: np.ndarray) -> np.ndarray:
    """IT (N, 15) of cats released with up axes ``u``, mirrored into u_y ≥ 0: roll / π and pitch / (π/2), the rest 0
    (a compose unit on Sy1, Sy2 reads only those)."""
    from felis.learning.landing.by_attitude import fold

    u = fold(u)
    it = np.zeros((len(u), 15))
    it[:, 4] = np.arctan2(u[:, 1], u[:, 2]) / np.pi
    it[:, 5] = -np.arcsin(np.clip(u[:, 0], -1.0, 1.0)) / (np.pi / 2)
    return it


def compose_unit(w: np.ndarray, hidden: int):
    """The paper's compose gene unit (`felis.learning.landing.policy.GeneUnit`, kind ``compose``) on Sy1, Sy2 with
    ``hidden`` neurons: ``w`` its W1 (hidden × 3) then the first output's row of W2 (hidden + 1); s2 and s3, the
    per-part signals, are 0 (the parts here are whole policies)."""
    from felis.learning.landing.policy import GeneUnit

    w1 = w[:hidden * 3].reshape(hidden, 3)
    w2 = np.zeros((3, hidden + 1))
    w2[0] = w[hidden * 3:]
    return GeneUnit("compose", (4, 5), hidden, w1, w2, 1.0).check()


def compose_choice(unit, u: np.ndarray) -> np.ndarray:
    """The part (0 or 1) the compose unit dispatches each up axis to: `dispatch_index` of its s1 over 2 parts."""
    from felis.learning.landing.policy import dispatch_index

    return dispatch_index(unit.raw_many(compose_inputs(u))[:, 0], 2)


def fit_compose(up: np.ndarray, landed: np.ndarray, hidden: int, steps: int = 4000, seed: int = 0):
    """A compose unit fitted (Adam, logistic loss) to say, for each training drop only one part lands, which one."""
    import torch

    torch.manual_seed(seed)
    x = torch.tensor(compose_inputs(up)[:, 4:6])
    y = torch.tensor((landed[:, 1] > landed[:, 0]).astype(float))
    m = torch.tensor((landed[:, 1] != landed[:, 0]).astype(float))
    net = torch.nn.Sequential(torch.nn.Linear(2, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, 1)).double()
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(steps):  # s1 = tanh(z): the logit 5 z keeps s1 off its flat ends
        z = 5.0 * torch.tanh(net(x)[:, 0])
        loss = (m * torch.nn.functional.binary_cross_entropy_with_logits(z, y, reduction="none")).sum() / m.sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    a, b = net[0], net[2]
    w = np.concatenate([np.hstack([a.weight.detach().numpy(), a.bias.detach().numpy()[:, None]]).ravel(),
                        b.weight.detach().numpy().ravel(), b.bias.detach().numpy()])
    return compose_unit(w, hidden)


def evolve_compose(up: np.ndarray, landed: np.ndarray, hidden: int, generations: int = 150, popsize: int = 24,
                   restarts: int = 3, seed: int = 0):
    """A compose unit evolved from random weights by CMA-ES (`cma`, restarts), maximising the training drops landed
    with the dispatch softened (a logistic of 20 s1), the best of the restarts by drops landed."""
    import cma

    it = compose_inputs(up)
    n = hidden * 3 + hidden + 1
    rng = np.random.default_rng(seed)
    best = None
    for r in range(restarts):
        def f(w):
            s = compose_unit(np.asarray(w), hidden).raw_many(it)[:, 0]
            q = 1.0 / (1.0 + np.exp(-20.0 * s))
            return -float(((1 - q) * landed[:, 0] + q * landed[:, 1]).sum())
        es = cma.CMAEvolutionStrategy(rng.normal(0.0, 0.5, n), 0.3,
                                      {"popsize": popsize, "seed": seed + 1 + r, "verbose": -9})
        for _ in range(generations):
            ws = es.ask()
            es.tell(ws, [f(w) for w in ws])
        unit = compose_unit(np.asarray(es.result.xbest), hidden)
        got = int(landed[np.arange(len(up)), compose_choice(unit, up)].sum())
        if best is None or got > best[0]:
            best = (got, unit)
    return best[1]


def evaluate_vote(args) -> dict:
    from felis.learning.landing.evaluate import by_tilt

    d, v, _ = load_vote(args.policy)
    h = float(d["height_m"])
    units = {}
    if args.compose:  # the paper's compose net on the vote's training drops, fitted and evolved (2 parts)
        if v.parts != 2:
            raise ParameterError(f"landing vote: --compose dispatches between 2 parts; {args.policy} has {v.parts}")
        units = {"compose_fitted": fit_compose(v.probes, v.landed, args.compose),
                 "compose_evolved": evolve_compose(v.probes, v.landed, args.compose)}
    lib = load_library()
    sim = design_sim("cat")
    res = {"policy": str(args.policy), "height_m": h, "drops": args.drops, "parts": d["parts"], "seeds": {}}
    if units:
        res["compose"] = {"hidden": args.compose, "training_landed": {
            k: int(v.landed[np.arange(len(v.probes)), compose_choice(x, v.probes)].sum()) for k, x in units.items()}}
    try:
        for s in args.seeds:
            drops = drops_from(args.drops, s, h)
            row = {}
            parts_landed = []
            for name in d["parts"]:
                got = _run(sim, drops, _part(name, Path(args.policy).parent, lib, sim, drops))
                parts_landed.append(got)
                row[name] = {"landed": sum(got), "by_tilt": by_tilt(drops, got)}
            pol = vote_batch(args.policy, lib, [x.height_m for x in drops], _n_ticks(drops), joint_speeds(sim.spec))
            got = _run(sim, drops, pol)
            chose = np.bincount(v.choose(np.array([drop_up(x) for x in drops])), minlength=v.parts)
            row["vote"] = {"landed": sum(got), "by_tilt": by_tilt(drops, got),
                           "chose": {n: int(c) for n, c in zip(d["parts"], chose, strict=True)}}
            ups = np.array([drop_up(x) for x in drops])
            for name, unit in units.items():  # its choice is made at release: each drop lands as its part alone
                k = compose_choice(unit, ups)
                row[name] = {"landed": int(sum(parts_landed[j][i] for i, j in enumerate(k))),
                             "chose": {n: int(c) for n, c in zip(d["parts"], np.bincount(k, minlength=2), strict=True)}}
            res["seeds"][str(s)] = row
    finally:
        sim.close()
    return res


def record_evaluation(path: str, name: str, res: dict, argv: str) -> None:
    """Keep an evaluation in the vote file, under ``evaluated[name]`` with its command (written whole, atomically)."""
    p = Path(path)
    d = json.loads(p.read_text())
    d.setdefault("evaluated", {})[name] = {"command": "python bench/landing_vote.py " + argv,
                                            **{k: v for k, v in res.items() if k != "policy"}}
    tmp = p.with_suffix(p.suffix + ".tmp")
    tmp.write_text(json.dumps(d, separators=(",", ":")))
    tmp.replace(p)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="build a vote into this file")
    ap.add_argument("--policy", help="evaluate the vote of this file")
    ap.add_argument("--height", type=float, default=3.0, help="build: the drop height (m, default 3)")
    ap.add_argument("--parts", nargs="+", default=["library", "landing_caps48-3m.json"],
                    help="build: the policies voted between, the fallback first (library, or caps files beside --out)")
    ap.add_argument("--train-seeds", type=int, nargs="+", default=[100, 101, 102, 103, 104, 105])
    ap.add_argument("--sigmas", type=float, nargs="+", default=[4, 6, 8, 10, 12, 15, 20])
    ap.add_argument("--drops", help="random:N draws (build: random:400, evaluate: random:100)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--record", metavar="NAME", help="with --policy FILE: keep the evaluation in FILE")
    ap.add_argument("--compose", type=int, default=0, metavar="H",
                    help="with --policy FILE: also the paper's compose net (a gene unit on Sy1, Sy2 with H hidden "
                    "neurons) as the dispatcher, fitted to the file's training drops and evolved on them from random "
                    "weights; each lands its choices as the parts alone land them")
    args = ap.parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)
    if (args.out is None) == (args.policy is None):
        ap.error("give --out FILE (build) or --policy FILE (evaluate)")
    if not 0 < args.height <= 20 or not all(0 < s <= 90 for s in args.sigmas):
        ap.error("--height must be in (0, 20] m and each of --sigmas in (0, 90]°")
    if args.record is not None and args.policy is None:
        ap.error("--record keeps an evaluation: give --policy FILE")
    if args.compose < 0 or (args.compose and args.policy is None):
        ap.error("--compose H (≥ 1) evaluates a compose net with --policy FILE")
    if args.out and len(args.train_seeds) < 2:
        ap.error("--train-seeds: σ is chosen leaving one seed out, so give at least two")
    args.drops = args.drops or ("random:400" if args.out else "random:100")
    if not args.drops.startswith("random:"):
        ap.error("--drops: random:N")
    if args.compose:
        import torch

        torch.set_num_threads(1)  # a small net: threads cost more than they give
    try:
        if args.out:
            build(args)
            return
        res = evaluate_vote(args)
        if args.record:
            record_evaluation(args.policy, args.record, res, " ".join(args.argv))
    except ParameterError as e:
        raise SystemExit(str(e)) from None
    if args.json:
        print(json.dumps(res, indent=1))
        return
    print(f"{res['policy']}: {args.drops} from {res['height_m']:g} m, landed")
    for s, row in res["seeds"].items():
        print(f"  seed {s}: " + ", ".join(f"{n} {r['landed']}" for n, r in row.items())
              + f" (the vote chose {row['vote']['chose']})")
    if "compose" in res:
        print(f"  compose nets ({res['compose']['hidden']} hidden) on the training drops: "
              f"{res['compose']['training_landed']}")


if __name__ == "__main__":
    main()
