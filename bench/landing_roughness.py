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
    (tried on both: within ``radius_deg`` of each) lands p too; each probe paired with every other in the bin.

    With T the tried and L the landing matrix (probes × candidates) and M = T ∧ L, a pair (p, q) counts
    |T[p] ∧ M[q]| candidates of which |M[p] ∧ M[q]| land p too: popcounts of bit-packed rows, over the pairs a
    k-d tree finds within the widest bin (the shipped 3 m shelf: ~1.8 M ordered pairs, a few seconds)."""
    from scipy.spatial import cKDTree

    probe_up = np.asarray(probe_up, dtype=float)
    far = max(hi for _, hi in bins)
    pairs = cKDTree(probe_up).query_pairs(2.0 * math.sin(math.radians(far + 0.5) / 2.0),  # a margin: the bins
                                          output_type="ndarray")  # go by the angle, stored axes are not quite unit
    p = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    q = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    a = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", probe_up[p], probe_up[q]), -1.0, 1.0)))
    tried = np.concatenate([angles_deg(probe_up[i:i + 2048], cand_up) <= radius_deg + 1e-9
                            for i in range(0, len(probe_up), 2048)]) if len(probe_up) else np.zeros((0, len(cand_up)),
                                                                                                    dtype=bool)
    T = np.packbits(tried, axis=1)
    M = np.packbits(tried & np.asarray(lands, dtype=bool), axis=1)
    out = []
    for lo, hi in bins:
        sel = np.flatnonzero((a >= lo) & (a < hi))
        n = hit = 0
        for k in range(0, len(sel), 100_000):
            pp, qq = p[sel[k:k + 100_000]], q[sel[k:k + 100_000]]
            n += int(np.bitwise_count(T[pp] & M[qq]).sum(dtype=np.int64))
            hit += int(np.bitwise_count(M[pp] & M[qq]).sum(dtype=np.int64))
        out.append({"from_deg": lo, "to_deg": hi, "pairs": int(len(sel)), "candidates": n,
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
