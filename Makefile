PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: sitl test test-slow lint bench dialect clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

sitl: $(STAMP)
	$(PY) -m hil.sitl $(ARGS)

# the fast tier on both cores; the lint first (it takes a second)
test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n 2 -m "not slow" --benchmark-disable $(ARGS)

# long runs and the 10,000-case fuzz properties
test-slow: $(STAMP)
	$(PY) -m pytest -q -n 2 -m slow --benchmark-disable $(ARGS)

lint: $(STAMP)
	$(PY) -m ruff check .

bench: $(STAMP)
	$(PY) -m pytest -q tests/bench/test_speed.py --benchmark-only --benchmark-json=bench.json
	$(PY) tests/bench/report.py bench.json

dialect: $(STAMP)
	$(PY) -m fsw.telemetry.dialect --generate

# the result tables in docs/ from the benchmarks' JSON (standard library only: no venv needed)
.PHONY: docs
docs:
	$(PYTHON) docs/tables.py

clean:
	rm -rf $(VENV) .pytest_cache .benchmarks build *.egg-info
