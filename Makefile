# sonarsim: the two README commands are `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed
DEMO   ?= demo_out

.PHONY: install demo test test-fast bench docs clean llvm

install: $(STAMP) llvm

# Reinstall only when the project metadata changes (idempotent).
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,bench,batch]"
	touch $(STAMP)

# Dr.Jit's CPU backend needs libLLVM >= 16 (Debian 12's default 15 aborts).
llvm: $(STAMP)
	@$(PY) scripts/ensure_llvm.py

demo: install
	$(PY) scripts/demo.py --out $(DEMO)

# Two pytest-xdist workers, whole files per worker (module fixtures are built once), the
# costliest files first (tests/conftest.py COSTLIEST_FIRST); TEST_WORKERS=0 runs serially.
TEST_WORKERS ?= 2
XDIST = $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder)
# Python's bytecode cache stays on for the tests even where the environment sets
# PYTHONDONTWRITEBYTECODE: every xdist worker collects every test module, and pytest's
# assertion rewriting of them, with the project's own modules, cost 9.0 CPU-s per collection
# uncached against 3.9 cached (`pytest --co`); the caches go to the gitignored __pycache__/.
CACHE_BYTECODE = PYTHONDONTWRITEBYTECODE=

test: install
	$(CACHE_BYTECODE) $(PY) -m pytest -q $(XDIST)

test-fast: install
	$(CACHE_BYTECODE) $(PY) -m pytest -q $(XDIST) -m "not slow"

# The Python API reference (pdoc, from the docstrings) into docs/api/ (not committed).
docs: install
	$(PY) -m pdoc --docformat restructuredtext --output-directory docs/api sonarsim recon
	@echo "API reference: docs/api/index.html"

bench: install
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache build *.egg-info docs/api
