"""Smoke test of ``bench/landing_study.py`` (the §6.6 reproduction): a tiny budget, one seed, every
experiment and baseline present in the results and the table. Numbers at this budget mean nothing."""

import json

import numpy as np
import pytest
from conftest import load_bench

TINY = {"population": 3, "exp1_generations": 1, "generations_simple": 1, "generations_complex": 1}


@pytest.fixture(scope="module")
def bench():
    return load_bench("landing_study")


def _shipped(name: str) -> dict:
    from pathlib import Path

    return json.loads((Path(__file__).parents[2] / "learning" / "weights" / name).read_text())


def _docs() -> str:
    from pathlib import Path

    return (Path(__file__).parents[2] / "docs" / "landing.md").read_text()


def _ahead(res: dict, g: int) -> tuple[int, int]:
    """Seed × orientation pairs where experiment 1's best with similarity is above / below f alone's after ``g``."""
    pairs = [(a[g - 1], b[g - 1]) for row in res["seeds"].values()
             for a, b in zip(row["exp1 f+similarity"]["best_f"], row["exp1 f"]["best_f"], strict=True)]
    return sum(a > b for a, b in pairs), sum(a < b for a, b in pairs)


# The paper's spine samples (the bench's default) and the 24 whole-body ones run in `make test-slow`: the study's
# code is the same for every sample set but the choice of the 7, and the training tests load the spine samples.
# The library's samples too (26 s): the default suite keeps the shipped study's figures (below).
@pytest.mark.parametrize("samples", [pytest.param("spine", marks=pytest.mark.slow),
                                     pytest.param("wholebody", marks=pytest.mark.slow),
                                     pytest.param("library", marks=pytest.mark.slow)])
def test_tiny_study_has_every_experiment_and_baseline(bench, tmp_path, samples):
    res = bench.study([5], TINY, workers=1, tmp=tmp_path, samples_file=bench.SAMPLES[samples])
    row = res["seeds"]["5"]
    if samples != "spine":
        from felis.learning.landing.samples import load_samples

        got = load_samples(bench.SAMPLES[samples])
        if samples == "wholebody":  # the 7 whole-body samples nearest the paper's 7 orientations stand in for them
            assert len(res["training"]) == 7 and all(list(map(float, got[i].orientation)) in res["training"]
                                                     for i in bench.nearest_samples(got, [(180, 0, 0)]))
        else:  # 7 samples that land stand in order
            assert res["training"] == [list(map(float, s.orientation)) for s in got] and all(s.landed for s in got)
    for name in ("f", "f+similarity"):  # experiment 1: orientations 1 and 4, generations or None (never)
        first = row[f"exp1 {name}"]["first_landed"]
        assert len(first) == 2 and all(g is None or g == 1 for g in first)
        assert [len(c) for c in row[f"exp1 {name}"]["best_f"]] == [1, 1]
    for exp, n in (("exp2", 7), ("exp3", 4)):
        for name in ("one-net", "simple-complex"):
            r = row[f"{exp} {name}"]
            assert r["of"] == n and 0 <= r["landed"] <= n and 0 <= r["upright"] <= n
            assert r["per_drop"].count(True) == r["landed"]
    assert set(res["baselines"]) == {"passive", "rules", "shipped"}
    assert res["baselines"]["passive"]["training"]["landed"] == 0  # 3 m, tilted ≥ 90°: nothing lands held still
    text = bench.table(res)
    assert "(1) f+similarity: generations to first landing" in text
    assert "| (2) baseline shipped: landed (upright) of 7 training orientations |" in text
    assert "| (3) baseline passive: landed (upright) of 4 untrained orientations |" in text
    assert "(1) f: best f after 1 generations" in text
    assert text.count("| seed 5 |") == 1
    json.dumps(res)  # what --json writes


def test_the_shipped_study_on_samples_that_land_says_what_the_docs_say():
    """docs/landing.md and the README, from `learning/weights/landing_study_library.json` (made by
    `bench/landing_study.py --samples library`, on the samples of the library extended beyond 100°): similarity
    lifts the best f after 30 generations in 4 of the 6 seed × orientation pairs, and nothing lands in experiment
    1, 2 or 3."""
    res = _shipped("landing_study_library.json")
    assert res["samples"].endswith("landing_samples_library.json") and sorted(res["seeds"]) == ["0", "1", "2"]
    assert res["budget"]["exp1_generations"] == 30 and res["budget"]["population"] == 16
    ahead = 0
    for row in res["seeds"].values():
        f, fs = row["exp1 f"], row["exp1 f+similarity"]
        ahead += sum(a[-1] > b[-1] for a, b in zip(fs["best_f"], f["best_f"], strict=True))
        assert f["first_landed"] == fs["first_landed"] == [None, None]
        assert all(row[f"{e} {n}"]["landed"] == 0 for e in ("exp2", "exp3") for n in ("one-net", "simple-complex"))
    assert ahead == 4


def test_the_library_samples_are_picked_on_the_cat_the_study_runs_on(bench):
    """`--samples library` takes the samples picked on `--design`'s cat (a motion that lands a start on one cat
    need not land it on another); each file says which cat, and the command that made it names the file."""
    from pathlib import Path

    from felis.learning.landing.samples import load_samples

    assert set(bench.LIBRARY_SAMPLES) == {"cat", "4ms-paw"}
    for design, path in bench.LIBRARY_SAMPLES.items():
        doc = json.loads(Path(path).read_text())
        assert doc["design"] == design and f"'learning/weights/{Path(path).name}'" in doc["command"]
        got = load_samples(path)
        assert len(got) == 7 and all(s.landed for s in got)
        assert all(e["angle_to_target_deg"] <= 31 for e in doc["samples"])


def test_a_study_on_an_unknown_design_or_one_without_samples_is_one_line():
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).parents[2] / "bench" / "landing_study.py"
    for argv, says in ((["--design", "cat-x"], "unknown design 'cat-x'"),
                       (["--design", "6V", "--samples", "library"], "no library samples picked on 6V"),
                       (["--exp1-generations", "0"], "--exp1-generations must be at least 1, got 0"),
                       (["--generations-complex", "-2"], "--generations-complex must be at least 1, got -2"),
                       (["--fitness", "eq10"], "argument --fitness: invalid choice: 'eq10'")):
        r = subprocess.run([sys.executable, str(script), *argv], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_study_on_the_described_cat_in_the_docs_is_the_shipped_run(bench):
    """docs/landing.md's table of the study on the described cat (2 ms paws at 0.5 ms, samples picked on it) is
    `table` of `learning/weights/landing_study_library_cat.json` (made by `bench/landing_study.py --samples library
    --design cat --json ...`), row for row, and its reading counts what the file holds."""
    res = _shipped("landing_study_library_cat.json")
    assert res["design"] == "cat" and res["samples"] == "learning/weights/landing_samples_library_cat.json"
    assert res["budget"] == bench.FULL and sorted(res["seeds"]) == ["0", "1", "2"]
    doc = _docs()
    assert bench.table(res) in doc
    ahead, _ = _ahead(res, 30)
    landed = sum(row[f"{e} {n}"]["landed"] for row in res["seeds"].values() for e in ("exp2", "exp3")
                 for n in ("one-net", "simple-complex"))
    flat = " ".join(doc.split())
    assert f"After 30 generations similarity is ahead in {ahead} of the 6 seed × orientation pairs" in flat
    firsts = [row[f"exp1 {n}"]["first_landed"] for row in res["seeds"].values() for n in ("f", "f+similarity")]
    assert landed == 0 and all(f == [None, None] for f in firsts)  # what the reading says: nothing lands


def test_the_table_of_experiment_1_alone_at_another_budget(bench):
    """``--exp1-only --exp1-generations 300 --fitness landing``: experiment 1's rows only, the best landing score
    after 10, 30, 100 and 300 generations, and how often it landed; a results file from before those were recorded
    keeps its table."""
    def exp1(first, best, landed):
        return {"first_landed": first, "first_upright": [1, 1], "best_f": [list(np.linspace(0, b, 300)) for b in best],
                "best_landed": landed, "rollouts_landed": [2 * n for n in landed]}

    res = {"fitness": "landing", "budget": dict(bench.FULL, exp1_generations=300),
           "seeds": {"0": {"exp1 f": exp1([None, 58], [2.5, 4.5], [0, 243]),
                           "exp1 f+similarity": exp1([None, 22], [2.4, 4.6], [0, 279])}}}
    text = bench.table(res)
    rows = text.splitlines()
    assert len(rows) == 2 + 2 * 8 and "(2)" not in text and "baseline" not in text
    assert "| (1) f: generations to first landing, orientation 1 / 4 | never / 58 |" in rows
    assert [r.split(" after ")[1].split(" ")[0] for r in rows if "best landing score after" in r] == ["10", "30", "100",
                                                                                                      "300"] * 2
    assert "| (1) f+similarity: best landing score after 300 generations, orientation 1 / 4 | 2.40 / 4.60 |" in rows
    assert "| (1) f+similarity: generations whose best lands, orientation 1 / 4 | 0 / 279 |" in rows
    assert "| (1) f: rollouts that land, orientation 1 / 4 | 0 / 486 |" in rows
    for row in res["seeds"]["0"].values():  # a file from before 2026-11-29: the same rows without the counts
        del row["best_landed"], row["rollouts_landed"]
    res["fitness"] = "eq9"
    old = bench.table(res)
    assert len(old.splitlines()) == 2 + 2 * 6 and "best f after 100 generations" in old and "lands," not in old


def test_the_study_with_the_landing_fitness_in_the_docs_is_the_shipped_run(bench):
    """docs/landing.md's table of the study ranked by our landing score is `table` of
    `learning/weights/landing_study_library_cat_landing.json` (`bench/landing_study.py --samples library --design cat
    --fitness landing`), and its reading counts what the file holds: experiment 1 lands once (similarity, seed 0,
    orientation 4, from generation 22), similarity is ahead in 2 of 6 pairs after 30 generations, and no net of
    experiment 2 or 3 lands."""
    res = _shipped("landing_study_library_cat_landing.json")
    assert res["fitness"] == "landing" and res["design"] == "cat" and res["budget"] == bench.FULL
    assert res["samples"] == "learning/weights/landing_samples_library_cat.json"
    assert sorted(res["seeds"]) == ["0", "1", "2"]
    doc = _docs()
    assert bench.table(res) in doc
    flat = " ".join(doc.split())
    ahead, behind = _ahead(res, 30)
    assert f"After 30 generations similarity is ahead in {ahead} of the 6 seed × orientation pairs" in flat
    assert f"and behind in {behind} (orientation 1 in every seed" in flat
    firsts = {(s, n): row[f"exp1 {n}"]["first_landed"] for s, row in res["seeds"].items()
              for n in ("f", "f+similarity")}
    assert {k: v for k, v in firsts.items() if v != [None, None]} == {("0", "f+similarity"): [None, 22]}
    assert "similarity on orientation 4 in seed 0, from generation 22" in flat
    assert all(row[f"{e} {n}"]["landed"] == 0 for row in res["seeds"].values() for e in ("exp2", "exp3")
               for n in ("one-net", "simple-complex"))


def test_experiment_1_at_300_generations_in_the_docs_is_the_shipped_run(bench):
    """docs/landing.md's five-seed table of experiment 1 at 300 generations with the landing fitness is `table` of
    `learning/weights/landing_study_exp1_300_cat_landing.json`, and its reading (and the README's) counts what the
    file holds: similarity's best lands orientation 4 in every seed, f alone's in 3 of 5, similarity first in 3;
    more rollouts land with similarity in every seed; orientation 1 never lands."""
    res = _shipped("landing_study_exp1_300_cat_landing.json")
    assert res["fitness"] == "landing" and res["design"] == "cat" and res["budget"]["exp1_generations"] == 300
    assert sorted(res["seeds"]) == ["0", "1", "2", "3", "4"] and not res["baselines"]
    assert all(set(row) == {"exp1 f", "exp1 f+similarity", "seconds"} for row in res["seeds"].values())
    doc = _docs()
    assert bench.table(res) in doc
    rows = list(res["seeds"].values())
    f = [row["exp1 f"]["first_landed"] for row in rows]
    sim = [row["exp1 f+similarity"]["first_landed"] for row in rows]
    assert all(o1 is None for o1, _ in f + sim)  # orientation 1 never
    assert all(row[f"exp1 {n}"]["rollouts_landed"][0] == 0 for row in rows for n in ("f", "f+similarity"))
    f_lands, sim_lands = sum(o4 is not None for _, o4 in f), sum(o4 is not None for _, o4 in sim)
    sim_first = sum(b is not None and (a is None or b < a) for (_, a), (_, b) in zip(f, sim, strict=True))
    more = sum(row["exp1 f+similarity"]["rollouts_landed"][1] > row["exp1 f"]["rollouts_landed"][1] for row in rows)
    assert (f_lands, sim_lands, sim_first, more) == (3, 5, 3, 5)
    flat = " ".join(doc.split())
    assert "lands it in **all 5 seeds** (first at generation 22, 55, 227, 47 and 30)" in flat
    assert "the best ranked by f alone in **3 of 5** (58, 33, 21; never in seeds 1 and 2)" in flat
    assert "More of the population lands with similarity in every seed" in flat
    from pathlib import Path

    readme = " ".join((Path(__file__).parents[2] / "README.md").read_text().split())
    assert "similarity's best lands the side-on start in all 5 seeds and f alone's in 3" in readme


def test_experiment_2_at_four_times_the_budget_in_the_docs_is_the_shipped_run(bench):
    """docs/landing.md's table of the study with the landing fitness and four times experiment 2's budget is `table`
    of `learning/weights/landing_study_library_cat_landing_x4.json`, and its reading counts what the file holds."""
    res = _shipped("landing_study_library_cat_landing_x4.json")
    assert res["fitness"] == "landing" and res["design"] == "cat" and sorted(res["seeds"]) == ["0", "1"]
    assert res["budget"] == dict(bench.FULL, generations_simple=60, generations_complex=40)
    doc = _docs()
    assert bench.table(res) in doc
    rows = list(res["seeds"].values())
    landed = sum(r[f"{e} {n}"]["landed"] for r in rows for e in ("exp2", "exp3") for n in ("one-net", "simple-complex"))
    up = {(e, n): ", ".join(str(r[f"{e} {n}"]["upright"]) for r in rows)
          for e in ("exp2", "exp3") for n in ("one-net", "simple-complex")}
    flat = " ".join(doc.split())
    assert landed == 0 and "Nothing lands in experiments 2 and 3 at four times the budget either" in flat
    assert (f"simple–complex {up['exp2', 'simple-complex']}, one net {up['exp2', 'one-net']}; of the 4 untrained: "
            f"{up['exp3', 'simple-complex']} against {up['exp3', 'one-net']}.") in flat
