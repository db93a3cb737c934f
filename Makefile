# Two commands for a fresh Debian 12 machine: `make demo` and `make test`.
VENV := .venv
BIN := $(VENV)/bin
export PYOPENGL_PLATFORM ?= egl

.PHONY: demo test lint bench setup clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml scripts/install-system-deps.sh
	sh scripts/install-system-deps.sh
	python3 -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

demo: setup
	$(BIN)/facewire demo

test: setup
	sh scripts/install-system-deps.sh --test
	$(BIN)/python -m pytest -q

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: setup
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-output.mp4 demo-compare.mp4 demo-stats.json
