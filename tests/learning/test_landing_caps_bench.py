"""``bench/landing_caps.py``: a cap policy built from the library and evaluated against it."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import load_bench

BENCH = Path(__file__).resolve().parents[2] / "bench" / "landing_caps.py"


def test_build_then_resume_then_evaluate(tmp_path):
    """A one-centre build (a generation of two on three starts), resumed (nothing left to do: the same file), a
    resume with other settings refused in one line, one more generation (`--more`: kept only if it scores higher;
    recorded), then the evaluation of it and the library on six drops."""
    out = tmp_path / "caps.json"
    cmd = [sys.executable, str(BENCH), "--out", str(out), "--centres", "6", "--max-tilt", "60", "--train", "3",
           "--generations", "1", "--popsize", "2", "--steps", "50"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    (c,) = d["caps"]
    assert d["format"] == "felis-landing-caps" and d["settings"]["train"] == 3 and c["rollouts"] == 3 + 2 * 3
    assert 0 <= c["evolved_lands_train"] <= 3 and len(c["best_after_generation"]) == 1 and c["tilt_deg"] <= 60
    before = out.read_bytes()
    r = subprocess.run([*cmd, "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and out.read_bytes() == before and "1 behaviours" in r.stdout
    r = subprocess.run([*cmd[:-2], "--steps", "60", "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "built with other settings" in r.stderr and r.stderr.strip().count("\n") == 0
    r = subprocess.run([*cmd, "--more", "1"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d2 = json.loads(out.read_text())
    (c2,) = d2["caps"]
    assert c2["score"] >= c["score"] and len(c2["more"]) == 1 and c2["more"][0]["rollouts"] == 3 + 2 * 3
    m = c2["more"][0]
    assert m["score_before"] == c["score"] and m["lands_train_before"] == c["evolved_lands_train"]
    assert d2["more_by"] == [" ".join(cmd[2:] + ["--more", "1"])] and d2["made_by"] == d["made_by"]
    r = subprocess.run([*cmd[:3], str(tmp_path / "none.json"), *cmd[4:], "--more", "1"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1 and "--more continues a built file" in r.stderr
    ev = ["--policy", str(out), "--drops", "random:6", "--seeds", "0", "--late", "1", "--json", "--record", "six"]
    r = subprocess.run([sys.executable, str(BENCH), *ev], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    row = res["seeds"]["0"]
    assert res["behaviours"] == 1 and set(row) == {"caps", "library"}
    for v in row.values():
        assert len(v["landed"]) == 2 and all(0 <= n <= 6 for n in v["landed"])
        assert sum(b["landed"] for b in v["by_tilt"].values()) == v["landed"][0]
    kept = json.loads(out.read_text())  # --record: the evaluation in the file, its behaviours untouched
    assert kept["evaluated"]["six"] == {"command": "python bench/landing_caps.py " + " ".join(ev),
                                        **{k: v for k, v in res.items() if k != "policy"}}
    assert kept["caps"] == d2["caps"]
    r = subprocess.run([*cmd, "--more", "1"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and json.loads(out.read_text())["evaluated"] == kept["evaluated"]  # kept by --more
    r = subprocess.run([sys.executable, str(BENCH), "--out", str(out), "--record", "x"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "--record keeps an evaluation" in r.stderr


def test_neighbours_start_each_centre_from_the_best_of_its_fit_and_the_centres_built_before(tmp_path):
    """``--neighbours 2``: the first centre has nothing built before it and starts from its fit; each later one
    scores its fit and the (up to) two nearest built centres' behaviours on its training starts, starts from the
    best, records which and what it landed, and counts those rollouts; a resume with another N is refused."""
    out = tmp_path / "caps.json"
    cmd = [sys.executable, str(BENCH), "--out", str(out), "--centres", "48", "--max-tilt", "40", "--train", "2",
           "--generations", "1", "--popsize", "2", "--steps", "10", "--radius", "30", "--neighbours", "2"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    assert d["settings"]["neighbours"] == 2 and len(d["caps"]) == 3
    first, *rest = d["caps"]
    assert "start" not in first and first["rollouts"] == 2 + 2 * 2
    for k, c in enumerate(rest, start=1):
        assert c["start"] in ["fit"] + [f"centre {j + 1}" for j in range(k)], c["start"]
        assert 0 <= c["start_lands_train"] <= 2 and c["rollouts"] == 2 + 2 * 2 + 2 * min(k, 2)
        assert f"evolved (from {c['start']}, which lands {c['start_lands_train']})" in r.stdout
    r = subprocess.run([*cmd[:-1], "1", "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and "built with other settings" in r.stderr
    r = subprocess.run([*cmd, "--more", "1", "--below", "3"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr  # --more with --neighbours: from the best of its own and its 2 nearest
    for k, (a, b) in enumerate(zip(d["caps"], json.loads(out.read_text())["caps"], strict=True)):
        (m,) = b["more"]
        assert m["start"] in ["own"] + [f"centre {j + 1}" for j in range(3) if j != k], m["start"]
        assert m["rollouts"] == 2 + 2 * 2 + 2 * 2 and b["score"] >= a["score"] == m["score_before"]


def test_shift_from_starts_each_centre_from_a_lower_heights_behaviours_run_shifted(tmp_path):
    """``--shift-from FILE --height 3``: no fit; each centre starts from the best of FILE's nearest behaviours (made
    for 1 m) and its built neighbours', every one run shifted as if released from 1 m; the file records the shift and
    `felis eval landing --policy FILE` runs it shifted; a FILE of another size or not lower is one line."""
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, load_cap_policy

    out = tmp_path / "caps3.json"
    cmd = [sys.executable, str(BENCH), "--out", str(out), "--height", "3", "--centres", "48", "--max-tilt", "30",
           "--train", "2", "--generations", "1", "--popsize", "2", "--radius", "30", "--neighbours", "1",
           "--shift-from", str(SHIPPED_CAPS)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    assert d["settings"]["shift_from"] == SHIPPED_CAPS.name and d["settings"]["shift_from_m"] == 1.0
    first, second = d["caps"]
    assert "fitted_lands_train" not in first and first["start"].startswith(f"{SHIPPED_CAPS.name} centre ")
    assert second["start"] in (f"{SHIPPED_CAPS.name} centre 1", f"{SHIPPED_CAPS.name} centre 2", "centre 1")
    assert first["rollouts"] == 2 + 2 * 2 + 2 * 1 - 2 and second["rollouts"] == 2 + 2 * 2 + 2 * 1
    assert load_cap_policy(out).shift == (3.0, 1.0) and load_cap_policy(SHIPPED_CAPS).shift is None
    r = subprocess.run([sys.executable, "-m", "felis", "eval", "landing", "--policy", str(out), "--drops", "random:2",
                        "--height", "3", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and json.loads(r.stdout)["policy"] == str(out), r.stderr
    for other in (str(out), str(tmp_path / "none.json")):
        r = subprocess.run([*cmd[:3], str(tmp_path / "x.json"), *cmd[4:-1], other], capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 1 and r.stderr.strip().count("\n") == 0 and other in r.stderr, r.stderr


@pytest.mark.parametrize("text, says", [("{", "Expecting"), ('{"format": "x"}', "not a felis-landing-caps file"),
                                        ('{"format": "felis-landing-caps", "settings": {"hidden": 8}, "caps": []}',
                                         "holds no behaviour")])
def test_a_bad_caps_file_is_one_line(tmp_path, text, says):
    from felis.errors import ParameterError

    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(ParameterError, match=says):
        load_bench("landing_caps").load_caps(p)
    r = subprocess.run([sys.executable, str(BENCH), "--policy", str(p)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and str(p) in r.stderr and r.stderr.strip().count("\n") == 0


def test_a_genome_of_the_wrong_length_is_refused(tmp_path):
    from felis.errors import ParameterError

    bench = load_bench("landing_caps")
    g = np.zeros(len(bench.genome(bench.template(8))) - 1).tolist()
    p = tmp_path / "short.json"
    p.write_text(json.dumps({"format": "felis-landing-caps", "settings": {"hidden": 8},
                             "caps": [{"centre": [0, 0, 1], "genome": g}]}))
    with pytest.raises(ParameterError, match="a genome of"):
        bench.load_caps(p)
    bad = subprocess.run([sys.executable, str(BENCH)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "give --out FILE (build) or --policy FILE (evaluate)" in bad.stderr


def test_the_shipped_cap_policy_lands_what_the_docs_say():
    """`learning/weights/landing_caps-1m.json`: 9 behaviours, six evolved further; run again on `random:100` seeds 0 and
    1 from 1 m it lands what its recorded evaluation says (and by tilt), and docs/landing.md "A cap policy" and the
    README quote those counts."""
    from felis.learning.landing.evaluate import by_tilt, run_drops
    from felis.scenarios.drop import drops_from

    root = BENCH.parents[1]
    path = root / "learning" / "weights" / "landing_caps-1m.json"
    d, centres, behaviours = load_bench("landing_caps").load_caps(path)
    assert len(behaviours) == 9 and sum(1 for c in d["caps"] if c.get("more")) == 6
    assert all(c["more"][0]["score"] == c["score"] and c["more"][0]["evolved_lands_train"] == c["evolved_lands_train"]
               for c in d["caps"] if c.get("more"))
    ev = d["evaluated"]["after_more"]["seeds"]
    for s in ("0", "1"):  # as `felis eval landing --policy FILE --drops random:100 --seed S` runs it
        drops = drops_from("random:100", int(s), 1.0)
        landed = [bool(o.landed) for o in run_drops(drops, str(path))]
        assert sum(landed) == ev[s]["caps"]["landed"][0] and by_tilt(drops, landed) == ev[s]["caps"]["by_tilt"]
    before = d["evaluated"]["before_more"]["seeds"]
    text = " ".join((root / "docs" / "landing.md").read_text().split())

    def pair(e, k):
        return f"{e['0']['caps']['landed'][k]} / {e['0']['caps']['landed'][k + 1]}", \
            f"{e['1']['caps']['landed'][k]} / {e['1']['caps']['landed'][k + 1]}"

    assert (f"| cap policy, 9 behaviours, 30 generations each | {before['0']['caps']['landed'][0]} | "
            f"{before['1']['caps']['landed'][0]} |") in text
    assert "| … started 1 / 2 ticks late | {} | {} |".format(*pair(before, 1)) in text
    assert (f"| **cap policy after `--more 30 --below 12`** | **{ev['0']['caps']['landed'][0]}** | "
            f"**{ev['1']['caps']['landed'][0]}** |") in text
    assert "| … started 1 / 2 ticks late | {} | {} |".format(*pair(ev, 1)) in text
    lib = {s: ev[s]["library"]["landed"] for s in ev}
    assert lib["0"][0] == 89 and lib["1"][0] == 75  # `felis eval landing`'s figures for the library
    assert f"| … started 1 / 2 ticks late | {lib['0'][1]} / {lib['0'][2]} | {lib['1'][1]} / {lib['1'][2]} |" in text
    for name, label in (("caps", "cap policy"), ("library", "library")):
        bt = ev["0"][name]["by_tilt"]
        assert f"| {label} | " + " | ".join(f"{b['landed']}/{b['total']}" for b in bt.values()) + " |" in text
    more = {c["tilt_deg"]: (c["more"][0]["lands_train_before"], c["evolved_lands_train"]) for c in d["caps"]
            if c.get("more")}
    assert more == {29.0: (5, 12), 37.7: (8, 12), 92.4: (8, 9), 102.0: (7, 11), 107.0: (3, 7), 117.3: (2, 1)}
    assert all(c["more"][0]["score"] > c["more"][0]["score_before"] for c in d["caps"] if c.get("more"))
    for s in ("four gain 4–7 training starts (the 29° centre 5 to 12, the 107° one 3 to 7) and the 92° centre gains 1",
              "lands one start fewer (2 to 1)", "the policy gains 6 and 6", "land 53 and 39", "60 % and 52 %",
              "it lands 10 of 47 on seed 0 where the library lands 36", "it lands 43 of 53",
              "Started 2 ticks late it loses 9 and 7, where the library loses 18 and 14",
              "27 + 17 min on 2 cores", "from 4.38 to 6.70"):
        assert s in text, s
    assert round(sum(c["seconds"] for c in d["caps"]) / 60) == 27
    assert round(sum(m["seconds"] for c in d["caps"] for m in c.get("more", [])) / 60) == 17
    readme = " ".join((root / "README.md").read_text().split())
    c0, c1 = ev["0"]["caps"]["landed"], ev["1"]["caps"]["landed"]
    assert (f"From 1 m it lands {c0[0]} and {c1[0]} of `random:100` seeds 0 and 1, where the paper's evolved nets "
            f"land 26 and 19 and the library {lib['0'][0]} and {lib['1'][0]}. Started 2 ticks late it loses "
            f"{c0[0] - c0[2]} and {c1[0] - c1[2]}, the library {lib['0'][0] - lib['0'][2]} and "
            f"{lib['1'][0] - lib['1'][2]}.") in readme
    assert f"nine of them, chosen by the nearest centre, land {c0[0]} and {c1[0]} from 1 m" in readme


def _tilt_rows_in(text: str, seeds: dict, caps_label: str) -> None:
    """The docs' by-tilt rows of a recorded evaluation (``seeds``: seed → {"caps", "library"} → by_tilt)."""
    for s in ("0", "1"):
        for name, label in (("caps", caps_label), ("library", "library")):
            bt = seeds[s][name]["by_tilt"]
            assert f"| {label}, seed {s} | " + " | ".join(f"{b['landed']}/{b['total']}" for b in bt.values()) + \
                " |" in text


def test_the_shipped_24_behaviour_cap_policy_lands_what_the_docs_say():
    """`learning/weights/landing_caps48-1m.json` (``--policy caps``): built as docs/landing.md "Twenty-four behaviours"
    says, each centre recording where its evolution started; run again on `random:100` seeds 0 and 1 from 1 m through
    `felis eval landing`'s path it lands its recorded counts (and by tilt); every figure the docs and the README quote
    is recounted from the file's recorded evaluations."""
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, load_caps
    from felis.learning.landing.evaluate import by_tilt, run_drops
    from felis.scenarios.drop import drops_from

    root = BENCH.parents[1]
    assert SHIPPED_CAPS == root / "learning" / "weights" / "landing_caps48-1m.json"
    d, centres, behaviours = load_caps(SHIPPED_CAPS)
    assert d["settings"] == {"height_m": 1.0, "centres": 48, "max_tilt_deg": 180.0, "radius_deg": 42.0, "train": 16,
                             "generations": 30, "popsize": 16, "sigma": 0.1, "hidden": 8, "steps": 1500, "seed": 0,
                             "neighbours": 3}
    caps = d["caps"]
    assert len(behaviours) == 24 and "more" not in d and "start" not in caps[0]
    assert d["made_by"] == ("python bench/landing_caps.py --out learning/weights/landing_caps48-1m.json --centres 48 "
                            "--max-tilt 180 --neighbours 3")
    ev = d["evaluated"]
    for s in ("0", "1"):
        drops = drops_from("random:100", int(s), 1.0)
        landed = [bool(o.landed) for o in run_drops(drops, "caps")]
        row = ev["as_built"]["seeds"][s]["caps"]
        assert sum(landed) == row["landed"][0] and by_tilt(drops, landed) == row["by_tilt"]
    text = " ".join((root / "docs" / "landing.md").read_text().split())
    readme = " ".join((root / "README.md").read_text().split())
    a = ev["as_built"]["seeds"]
    c0, c1, l0, l1 = a["0"]["caps"]["landed"], a["1"]["caps"]["landed"], a["0"]["library"]["landed"], \
        a["1"]["library"]["landed"]
    assert (c0[0], c1[0], l0[0], l1[0]) == (90, 83, 89, 75)  # the library's: `felis eval landing`'s figures
    assert f"| **cap policy, 24 behaviours (`--policy caps`)** | **{c0[0]}** | **{c1[0]}** |" in text
    assert f"| … started 1 / 2 ticks late | {c0[1]} / {c0[2]} | {c1[1]} / {c1[2]} |" in text
    assert f"| … started 1 / 2 ticks late | {l0[1]} / {l0[2]} | {l1[1]} / {l1[2]} |" in text
    _tilt_rows_in(text, a, "cap policy")
    held = {s: (row["caps"]["landed"][0], row["library"]["landed"][0])
            for e in ("heldout_2_7", "heldout_10_12") for s, row in ev[e]["seeds"].items()}
    first = [held[str(s)][0] for s in range(2, 8)]
    lib = [held[str(s)][1] for s in range(2, 8)]
    mean, lmean = round(sum(first) / 6, 1), round(sum(lib) / 6, 1)
    later = [held[str(s)][0] for s in (10, 11, 12)]
    assert (mean, lmean) == (85.7, 70.2) and later == [89, 83, 80]
    assert ("| cap policy, 24 behaviours | " + " | ".join(map(str, first)) + f" | {mean} | "
            + " | ".join(map(str, later)) + " |") in text
    assert ("| motion library | " + " | ".join(map(str, lib)) + f" | {lmean} | "
            + " | ".join(str(held[str(s)][1]) for s in (10, 11, 12)) + " |") in text
    assert min(first + later) >= 75 and sum(x >= 75 for x in lib + [held[str(s)][1] for s in (10, 11, 12)]) == 3
    tall = ev["at_3m"]
    assert tall["height_m"] == 3.0 and tall["command"].endswith("--height 3 --late 0 --record at_3m")
    assert [tall["seeds"][s]["caps"]["landed"][0] for s in ("0", "1")] == [1, 1]
    assert [tall["seeds"][s]["library"]["landed"][0] for s in ("0", "1")] == [92, 81]  # `felis eval landing`'s
    band = [a[s]["caps"]["by_tilt"]["150-180"] for s in ("0", "1")]
    assert sum(b["landed"] for b in band) == 11 and sum(b["total"] for b in band) == 12
    # the build: where each evolution started, what the cells land
    assert sum(1 for c in caps[1:] if c["start"] != "fit") == 22 and sum(c["evolved_lands_train"] == 16
                                                                         for c in caps) == 17
    assert all(c["fitted_lands_train"] <= 1 for c in caps if c["tilt_deg"] > 86)
    weak = sorted((c["evolved_lands_train"], c["tilt_deg"]) for c in caps)[:3]
    assert weak == [(3, 88.8), (7, 148.7), (9, 121.4)]
    assert round(sum(c["seconds"] for c in caps) / 60) == 74
    assert [round(c["tilt_deg"]) for c in caps][::23] == [20, 160]
    for s in ("land 90 and 83 from 1 m", "85.7 on average on seeds 2–7", "4 of 4 and 7 of 8",
              "2 ticks late it loses 6 and 3, where the library loses 18 and 14",
              "22 of the 23 centres built after the first", "17 of 24 land all 16", "74 min on 2 cores",
              "land 1 and 1 of 100 from 3 m", "lands 11 of those 12 from 1 m"):
        assert s in text, s
    assert (c0[0] - c0[2], c1[0] - c1[2], l0[0] - l0[2], l1[0] - l1[2]) == (6, 3, 18, 14)
    for s in ("land 90 and 83 from 1 m", "85.7 on average on seeds 2–7 (the library 70.2)",
              "11 of the 12 starts tilted 150° or more", "lands 90 and 83 of `random:100` seeds 0 and 1",
              "89, 83 and 80 on seeds 10–12", "it loses 6 and 3 (the library 18 and 14)", "From 3 m it lands 1 and 1"):
        assert s in readme, s


def test_the_shipped_3m_cap_policy_lands_what_the_docs_say():
    """`learning/weights/landing_caps48-3m.json`: 24 behaviours for 3 m evolved from the 1 m ones run shifted, then
    three rounds of ``--more`` on the weak cells (docs/landing.md "The default"); run again on `random:100` seeds 0 and
    1 from 3 m through `felis eval landing`'s path (shifted, as its file says) it lands its recorded counts and by
    tilt; the docs' and the README's figures are recounted from the file."""
    from felis.learning.landing.cap_policy import SHIPPED_CAPS, load_cap_policy, load_caps
    from felis.learning.landing.evaluate import by_tilt, run_drops
    from felis.scenarios.drop import drops_from

    root = BENCH.parents[1]
    path = root / "learning" / "weights" / "landing_caps48-3m.json"
    d, _, behaviours = load_caps(path)
    build = ("--height 3 --centres 48 --max-tilt 180 --neighbours 3 --generations 10 --shift-from "
             "learning/weights/landing_caps48-1m.json")
    assert d["settings"] == {"height_m": 3.0, "centres": 48, "max_tilt_deg": 180.0, "radius_deg": 42.0, "train": 16,
                             "generations": 10, "popsize": 16, "sigma": 0.1, "hidden": 8, "steps": 1500, "seed": 0,
                             "neighbours": 3, "shift_from": SHIPPED_CAPS.name, "shift_from_m": 1.0}
    assert d["made_by"] == f"python bench/landing_caps.py --out learning/weights/landing_caps48-3m.json {build}"
    assert d["more_by"] == [f"--out /tmp/caps3m_more.json {build} --more 10 --below {n}" for n in (12, 14)]
    assert len(behaviours) == 24 and load_cap_policy(path).shift == (3.0, 1.0)
    ev = d["evaluated"]
    for s in ("0", "1"):
        drops = drops_from("random:100", int(s), 3.0)
        landed = [bool(o.landed) for o in run_drops(drops, str(path))]
        row = ev["final"]["seeds"][s]["caps"]
        assert sum(landed) == row["landed"][0] and by_tilt(drops, landed) == row["by_tilt"]
    text = " ".join((root / "docs" / "landing.md").read_text().split())
    readme = " ".join((root / "README.md").read_text().split())
    a, built = ev["final"]["seeds"], ev["as_built"]["seeds"]
    c0, c1, l0, l1 = (a["0"]["caps"]["landed"], a["1"]["caps"]["landed"], a["0"]["library"]["landed"],
                      a["1"]["library"]["landed"])
    assert (c0[0], c1[0], l0[0], l1[0]) == (69, 73, 92, 81)

    def held(name: str, policy: str) -> tuple[list, float]:
        got = [ev[name]["seeds"][str(s)][policy]["landed"][0] for s in range(2, 8)]
        return got, round(sum(got) / 6, 1)

    (caps_held, mean), (first_held, first_mean), (lib_held, lmean) = (
        held("final_heldout_2_7", "caps"), held("heldout_2_7", "caps"), held("final_heldout_2_7", "library"))
    assert (mean, first_mean, lmean) == (71.8, 66.2, 85.2)
    assert (f"| **cap policy for 3 m, shifted (`--policy learning/weights/landing_caps48-3m.json`)** | **{c0[0]}** | "
            f"**{c1[0]}** | {', '.join(map(str, caps_held))} ({mean}) |") in text
    assert (f"| … as built, before `--more` | {built['0']['caps']['landed'][0]} | {built['1']['caps']['landed'][0]} | "
            f"{', '.join(map(str, first_held))} ({first_mean}) |") in text
    assert f"| … started 1 / 2 ticks late | {c0[1]} / {c0[2]} | {c1[1]} / {c1[2]} | |" in text
    assert f"| … started 1 / 2 ticks late | {l0[1]} / {l0[2]} | {l1[1]} / {l1[2]} | |" in text
    assert f"| {l0[0]} | {l1[0]} | {', '.join(map(str, lib_held))} ({lmean}) |" in text
    _tilt_rows_in(text, a, "cap policy for 3 m")
    band = [a[s]["caps"]["by_tilt"]["150-180"]["landed"] for s in ("0", "1")]
    near = [a[s]["caps"]["by_tilt"]["0-30"]["landed"] for s in ("0", "1")]
    assert sum(band) == 10 and sum(near) == 12
    assert f"lands {c0[0]} and {c1[0]} from 3 m ({mean} on seeds 2–7), short of the library's 92 and 81" in readme
    caps = d["caps"]
    assert sum(c["start"].startswith(SHIPPED_CAPS.name) for c in caps) == 20
    assert sum(c["start_lands_train"] for c in caps) == 200 and round(sum(c["seconds"] for c in caps) / 60) == 30
    before = [c["more"][0]["lands_train_before"] if "more" in c else c["evolved_lands_train"] for c in caps]
    assert sum(before) == 298 and sum(b == 16 for b in before) == 4
    assert sum(c["evolved_lands_train"] for c in caps) == 322 and sum(len(c.get("more", [])) for c in caps) == 23
    assert round(sum(m["seconds"] for c in caps for m in c.get("more", [])) / 60) == 33
    assert max(10 + 10 * len(c.get("more", [])) for c in caps) == 40
    for words in ("20 of the 24 centres started from a shifted 1 m behaviour", "those starts land 200 of the 384 "
                  "training starts, the evolved behaviours 298, and 4 centres land all 16", "23 centre-rounds, 33 min",
                  "The training starts landed go from 298 to 322 of 384", "up to 40 on its weak cells"):
        assert words in text, words
