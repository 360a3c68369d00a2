# calstation — set-up, the main job and the tests.
#   make demo   set everything up, then run a full guided calibration on the simulated station
#   make test   set everything up, then run the test suite, ruff and mypy
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
PLUGIN_DIRS := $(sort $(dir $(wildcard plugins/*/pyproject.toml)))
STAMP  := $(VENV)/.calstation-installed
OUT    ?= out

.PHONY: setup system-deps demo test lint bench clean

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

# The guided run on the simulated station, unattended; its database and run folders go to $(OUT).
demo: setup
	CALSTATION_HOME=$(abspath $(OUT)) $(BIN)/calstation run recipes/sim-periodicity.yaml --yes
	CALSTATION_HOME=$(abspath $(OUT)) $(BIN)/calstation history

test: setup
	$(BIN)/ruff check calstation plugins tests benchmarks
	$(BIN)/mypy
	$(BIN)/python -m pytest -n 2 -q

bench: setup
	$(BIN)/python benchmarks/simulate_revolution.py
	$(BIN)/python benchmarks/recording_io.py
	$(BIN)/python benchmarks/calibration.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .mypy_cache .ruff_cache
