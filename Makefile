# Two commands do everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-all bench clean venv

venv: $(STAMP)

# Re-install when the package metadata changes.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/tofjax demo --out out/demo --overwrite

# Two workers (the machines have two cores; most of the suite's time is single-threaded XLA
# compilation), one file per worker so module fixtures (fits, simulations) are built once.
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

test-all: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m ""

bench: $(STAMP)
	$(PY) experiments/bench_forward.py --out out/bench
	$(PY) experiments/bench_acquire.py --out out/bench

clean:
	rm -rf out .pytest_cache
