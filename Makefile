# fluorocal: `make demo` and `make test` work on a fresh machine with only Python 3.11+.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check lint docs bench fixtures clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	rm -rf demo
	$(BIN)/fluorocal simulate demo/data --frames 8 --systems 2 --seed 7 --image-size 512 512
	$(BIN)/fluorocal run demo/data/fluorocal.toml
	$(BIN)/fluorocal inspect demo/data/fluorocal.toml

# one test process per core (pytest-xdist), each with one BLAS/OpenMP thread: the suite's numerics are small,
# and oversubscribed threads cost more than they give. --dist loadscope keeps a module's tests on one worker,
# so each module fixture is built once; the session fixtures are shared by the workers (tests/conftest.py).
# Bytecode is written beside the sources as usual (an environment's PYTHONDONTWRITEBYTECODE would make every
# worker and every CLI subprocess compile the sources and rewrite the test modules' asserts again); the
# libraries' bytecode compiled at installation is used from the first run.
# ARGS: more pytest options, e.g. `make test ARGS=--durations=15`
PYTEST := PYTHONDONTWRITEBYTECODE= OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --dist loadscope

# every feature, on small data (<= 3 min): the tests marked `check` are left to `make check`
test: $(STAMP)
	$(PYTEST) -m "not check" $(ARGS)

# the long checks: accuracy on larger simulated sets, long labelling sequences, the real radiographs (../shared/data),
# the attack battery (tests/attack: each case a test)
check: $(STAMP)
	$(PYTEST) -m check $(ARGS)

# the structure limits hold for tests/ and benchmarks/ too
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python .ci/limits.py pipeline stages tests benchmarks

# the documentation site (docs/, mkdocs.yml) built strictly: a broken link or reference fails
docs: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

fixtures: $(STAMP)
	$(BIN)/python fixtures/make_fixtures.py

clean:
	rm -rf demo .fluorocal build site *.egg-info
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +
