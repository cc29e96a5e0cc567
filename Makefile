# ucom-tools: `make demo` sets up .venv and runs the main job on the virtual fleet;
# `make test` runs lint, type checks and the test suite.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "ucom-tools needs Python >= 3.11"'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[test,plot]'
	@touch $(STAMP)

DEMO_STATE := $(VENV)/demo-state

demo: $(STAMP)
	$(BIN)/ucom flash firmware_images/armar3.fl.S --virtual armar3 --state $(DEMO_STATE)
	$(BIN)/ucom remote run armar3 --virtual armar3 --state $(DEMO_STATE) --for 3 \
	    --set 'Right Eye Target=1000' --set 'Left Eye Target=-1000' \
	    --set 'Neck Yaw Target=-2000' --set 'Right Elbow Target=1500'

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest

bench: $(STAMP)
	@fail=""; for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || fail="$$fail $$b"; \
	done; if [ -n "$$fail" ]; then echo "targets not met in:$$fail"; exit 1; fi

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
