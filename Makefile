# calstation — set-up, the main job and the tests.
#   make demo   set everything up, then start the web station on the simulated station and print
#               its URL (open it, start a run, click through the prompts)
#   make demo-console   the same run in the terminal, unattended
#   make test   set everything up, then run ruff, mypy, lint-imports and the test suite
#   make wheel-smoke   build the wheels, install them outside the checkout and run them there
#   make test-stress   make test while `stress --cpu 4` loads the machine (RUNS=3: three in a row)
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
PLUGIN_DIRS := $(sort $(dir $(wildcard plugins/*/pyproject.toml)))
STAMP  := $(VENV)/.calstation-installed
OUT    ?= out

.PHONY: setup system-deps demo demo-console test test-stress wheel-smoke lint bench bench-fleet clean

setup: $(STAMP)

$(STAMP): pyproject.toml $(wildcard plugins/*/pyproject.toml) Makefile
	@$(MAKE) --no-print-directory system-deps
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "calstation needs Python 3.11 or newer (found " + sys.version.split()[0] + ")")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]' $(foreach p,$(PLUGIN_DIRS),-e ./$(p))
	touch $@

# open3d cannot be imported without libusb-1.0 (and libgomp); install them from
# Debian's packages when they are missing.
system-deps:
	@bash scripts/system-deps.sh

# The web station on the simulated station (http://127.0.0.1:8470/, Ctrl-C stops it); its
# database and run folders go to $(OUT).
demo: setup
	CALSTATION_HOME=$(abspath $(OUT)) $(BIN)/calstation serve --recipes recipes

# The guided run on the simulated station in the terminal, unattended.
demo-console: setup
	CALSTATION_HOME=$(abspath $(OUT)) $(BIN)/calstation run recipes/sim-periodicity.yaml --yes
	CALSTATION_HOME=$(abspath $(OUT)) $(BIN)/calstation history

test: setup
	$(BIN)/ruff check calstation plugins tests benchmarks
	$(BIN)/mypy
	$(BIN)/lint-imports --no-logo
	$(BIN)/python -m pytest -n 2 -q
	$(BIN)/python -m pytest -q -m browser tests/

# The package as a user installs it: the wheels of calstation and each plugin built and
# checked, installed into a new virtual environment outside the checkout, and a simulated run to
# PASS, history and serve there (scripts/wheel-smoke.sh; CI runs it after the tests).
wheel-smoke: setup
	bash scripts/wheel-smoke.sh

# The suite must not depend on the machine's speed: tests wait on events, not clocks. This runs
# `make test` beside `stress --cpu $(STRESS_CPU)` (Debian's stress, installed when missing), $(RUNS)
# time(s) in a row; docs/reliability.md records the result.
STRESS_CPU ?= 4
RUNS ?= 1
test-stress: setup
	@bash scripts/system-deps.sh stress
	STRESS_CPU=$(STRESS_CPU) RUNS=$(RUNS) bash scripts/test-stress.sh

bench: setup
	$(BIN)/python benchmarks/simulate_revolution.py
	$(BIN)/python benchmarks/recording_io.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/startup.py
	$(BIN)/python benchmarks/web_load.py

# 1,000 stored runs on PostgreSQL re-processed with 1 and 2 local Dask workers (docs/fleet.md;
# about 45 minutes on two cores)
bench-fleet: setup
	$(BIN)/python benchmarks/fleet_reprocess.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .mypy_cache .ruff_cache
