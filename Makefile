# Two commands set everything up: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo demo-train test test-fast lint docs reference format bench clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

# The main job on embedded defaults: the whole product on loopback (about 2 min on 2 cores).
# A training server, a simulated world and 4 robot-agent processes on MUSEUM fly 100 missions on
# an untrained per-map team, retrain it from scratch over HTTP (EM on the fleet's own records,
# CE-PG, the evaluation gate), fly 100 missions on the new version, and print the capture times of
# both. (A server's own default first version is the general policy, docs/general-policy.md.)
demo: $(STAMP)
	$(VENV)/bin/mures fleet-sim --env museum --robots 4 --missions 200 --retrain-every 100 --retrain-episodes 30000 --seed 0 --init-policy untrained

# The offline trainer alone: train a 4-robot CE-PG team on MUSEUM (about a minute), then evaluate
# it and the reference searchers on the same 1500 episodes.
DEMO_DIR ?= out/demo-museum
demo-train: $(STAMP)
	$(VENV)/bin/mures train --env museum --robots 4 --episodes 30000 --em-first 4096 --em-missions 128 --seed 0 --out $(DEMO_DIR)
	@for s in policy:$(DEMO_DIR) random greedy; do \
	  $(VENV)/bin/mures evaluate --env museum --robots 4 --searcher $$s --episodes 1500 --seed 1 || exit 1; \
	done

# -n: one pytest worker per core (pytest-xdist), each taking whole test files, so that a file's
# module fixtures (a running fleet, a trained team) are built once; TEST_WORKERS=0 runs in one
# process. --durations: the slowest tests, so that a CI log shows where its minutes go
TEST_WORKERS ?= auto
test: $(STAMP)
	$(PY) -m pytest -q --durations=15 -n $(TEST_WORKERS) --dist loadfile

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# The documentation site (mkdocs.yml, docs/) in build/site; --strict: a broken link or a missing
# page fails. The command-line and REST API pages are generated from the code (docs/hooks/).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

# The generated reference in docs/cli.md and docs/api.md, written anew from the parsers and the
# OpenAPI document (tests/test_docs.py fails while it is stale)
reference: $(STAMP)
	$(PY) docs/hooks/reference.py

# The suite without the multi-process tests (servers, agents, fleets, subprocess training): minutes less.
test-fast: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: $(STAMP)
	$(PY) benchmarks/bench_belief.py
	$(PY) benchmarks/bench_sim.py
	$(PY) benchmarks/bench_estimate.py
	$(PY) benchmarks/bench_decision.py
	$(PY) benchmarks/bench_train.py
	$(PY) benchmarks/bench_ingest.py
	$(PY) benchmarks/bench_fleet.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache build *.egg-info
