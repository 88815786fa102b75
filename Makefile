PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: sitl test bench dialect clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

sitl: $(STAMP)
	$(PY) -m fsw.main --sitl $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q --benchmark-disable $(ARGS)

bench: $(STAMP)
	$(PY) -m pytest -q tests/benchmarks --benchmark-only --benchmark-json=bench.json
	$(PY) tests/benchmarks/report.py bench.json

dialect: $(STAMP)
	$(PY) -m fsw.telemetry.dialect --generate

# the result tables in docs/ from the benchmarks' JSON (standard library only: no venv needed)
.PHONY: docs
docs:
	$(PYTHON) docs/tables.py

clean:
	rm -rf $(VENV) .pytest_cache .benchmarks build *.egg-info
