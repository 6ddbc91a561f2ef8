# Two commands set everything up: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo test lint format bench clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

# The main job on embedded defaults: the reference searchers on MUSEUM.
demo: $(STAMP)
	@for s in random greedy; do \
	  $(VENV)/bin/mures evaluate --env museum --robots 4 --searcher $$s --episodes 1500 --seed 0 || exit 1; \
	done

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: $(STAMP)
	$(PY) benchmarks/bench_belief.py
	$(PY) benchmarks/bench_sim.py
	$(PY) benchmarks/bench_estimate.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
