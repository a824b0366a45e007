# Two entry points for a fresh Debian 12 machine (as root): `make demo` and `make test`.
# Both set everything up first; a second run only re-installs when pyproject.toml changed.
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.kinreg-installed
OUT    ?= out/demo

.PHONY: setup demo test test-slow test-all lint bench clean sample-data

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup-system.sh
	bash scripts/setup-system.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check --upgrade "pip>=25.1" 2>&1 | { grep -v "is ignored: it is neither" || true; }
	$(BIN)/python -m pip install -q --disable-pip-version-check -e ".[cholmod]" --group dev 2>&1 | { grep -v "is ignored: it is neither" || true; }
	touch $(STAMP)

demo: setup
	$(BIN)/kinreg info sample_data/run_trajectory.txt
	$(BIN)/kinreg info sample_data/run_cloud.laz
	$(BIN)/kinreg process --trajectory sample_data/run_trajectory.txt --cloud sample_data/run_cloud.laz \
		--out $(OUT) --overwrite
	@echo "demo output in $(OUT): stations.csv links.csv trajectory_corrected.txt corrected.laz sequence.e57 report.json report.html"

test: setup
	$(BIN)/python -m pytest -m "not slow" -q

test-slow: setup
	$(BIN)/python -m pytest -m "slow" -q

test-all: setup
	$(BIN)/python -m pytest -q

lint: setup
	$(BIN)/ruff check kinreg cli tests
	$(BIN)/mypy

sample-data: setup
	$(BIN)/python sample_data/simulate.py --out sample_data

bench: setup
	$(BIN)/python benchmarks/bench_ingest.py
	$(BIN)/python benchmarks/eval_accuracy.py
	$(BIN)/python benchmarks/bench_planes.py
	$(BIN)/python benchmarks/bench_block_solver.py

clean:
	rm -rf $(VENV) out .pytest_cache
