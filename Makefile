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
	@echo "demo output in $(OUT): stations.csv links.csv planes.csv trajectory_corrected.txt corrected.laz sequence.e57 report.json report.html"

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

# Today's figures of benchmarks/RESULTS.md into benchmarks/results/ (hours; one command per table there).
bench: setup
	$(BIN)/python benchmarks/accuracy_matrix.py --scenario sample heldout tilted --drift-models world slam gnss-ins \
		--magnitudes medium --seeds 1 2 3 4 5 6 7 8 9 10 11 12 --out benchmarks/results/accuracy_medium.json
	$(BIN)/python benchmarks/accuracy_matrix.py --scenario sample heldout tilted --drift-models world slam gnss-ins \
		--magnitudes small --seeds 1 2 3 --out benchmarks/results/accuracy_small.json
	$(BIN)/python benchmarks/accuracy_matrix.py --scenario sample --drift-models slam gnss-ins world \
		--magnitudes large --seeds 1 2 3 --out benchmarks/results/accuracy_large.json
	$(BIN)/python benchmarks/datum_modes.py --scenario sample heldout --drift-models gnss-ins world slam \
		--magnitudes medium --seeds 1 2 3 4 5 6 --out benchmarks/results/datum_modes.json
	$(BIN)/python benchmarks/long_run.py --data /tmp/kinreg-bench/long_gnss --drift-model gnss-ins \
		--out benchmarks/results/long_run_gnss_ins.json
	$(BIN)/python benchmarks/long_run.py --data /tmp/kinreg-bench/long_gnss_2deg --drift-model gnss-ins \
		--drift-at-end 0.1 2.0 --out benchmarks/results/long_run_gnss_ins_2deg.json
	$(BIN)/python benchmarks/scale.py --points 20e6 --skip-selected --out benchmarks/results/scale_20M.json
	$(BIN)/python benchmarks/block_solver.py --stations 231 2000 20000 100000 --scipy-max 20000 \
		--out benchmarks/results/block_solver.json
	$(BIN)/python benchmarks/network_speed.py --block-only --stations 100000 --cache /tmp/kinreg-bench --repeat 2 \
		--out benchmarks/results/block_100k.json
	$(BIN)/python benchmarks/network_speed.py --block-only --stations 20000 --cache /tmp/kinreg-bench --repeat 2 \
		--out benchmarks/results/block_20k.json
	$(BIN)/python benchmarks/calibration_room.py --seeds 100 --out benchmarks/results/calibration_room.json
	$(BIN)/python benchmarks/calibration_room.py --seeds 100 --zenith-step-deg 0.1 --board-offset-mm 10 \
		--gates-mm 10,100 --out benchmarks/results/calibration_room_fine_step.json
	$(BIN)/python benchmarks/calibration_room.py --seeds 50 --profiles 20 --start-lever-mm 100 --start-angle-deg 3 \
		--gates-mm 50 --out benchmarks/results/calibration_room_far_start.json

clean:
	rm -rf $(VENV) out .pytest_cache
