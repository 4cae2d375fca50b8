# hivemap: two commands set everything up on a fresh machine.
#   make test   create .venv, install hivemap + dev tools + system packages, run ruff, mypy, pytest
#   make demo   the same set-up, then render a small scenario, run server + agents, print the result
#               (the server keeps running for the viewer until Ctrl-C; DEMO_ARGS=--exit stops after the table)
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
# Debian packages the renderer (headless EGL/Mesa) and the browser tests need.
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 chromium chromium-driver docker-compose
STAMP := $(VENV)/.installed
# pytest-xdist processes for `make test`; each test file stays on one (its module fixtures run once).
TEST_WORKERS ?= 2

.PHONY: setup sysdeps test lint typecheck pytest demo bench clean

sysdeps:
	@scripts/install-sysdeps.sh $(APT_PACKAGES)

$(STAMP): pyproject.toml
	@command -v $(PY) >/dev/null || { echo "error: $(PY) not found; install Python 3.11" >&2; exit 1; }
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip setuptools wheel
	$(BIN)/pip install -q -e '.[dev]'
	@touch $(STAMP)

setup: sysdeps $(STAMP)

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: setup
	$(BIN)/mypy protocol server maps client sim eval cli

pytest: setup
	$(BIN)/pytest -q -x -n $(TEST_WORKERS) --dist loadfile --durations=15

test: lint typecheck pytest

demo: setup
	$(BIN)/python scripts/demo.py $(DEMO_ARGS)

bench: setup
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
