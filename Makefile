# ucom-tools: `make demo` sets up .venv and runs the main job on the virtual fleet;
# `make test` runs lint, type checks and the test suite (compiled, and the pure path beside it);
# `make compiled` builds the compiled run time (demo, test and bench do it first),
# `make pure` removes it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-compiled test-pure lint bench soak clean compiled pure

# the run time's hot modules compiled with mypyc in place (ucom_tools/compiled.py lists
# them; tools/compile.py builds them, or says why not and leaves the package pure Python)
COMPILED := build/mypyc/done
COMPILED_SOURCES := $(shell sed -n 's/^    "ucom_tools\.\([a-z0-9_.]*\)",$$/ucom_tools.\1/p' \
    ucom_tools/compiled.py | tr . / | sed 's/$$/.py/')

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "ucom-tools needs Python >= 3.11"'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-compile -e '.[test,plot]'
	@touch $(STAMP)

$(COMPILED): $(STAMP) ucom_tools/compiled.py tools/compile.py $(COMPILED_SOURCES)
	$(BIN)/python tools/compile.py

compiled: $(COMPILED)

pure:
	$(BIN)/python tools/compile.py --clean

DEMO_STATE := $(VENV)/demo-state

demo: $(COMPILED)
	$(BIN)/ucom flash firmware_images/armar3.fl.S --virtual armar3 --state $(DEMO_STATE)
	$(BIN)/ucom remote run armar3 --virtual armar3 --state $(DEMO_STATE) --for 3 \
	    --set 'Right Eye Target=1000' --set 'Left Eye Target=-1000' \
	    --set 'Neck Yaw Target=-2000' --set 'Right Elbow Target=1500'

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

# the pure-Python path, where the suite above ran the compiled modules: the frame traces
# recorded from it bit for bit, the models', the simulated bus's and frame lengths' own
# tests, and the PC's frame path (its shortcuts against the plain way, and the receiving
# scan against the regular expressions it replaced)
PURE_TESTS := tests/test_fidelity.py tests/test_compiled.py tests/test_simbus.py \
    tests/test_board.py tests/test_armar3_model.py tests/test_lauron4_model.py \
    tests/test_mutants.py tests/test_canbits.py tests/test_frame_path.py \
    tests/test_pc_fast_paths.py tests/test_plain_data.py

# lint, then the pure-Python path (it needs no build), beside the build (mypyc type-checks
# on its own, with a cache of its own under build/: tools/compile.py); then the compiled suite alone: its fleets run on the
# wall clock and a CPU-bound job beside them slows it by more than that job's own length;
# each one's output together, when it ends
test: $(STAMP)
	@$(MAKE) --no-print-directory -j2 --output-sync=target lint compiled test-pure
	@$(MAKE) --no-print-directory test-compiled

test-compiled: $(COMPILED)
	$(BIN)/python -m pytest

# (beside the build: whether the build runs is the compiled suite's test)
test-pure: $(STAMP)
	UCOM_PURE_PYTHON=1 $(BIN)/python -m pytest -n 0 -p no:cacheprovider $(PURE_TESTS) \
	    --deselect tests/test_compiled.py::test_the_compiled_modules_run_when_built

# (benchmarks/soak.py is left out: make soak runs it)
bench: $(COMPILED)
	@fail=""; for b in benchmarks/*.py; do [ $$b = benchmarks/soak.py ] && continue; \
	echo "== $$b"; $(BIN)/python $$b || fail="$$fail $$b"; \
	done; if [ -n "$$fail" ]; then echo "targets not met in:$$fail"; exit 1; fi

# ARMAR-III served at 1 kHz for 30 minutes, 1 % frame loss, a fault a minute, the PC
# holding and rejoining (benchmarks/soak.py); not part of bench or test
soak: $(COMPILED)
	$(BIN)/python benchmarks/soak.py

clean:
	$(PYTHON) tools/compile.py --clean
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
