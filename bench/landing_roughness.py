"""How fast a landing's verdict changes with the release attitude: the limit of a motion library's choice.

A shelf of the motion library (`learning.landing.library`) records, for each probe attitude, which candidate motions
land it (the probes' verdicts are deterministic). The library picks, at release, a motion that landed the probes
nearest to the attitude the IMU reports. That choice can only be as good as a motion that lands one attitude also
landing an attitude a little away. For each pair of probes p, q at angle d, this takes the candidates that land q
and were tried on p too (within ``--radius`` of both), and counts how many also land p: the chance that "it landed
my neighbour" carries over, by d. Nothing is simulated; it reads the library file.

    python bench/landing_roughness.py [LIBRARY.json] [--height 3] [--radius 15] [--json]

If the chance stays well below 1 however close the neighbour, a denser probe grid cannot make the choice much better
(docs/landing.md, issue 21).
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from felis.learning.landing.library import DEFAULT_LIBRARY, angles_deg, load_library

BINS = ((0.0, 1.0), (1.0, 1.5), (1.5, 2.0), (2.0, 3.0), (3.0, 5.0), (5.0, 8.0))


def carry_over(probe_up: np.ndarray, lands: np.ndarray, cand_up: np.ndarray, radius_deg: float,
               bins=BINS) -> list[dict]:
    """Per bin of probe-to-probe angle: pairs, and the share of (pair, candidate) where a candidate that lands q
    (tried on both: within ``radius_deg`` of each) lands p too; each probe paired with every other in the bin."""
    a = angles_deg(probe_up, probe_up)
    np.fill_diagonal(a, np.inf)
    tried = angles_deg(probe_up, cand_up) <= radius_deg + 1e-9
    out = []
    for lo, hi in bins:
        p, q = np.nonzero((a >= lo) & (a < hi))
        both = tried[p] & tried[q] & lands[q]
        n = int(both.sum())
        hit = int((both & lands[p]).sum())
        out.append({"from_deg": lo, "to_deg": hi, "pairs": int(len(p)), "candidates": n,
                    "lands_too": round(hit / n, 3) if n else None})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("library", nargs="?", default=str(DEFAULT_LIBRARY))
    ap.add_argument("--height", type=float, default=3.0)
    ap.add_argument("--radius", type=float, default=15.0, help="a candidate counts as tried on a probe "
                    "this close (deg; default 15: the build tries 30°, --add-probes 15°, so every probe had those)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    lib = load_library(args.library)
    shelf = next((s for s in lib.shelves if math.isclose(s.height_m, args.height, rel_tol=1e-6)), None)
    if shelf is None:
        raise SystemExit(f"landing_roughness: {args.library} has no shelf at {args.height:g} m")
    cand_up = shelf.candidates()[0]
    rows = carry_over(shelf.probe_up, shelf.lands, cand_up, args.radius)
    if args.json:
        print(json.dumps({"library": args.library, "height_m": args.height, "probes": len(shelf.probe_up),
                          "bins": rows}, indent=2))
        return
    print(f"landing_roughness: {args.library}, {args.height:g} m shelf, {len(shelf.probe_up)} probes, "
          f"{len(cand_up)} candidates")
    print("  probes apart      pairs   (pair, candidate)   a motion that lands one lands the other")
    for r in rows:
        share = "–" if r["lands_too"] is None else f"{r['lands_too']:.3f}"
        print(f"  {r['from_deg']:4.1f}–{r['to_deg']:<4.1f}°  {r['pairs']:9d}   {r['candidates']:17d}   {share}")


if __name__ == "__main__":
    main()
