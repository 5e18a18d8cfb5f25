# Two commands for a newcomer:  `make demo` (set up + main job)  and  `make test` (set up + tests).
# Both create and reuse .venv (and .venv-escnn for the optional escnn adapter) from the project's own files.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
ESCNN_VENV := .venv-escnn
ESCNN_PY := $(ESCNN_VENV)/bin/python
ESCNN_STAMP := $(ESCNN_VENV)/.installed
PYTEST_ARGS ?=

.PHONY: setup setup-escnn test test-core test-escnn demo reproduce report lint format bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements/torch.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements/torch.txt
	$(PY) -m pip install --quiet -e ".[dev,export,marl,ros]"
	touch $(STAMP)

# escnn needs numpy<2, so its adapter is tested in a separate environment.
setup-escnn: $(ESCNN_STAMP)

# escnn goes in with --no-deps (its py3nj dependency needs a Fortran compiler and is optional), after its real
# runtime dependencies (requirements/escnn.txt, the `escnn` extra); the last line checks that the adapter works.
$(ESCNN_STAMP): pyproject.toml requirements/torch.txt requirements/escnn.txt requirements/escnn-nodeps.txt
	$(PYTHON) -m venv $(ESCNN_VENV)
	$(ESCNN_PY) -m pip install --quiet --upgrade pip
	$(ESCNN_PY) -m pip install --quiet -r requirements/torch.txt
	$(ESCNN_PY) -m pip install --quiet -r requirements/escnn.txt -e ".[dev,escnn]"
	$(ESCNN_PY) -m pip install --quiet --no-deps -r requirements/escnn-nodeps.txt
	$(ESCNN_PY) -W ignore -c "from escnn import group; from groupcanon.compat.escnn import from_escnn; from_escnn(group.so2_group().irrep(1))"
	touch $(ESCNN_STAMP)

test: test-core test-escnn

test-core: $(STAMP)
	$(PY) -m ruff check src tests examples benchmarks docs/*.py
	$(PY) -m pytest -n 2 -q $(PYTEST_ARGS)

test-escnn: $(ESCNN_STAMP)
	$(ESCNN_PY) -m pytest -q -m escnn tests/groupcanon/test_escnn_adapter.py

demo: $(STAMP)
	$(VENV)/bin/egcbf demo --out out/demo --overwrite

# the repository's own reproduction (hours on two cores; resumable: run it again to continue): docs/reproduction.md
reproduce: $(STAMP)
	$(VENV)/bin/egcbf reproduce --out docs/results/reproduction --report docs/reproduction.md --workers 2 --no-progress
	$(MAKE) report

# every page generated from the reproduction's cells, regenerated from the committed cells (nothing is computed)
report: $(STAMP)
	$(VENV)/bin/egcbf reproduce --out docs/results/reproduction --report docs/reproduction.md --report-only --no-progress
	$(PY) docs/gen_marl.py
	$(PY) benchmarks/sweep_cpu_hours.py

lint: $(STAMP)
	$(PY) -m ruff check src tests examples benchmarks docs/*.py
	$(PY) -m ruff format --check src tests examples benchmarks docs/*.py

format: $(STAMP)
	$(PY) -m ruff format src tests examples benchmarks docs/*.py
	$(PY) -m ruff check --fix src tests examples benchmarks

# Speed measurements; each script rewrites its own section of docs/benchmarks.md.
bench: $(STAMP)
	$(PY) benchmarks/run.py
	$(PY) benchmarks/env_scaling.py --threads 1
	$(PY) benchmarks/qp_scaling.py
	$(PY) benchmarks/policy_scaling.py
	$(PY) benchmarks/filter_cost.py
	$(PY) benchmarks/agent_latency.py
	$(PY) benchmarks/gcbfplus_speed.py

clean:
	rm -rf $(VENV) $(ESCNN_VENV) .pytest_cache .ruff_cache .hypothesis
