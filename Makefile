# Two commands for a fresh Debian 12 machine: `make demo` and `make test`.
VENV := .venv
BIN := $(VENV)/bin
export PYOPENGL_PLATFORM ?= egl

.PHONY: demo test lint bench setup dev clean

# What running needs; `make test` adds the dev tools (pytest, ruff, mypy, scikit-image...).
setup: $(VENV)/.installed
dev: $(VENV)/.dev

$(VENV)/.installed: pyproject.toml scripts/install-system-deps.sh
	sh scripts/install-system-deps.sh
	python3 -m venv $(VENV)
	@echo "installing facewire and what it runs on into $(VENV) (about 800 MB; a few minutes)"
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --progress-bar on -e .
	touch $@

$(VENV)/.dev: $(VENV)/.installed
	$(BIN)/pip install --progress-bar on -e '.[dev]'
	touch $@

demo: setup
	$(BIN)/facewire demo

test: dev
	sh scripts/install-system-deps.sh --test
	$(BIN)/python -m pytest -q

lint: dev
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: dev
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-output.mp4 demo-compare.mp4 demo-stats.json
