# Two commands do all set-up: `make test` and `make demo` create .venv and install on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/demo

.PHONY: test demo lint bench clean browser

$(STAMP): pyproject.toml setup.py robot_agent/slam/_kernels.c shared/_kernels.c shared/_common.h  # the C kernels are built by the install
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

test: $(STAMP) browser
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n auto --dist loadfile

browser:  # the headless browser of the live-view test (Debian's chromium + chromedriver), when missing
	@.ci/browser

demo: $(STAMP)
	$(BIN)/fleet-slam demo --robots 3 --world office --out $(OUT)

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_sim.py

clean:
	rm -rf $(VENV) out .pytest_cache
