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

# The main job on embedded defaults: train a 4-robot CE-PG team on MUSEUM (about a minute on
# 2 cores), then evaluate it and the reference searchers on the same 1500 episodes.
DEMO_DIR ?= out/demo-museum
demo: $(STAMP)
	$(VENV)/bin/mures train --env museum --robots 4 --episodes 30000 --em-first 4096 --em-missions 128 --seed 0 --out $(DEMO_DIR)
	@for s in policy:$(DEMO_DIR) random greedy; do \
	  $(VENV)/bin/mures evaluate --env museum --robots 4 --searcher $$s --episodes 1500 --seed 1 || exit 1; \
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
	$(PY) benchmarks/bench_decision.py
	$(PY) benchmarks/bench_train.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
