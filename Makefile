# Two front doors: `make demo` and `make test`. Both build .venv from scratch when it is missing or stale.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OMP_NUM_THREADS ?= 1
export MPLBACKEND ?= Agg
export WANDB_MODE ?= offline

.PHONY: venv demo test bench clean

venv: $(STAMP)

# torch first, pinned exactly (the local CPU wheel); then the package and its pinned dependencies.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip==24.3.1
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python evaluate.py experiment=pusht_demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/maps.py
	$(BIN)/python benchmarks/pusht_env.py
	$(BIN)/python benchmarks/pusht_replay.py
	$(BIN)/python benchmarks/pusht_expert.py

clean:
	rm -rf $(VENV) outputs multirun
