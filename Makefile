# Set-up and the two Quickstart jobs. `make quickstart` and `make test` work on a fresh machine.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# PyTorch: the CUDA build (2.14.1 with torchvision; its CUDA libraries make the venv about 8 GB) where
# the disk has room for it, else the CPU build (2.13.0+cpu: a venv of 1.85 GB with the dev extras,
# measured 2026-12-05, and a test run needs 0.3 GB more). CI's clean clone has had 6.5 GB free and once
# 2 GB; below the estimate the set-up warns and tries, since a refusal would fail for certain. `make
# setup TORCH=cuda` or `TORCH=cpu` chooses. torchvision is left out of the CPU build: PyPI's wheels are
# built for the CUDA torch and do not import beside the CPU one; only the optional Faster R-CNN prompt
# needs it. The LeRobot formats (0.3 GB) come where the disk has room; open3d and Ray (1.2 GB) with
# `make test-slow` only (the extras `fast` and `ray`).
TORCH ?= auto
CUDA_FREE_KB := 8500000
CPU_FREE_KB := 2200000
# pyarrow and PyAV (0.3 GB) and room for the tests' largest folder (0.3 GB) beside them.
LEROBOT_FREE_KB := 700000
TORCH_CUDA := torch==2.14.1 torchvision==0.29.1
TORCH_CPU := torch==2.13.0+cpu
TORCH_CPU_INDEX := https://download.pytorch.org/whl/cpu
VENV_DIR = $(dir $(abspath $(VENV)))
FREE_KB = df -Pk $(VENV_DIR) | awk 'NR==2 {print $$4}'
PIP := $(BIN)/pip install -q --no-cache-dir

$(STAMP): pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
		(apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null || \
		echo "warning: could not install libusb-1.0-0 (open3d needs it)"; fi
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	@# Skipped once torch imports, so that a set-up that ran out of disk inside pip is checked again.
	@$(BIN)/python -c 'import torch' 2>/dev/null || { \
		free=$$($(FREE_KB)); kind=$(TORCH); \
		if [ $$kind = auto ]; then kind=cpu; [ $$free -ge $(CUDA_FREE_KB) ] && kind=cuda; fi; \
		need=$(CPU_FREE_KB); [ $$kind = cuda ] && need=$(CUDA_FREE_KB); \
		if [ $$free -lt $$need ]; then echo "warning: $(VENV_DIR): the set-up with PyTorch's $$kind build" \
			"needs about $$((need / 100000))00 MB, $$((free / 1000)) MB free; trying"; fi; \
		echo "PyTorch: the $$kind build ($$((free / 1000000)) GB free)"; \
		if [ $$kind = cuda ]; then $(PIP) $(TORCH_CUDA); \
		else $(PIP) $(TORCH_CPU) 2>/dev/null || $(PIP) --extra-index-url $(TORCH_CPU_INDEX) $(TORCH_CPU); fi; }
	$(PIP) -e '.[dev]'
	@free=$$($(FREE_KB)); \
	if [ $$free -ge $(LEROBOT_FREE_KB) ]; then $(PIP) -e '.[dev,lerobot]'; else echo "warning: $$((free / 1000))" \
		"MB free: the LeRobot formats (pyarrow, PyAV, 0.3 GB) are not installed: their tests are left out"; fi
	touch $(STAMP)

setup: $(STAMP)

quickstart: $(STAMP)
	$(BIN)/vfdata quickstart data/quickstart

# One worker per core, at most 4 (pytest-xdist): 264 s instead of 349 s on the 2-core machine (2026-12-07).
# Each worker holds torch (up to 2.1 GB); the slow tier stays in one process (DDP and Ray open their own).
test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4

# The slow tier: whole pipelines on simulated and real recordings, DDP, Ray, every config.
test-slow: $(STAMP)
	$(PIP) -e '.[dev,lerobot,fast,ray]'
	$(BIN)/python -m pytest -q -m slow

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python bench/run_all.py
