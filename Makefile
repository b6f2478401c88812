# `make run` and `make test` each create (or reuse) the project's environment in .venv/.
PYTHON ?= python3
# torch's CPU build. This machine keeps the wheel in pip's local cache; elsewhere take it from
# PyTorch's own CPU wheel index: make TORCH_INDEX=https://download.pytorch.org/whl/cpu test
TORCH ?= torch==2.13.0
TORCH_INDEX ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The environment is installed without bytecode (--no-compile, below); the first import of a module writes it,
# for every later process, even where the environment says not to write any.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: run show test lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# the CPU build of torch first, so nothing pulls a multi-GB CUDA build. --no-compile: the modules a run
	# imports are compiled when first imported (a fraction of torch's and Ray's files; the build 112 s -> 64 s)
	$(BIN)/python -m pip install -q --no-compile '$(TORCH)' $(if $(TORCH_INDEX),--index-url '$(TORCH_INDEX)')
	$(BIN)/python -m pip install -q --no-compile -e '.[dev]'
	touch $(STAMP)

# A fresh run folder each time, so no earlier run is ever overwritten.
run: $(STAMP)
	$(BIN)/formation train configs/quickstart.yaml --out runs/quickstart-$$(date +%Y%m%d-%H%M%S)

show: $(STAMP)
	$(BIN)/formation show --setting 1 --out runs/show

test: $(STAMP)
	$(BIN)/ruff check formation tests benchmarks experiments
	# two workers for two cores: the tests that train spend much of their time waiting on Ray
	$(BIN)/python -m pytest -q -n 2 --dist worksteal

bench: $(STAMP)
	$(BIN)/python benchmarks/env_speed.py

clean:
	rm -rf $(VENV) runs
