# felis: `make demo` and `make test` build .venv on first use, then run.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# make test runs the suite on every core (pytest-xdist; an idle worker takes tests queued on a busy one, worksteal);
# TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= auto

.PHONY: demo test test-slow test-rerun bench ik-study landing-study lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -e '.[dev,cluster]'
	@touch $(STAMP)

demo: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(VENV)/bin/felis demo

test: $(STAMP)
	$(VENV)/bin/ruff check --quiet .
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) -m pytest -q -n $(TEST_WORKERS) $$(test "$(TEST_WORKERS)" = 0 || echo --dist worksteal)

test-slow: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) -m pytest -q -m slow

# A third reader of the logs: Rerun's MCAP import, in a venv of its own (rerun-sdk is ~460 MB; not a dependency).
RERUN_VENV := .venv-rerun
$(RERUN_VENV)/bin/rerun:
	@test -x $(RERUN_VENV)/bin/python || $(PYTHON) -m venv $(RERUN_VENV)
	$(RERUN_VENV)/bin/pip install --quiet rerun-sdk==0.41.0

test-rerun: $(STAMP) $(RERUN_VENV)/bin/rerun
	FELIS_RERUN=$(CURDIR)/$(RERUN_VENV)/bin/rerun MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) -m pytest -q tests/logs/test_rerun_import.py

bench: $(STAMP)
	$(PY) bench/sim_speed.py
	$(PY) bench/bus_loop.py
	$(PY) bench/sysid_recovery.py
	$(PY) bench/ik_latency.py
	$(PY) bench/balance_monitor.py
	$(PY) bench/dtw_speed.py
	$(PY) bench/landing_speed.py

# The IK nets' size table and the paper's ablations over 3 seeds (about 35 min on 2 cores).
ik-study: $(STAMP)
	$(PY) bench/ik_study.py

# Seed 000's §6.6 experiments over 3 seeds with baselines (about 25 min on 2 cores).
landing-study: $(STAMP)
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(PY) bench/landing_study.py --json runs/landing_study.json

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) $(RERUN_VENV) runs build *.egg-info
