# Set-up and everyday commands. `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# where configs/benchmark/quick.yaml writes (its out, data root and cache)
DEMO_OUT := demo_out

.PHONY: setup demo test test-all lint bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -c constraints.txt -e ".[dev,rosbag,export]"
	touch $@

# the comparison table on simulated data: simulate, label, train and test every model, profile, render, with
# the learning curves in the captions: this machine's run of configs/benchmark/learning.yaml once there is one,
# else the measured run kept in results/ (results/README.md says how it was made)
LEARNING := $(firstword $(wildcard $(DEMO_OUT)/learning/results.csv) results/learning.csv)
demo: setup
	$(BIN)/aaute benchmark --suite configs/benchmark/quick.yaml
	$(BIN)/aaute leaderboard $(DEMO_OUT)/benchmark/results.csv --out $(DEMO_OUT)/leaderboard --learning $(LEARNING)

test: setup
	$(BIN)/python -m pytest

test-all: setup
	$(BIN)/python -m pytest -m ""

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python -m benchmarks.studies.recording_bench

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
