# Two front doors: `make demo` and `make test`. Both build .venv from scratch when it is missing or stale.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export OMP_NUM_THREADS ?= 1
export MPLBACKEND ?= Agg
export WANDB_MODE ?= offline

.PHONY: venv osmesa demo test test-fast lint docs bench clean
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

venv: $(STAMP)

# Offscreen MuJoCo rendering on the CPU (the packing camera): Debian's libosmesa6, installed when missing. Without
# it (no apt, no rights) MuJoCo falls back to Mesa's EGL, which renders the same images.
osmesa:
	@ldconfig -p | grep -q libOSMesa || { command -v apt-get >/dev/null && \
	  { $(SUDO) apt-get install -y -q --no-install-recommends libosmesa6 >/dev/null 2>&1 || \
	    { $(SUDO) apt-get update -q >/dev/null 2>&1 && $(SUDO) apt-get install -y -q --no-install-recommends libosmesa6 >/dev/null 2>&1; }; } || \
	  echo "libosmesa6 could not be installed: MuJoCo will render through EGL"; }

# torch first, on its own: TORCH=cpu (default) takes the CPU wheel; TORCH=cu128 (or another CUDA tag) takes PyTorch's
# CUDA wheel of the same version from download.pytorch.org (docs/install.md). Then the package with the exact versions
# of constraints.txt (pyproject.toml declares ranges); pip check must find nothing missing.
TORCH ?= cpu
TORCH_VERSION := $(shell sed -n 's/^torch==//p' constraints.txt)
TORCH_INDEX := $(if $(filter cpu,$(TORCH)),,--index-url https://download.pytorch.org/whl/$(TORCH))
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip==24.3.1
	$(BIN)/python -m pip install -q torch==$(TORCH_VERSION) $(TORCH_INDEX)
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[test]'
	$(BIN)/python -m pip check
	$(BIN)/python -c "import torch, numpy; assert torch.__version__.startswith('$(TORCH_VERSION)+$(TORCH)') and numpy.__version__ == '1.26.4', (torch.__version__, numpy.__version__)"
	touch $(STAMP)

demo: $(STAMP) osmesa
	$(BIN)/kpflow-evaluate experiment=pusht_demo

# ruff (pyflakes, import order, complexity; see pyproject.toml) and ruff's formatting, then every test, on 2 worker processes (one test
# file per worker, so a file's module fixtures such as the MuJoCo scenes are built once), printing the 20 slowest.
# `make test-fast` leaves out the tests marked slow (CLI subprocesses, MuJoCo scenes, long rollouts) for the inner loop.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint osmesa
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=20

test-fast: lint
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

# The documentation site into site/ (mkdocs-material; the test suite builds it with --strict too).
docs: $(STAMP)
	$(BIN)/mkdocs build --strict

bench: $(STAMP)
	$(BIN)/python benchmarks/maps.py
	$(BIN)/python benchmarks/pusht_env.py
	$(BIN)/python benchmarks/pusht_replay.py
	$(BIN)/python benchmarks/pusht_expert.py
	$(BIN)/python benchmarks/metrics.py

clean:
	rm -rf $(VENV) outputs multirun site
