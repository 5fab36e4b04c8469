# The two commands a newcomer needs: `make demo` (bake a bundled scene, relight, write images)
# and `make test`. Everything installs itself into .venv on first use.
PYTHON ?= python3.11
# Where pip gets torch 2.13.0. Empty: pip's configured index (on Linux, PyPI serves the CUDA build).
# Set it to PyTorch's CPU-only wheel index for the CPU build (README, Install).
TORCH_INDEX_URL ?=
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install test lint demo bake clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet $(if $(TORCH_INDEX_URL),--index-url "$(TORCH_INDEX_URL)") torch==2.13.0
	$(BIN)/pip install --quiet -e '.[test,lint]'
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/pytest -n auto

# ruff (lint rules and formatting) on the whole tree, mypy on relight_torch/ (settings in pyproject.toml).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build *.egg-info

# The README's first command: bake a bundled scene, relight it under light edits, write images and a chart.
demo: $(STAMP)
	$(BIN)/relight demo --out out/demo

# Bake a shot's direct-lighting cache: make bake SCENE=shot.usda CAMERA=/World/Camera OUT=cache/
bake: $(STAMP)
	@test -n "$(SCENE)" -a -n "$(CAMERA)" || { echo "usage: make bake SCENE=shot.usda CAMERA=/Path/Camera [OUT=dir]" >&2; exit 2; }
	$(BIN)/relight bake "$(SCENE)" --camera "$(CAMERA)" --out "$(or $(OUT),out/bake)"
