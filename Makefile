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

.PHONY: setup setup-escnn test test-core test-escnn demo lint format bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements/torch.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements/torch.txt
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

# escnn needs numpy<2, so its adapter is tested in a separate environment.
setup-escnn: $(ESCNN_STAMP)

$(ESCNN_STAMP): pyproject.toml requirements/torch.txt requirements/escnn.txt
	$(PYTHON) -m venv $(ESCNN_VENV)
	$(ESCNN_PY) -m pip install --quiet --upgrade pip
	$(ESCNN_PY) -m pip install --quiet -r requirements/torch.txt
	$(ESCNN_PY) -m pip install --quiet -r requirements/escnn.txt
	$(ESCNN_PY) -m pip install --quiet -e ".[dev,escnn]"
	touch $(ESCNN_STAMP)

test: test-core test-escnn

test-core: $(STAMP)
	$(PY) -m ruff check src tests examples benchmarks
	$(PY) -m pytest -n 2 -q $(PYTEST_ARGS)

test-escnn: $(ESCNN_STAMP)
	$(ESCNN_PY) -m pytest -q -m escnn -p no:randomly tests/groupcanon/test_escnn_adapter.py

demo: $(STAMP)
	$(PY) examples/wrap_pyg_layer.py

lint: $(STAMP)
	$(PY) -m ruff check src tests examples benchmarks
	$(PY) -m ruff format --check src tests examples benchmarks

format: $(STAMP)
	$(PY) -m ruff format src tests examples benchmarks
	$(PY) -m ruff check --fix src tests examples benchmarks

bench: $(STAMP)
	$(PY) benchmarks/run.py

clean:
	rm -rf $(VENV) $(ESCNN_VENV) .pytest_cache .ruff_cache .hypothesis
