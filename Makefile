# Set-up and the two Quickstart jobs. `make quickstart` and `make test` work on a fresh machine.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# PyTorch 2.14.1 is a CUDA build: with its libraries a new venv takes about 7.5 GB.
MIN_FREE_KB ?= 8000000
VENV_DIR = $(dir $(abspath $(VENV)))

.PHONY: setup quickstart test test-slow lint bench

$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
		(apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null || \
		echo "warning: could not install libusb-1.0-0 (open3d needs it)"; fi
	@# Skipped once torch imports, so that a set-up that ran out of disk inside pip is checked again.
	@$(BIN)/python -c 'import torch' 2>/dev/null || { mkdir -p $(VENV_DIR) && \
		[ $$(df -Pk $(VENV_DIR) | awk 'NR==2 {print $$4}') -ge $(MIN_FREE_KB) ]; } || \
		{ echo "error: $(VENV_DIR): a new $(VENV) needs about 8 GB free (PyTorch and its CUDA libraries), $$(df -Ph $(VENV_DIR) | awk 'NR==2 {print $$4}') free"; exit 1; }
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q --no-cache-dir torch==2.14.1 torchvision==0.29.1
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

quickstart: $(STAMP)
	$(BIN)/vfdata quickstart data/quickstart

test: $(STAMP)
	$(BIN)/python -m pytest -q

# The slow tier: whole pipelines on simulated and real recordings, DDP, Ray, every config.
test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python bench/run_all.py
