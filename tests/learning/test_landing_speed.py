"""Smoke test of ``bench/landing_speed.py``: its three parts on a tiny setup (no timing claims)."""

from dataclasses import replace

import pytest
from conftest import load_bench

from felis.learning.landing import task as lk
from felis.learning.landing.samples import STEPS


@pytest.fixture(scope="module")
def bench():
    return load_bench("landing_speed")


def test_landing_speed_parts(bench):
    task, jobs = bench.setup(1)
    assert task.k == 7 and task.steps == STEPS and len(jobs) == task.k
    # two orientations, 20 ticks: the same code paths in a few seconds
    task = replace(task, orientations=task.orientations[:2], heights_m=task.heights_m[:2], steps=20,
                   sf=task.sf[:2], tf=task.tf[:2])
    jobs = jobs[:2]
    one = bench.episode_speed(task, jobs, repeats=1)
    assert one["anchor_same_physics"] is True  # the bare loop redoes felis's physics bit for bit
    assert one["episodes_per_batch"] == 2
    for key in ("bare_mj_step_episodes_per_s", "rollout_episodes_per_s", "job_episodes_per_s", "job_ratio"):
        assert one[key] > 0
    pool = bench.pool_speedup(task, jobs, repeats=1)
    assert pool["identical_results"] is True
    assert pool["jobs_per_map"] == 2 and pool["speedup"] > 0 and isinstance(pool["met"], bool)
    assert lk._WORKER is None  # both parts release this process's simulation
    batched = bench.batched_speed(task, jobs, repeats=1)  # part 3: the batch against open loop and sequential
    for key in ("open_loop_steps_per_s", "batched_steps_per_s", "sequential_steps_per_s", "ratio_open_loop",
                "ratio_today"):
        assert batched[key] > 0
    assert isinstance(batched["met"], bool) and lk._WORKER is None
