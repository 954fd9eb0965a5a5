# Two entry points, both self-installing into ./.venv on first use, at the versions in requirements.lock:
#   make demo       the main job, end to end, on built-in defaults (the core package only)
#   make test       lint, format check, the docs build and the whole test suite (every extra; what CI runs)
# and, for everyday work, `make test-fast` (no slow, LIBERO, browser, LeRobot or robot-side tests, and only the
# extras the rest use), `make test-floors` (the store's tests on zarr's lowest supported release), `make docs`,
# `make lock`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
LOCK   := requirements.lock
ROBOT  := .venv-robot
ROBOT_LOCK := requirements-robot.lock
LEROBOT := .venv-lerobot
LEROBOT_LOCK := requirements-lerobot.lock
LEROBOT_TESTS := $(wildcard tests/test_lerobot*.py)
CORE   := $(VENV)/.core-installed
FAST   := $(VENV)/.fast-installed
ALL    := $(VENV)/.all-installed
XDIST  := --numprocesses auto --maxprocesses 4 --dist loadfile
# pip without byte-compiling every installed file (the environments hold about 600 MB of Python, much of it never
# imported): Python compiles what is imported, once, on first import.
PIPQ   := --quiet --no-compile
# The three environments (.venv, .venv-robot, .venv-lerobot) build side by side, and lint beside the docs build.
MAKEFLAGS += --jobs=3

.PHONY: install install-all demo test test-fast test-floors lint format docs lock

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install $(PIPQ) --upgrade pip

# The core package: all the main job needs.
$(CORE): pyproject.toml $(LOCK) | $(BIN)/python
	$(BIN)/pip install $(PIPQ) -c $(LOCK) -e .
	touch $@

# What `make test-fast` uses: the light extras its tests import, without LIBERO, Ray (its tests are all slow), Chromium
# and the robot and LeRobot environments.
$(FAST): $(CORE)
	$(BIN)/pip install $(PIPQ) -c $(LOCK) -e ".[studio,serve,language,iphumi,dev]"
	touch $@

# Every extra but lerobot: the studio, transformers (the Language baseline's pretrained encoder), LIBERO (2.1 GB), tests,
# docs. The studio's browser test drives Debian's chromium (pip's playwright cannot download its own browser offline);
# nothing else needs it. The lerobot extra has its own environment, .venv-lerobot (below).
$(ALL): $(CORE) $(ROBOT)/.installed $(LEROBOT)/.installed
	$(BIN)/pip install $(PIPQ) -c $(LOCK) -e ".[all]"
	command -v chromium >/dev/null || apt-get install -y -q chromium >/dev/null || \
		(apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null) || \
		sudo apt-get install -y -q chromium >/dev/null || echo "warning: could not install chromium (apt)"
	touch $@

# A robot computer's environment for the tests of `bpp serve`: openpi's client (numpy < 2) and bpp without torch.
$(ROBOT)/.installed: $(ROBOT_LOCK) pyproject.toml
	$(PYTHON) -m venv $(ROBOT)
	$(ROBOT)/bin/pip install $(PIPQ) --upgrade pip
	$(ROBOT)/bin/pip install $(PIPQ) -r $(ROBOT_LOCK)
	$(ROBOT)/bin/pip install $(PIPQ) --no-deps -e .
	touch $@

# LeRobot's environment for the tests of `bpp lerobot import|export` (marker lerobot): LeRobot 0.4.4, the newest
# release for Python 3.11, needs torch < 2.11, older than requirements.lock's. It is built as a LeRobot user's is: a
# new venv, LeRobot first, then bpp with its lerobot extra on top. lerobot-first.txt records what LeRobot installed,
# and bpp-plan.json what a plain `pip install -e .[lerobot]` (no constraints) would install or change then;
# tests/test_lerobot_install.py checks that bpp changed none of LeRobot's packages and would not have.
$(LEROBOT)/.installed: $(LEROBOT_LOCK) pyproject.toml
	rm -rf $(LEROBOT)
	$(PYTHON) -m venv $(LEROBOT)
	$(LEROBOT)/bin/pip install $(PIPQ) --upgrade pip
	$(LEROBOT)/bin/pip install $(PIPQ) -c $(LEROBOT_LOCK) lerobot
	$(LEROBOT)/bin/pip freeze --all > $(LEROBOT)/lerobot-first.txt
	$(LEROBOT)/bin/pip install $(PIPQ) --dry-run --report $(LEROBOT)/bpp-plan.json -e ".[lerobot]"
	$(LEROBOT)/bin/pip install $(PIPQ) -c $(LEROBOT_LOCK) -e ".[lerobot]" pytest pytest-xdist
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

# BPP_REQUIRE_ALL: a test whose optional part is missing fails here instead of being skipped. The LeRobot tests
# (tests/test_lerobot*.py, marked lerobot) run in LeRobot's environment, every other test in .venv.
test: lint docs
	BPP_REQUIRE_ALL=1 $(BIN)/pytest -q --durations=15 $(XDIST) -m "not lerobot"
	BPP_REQUIRE_ALL=1 $(LEROBOT)/bin/pytest -q --durations=15 $(XDIST) -m lerobot $(LEROBOT_TESTS)

test-fast: $(FAST)
	$(BIN)/pytest -q -m "not slow and not libero and not browser and not lerobot and not openpi" $(XDIST)

# The store's tests against zarr's lowest declared release (pyproject.toml), installed beside .venv's own in .floors/
# and put first on the path, so that the range's lower bound stays one the store works with.
ZARR_FLOOR := $(shell sed -n 's/.*"zarr>=\([0-9.]*\),.*/\1/p' pyproject.toml)
test-floors: $(ALL)
	rm -rf .floors
	$(BIN)/pip install $(PIPQ) --target .floors --no-deps "zarr==$(ZARR_FLOOR)" "crc32c>=2.7,<3"
	PYTHONPATH=.floors $(BIN)/python -c "import zarr; assert zarr.__version__ == '$(ZARR_FLOOR)', zarr.__file__"
	PYTHONPATH=.floors $(BIN)/pytest -q -p no:cacheprovider tests/test_store.py tests/test_store_integrity.py

# Re-resolve the locks from pyproject.toml's ranges, keeping their versions where they still fit (add --upgrade to
# move to the newest). The locks are for CPython 3.11 on Linux x86-64; elsewhere pip resolves the ranges in
# pyproject.toml.
lock: | $(BIN)/python
	$(BIN)/pip install $(PIPQ) "uv>=0.9,<1"
	$(BIN)/uv pip compile pyproject.toml --extra all --python-version 3.11.7 --python-platform x86_64-manylinux_2_28 \
		--annotation-style line -o $(LOCK)
	$(BIN)/uv pip compile requirements-lerobot.in pyproject.toml --extra lerobot --python-version 3.11.7 \
		--python-platform x86_64-manylinux_2_28 --annotation-style line -o $(LEROBOT_LOCK)
	$(BIN)/uv pip compile requirements-robot.in --python-version 3.11.7 --python-platform x86_64-manylinux_2_28 \
		--annotation-style line -o $(ROBOT_LOCK)
