PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: sitl test test-slow lint bench dialect clean install-target

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test]'
	$(PY) -c "from fsw.flight import load_compiled_kernels; load_compiled_kernels()"   # numba's cache, once
	touch $(STAMP)

sitl: $(STAMP)
	$(PY) -m hil.sitl $(ARGS)

# the fast tier on both cores; the lint first (it takes a second)
test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n 2 -m "not slow" --benchmark-disable $(ARGS)

# stock MAVProxy for the slow tier's test against it (the `tools` extra)
TOOLS := $(VENV)/.tools
$(TOOLS): $(STAMP)
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test,tools]'
	touch $(TOOLS)

# long runs, the 10,000-case fuzz properties, stock MAVProxy against the box
test-slow: $(TOOLS)
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

# on the flight computer, as root: the service user in the device groups, a venv with the target extra in
# $(PREFIX), the example configuration (kept if present), udev rules for the groups, the systemd unit
# (docs/target.md)
PREFIX       ?= /opt/debris-box
SERVICE_USER ?= debris
install-target:
	@test "$$(id -u)" = 0 || { echo "install-target: run it as root (sudo make install-target)" >&2; exit 1; }
	for g in i2c spi gpio dialout; do getent group $$g >/dev/null || groupadd --system $$g; done
	id -u $(SERVICE_USER) >/dev/null 2>&1 || useradd --system --user-group --no-create-home \
	    --home-dir /var/lib/debris-box --shell /usr/sbin/nologin $(SERVICE_USER)
	usermod -a -G i2c,spi,gpio,dialout $(SERVICE_USER)
	$(PYTHON) -m venv $(PREFIX)/venv
	$(PREFIX)/venv/bin/pip install --quiet -c constraints.txt '.[target]'
	$(PREFIX)/venv/bin/python -c "from fsw.flight import load_compiled_kernels; load_compiled_kernels()"
	install -m 0644 docs/target.md $(PREFIX)/target.md
	install -d -m 0750 -g $(SERVICE_USER) /etc/debris-box
	test -e /etc/debris-box/box.toml || install -m 0640 -g $(SERVICE_USER) deploy/box.toml /etc/debris-box/box.toml
	test -e /etc/udev/rules.d/99-debris-box.rules || install -m 0644 deploy/99-debris-box.rules /etc/udev/rules.d/
	install -m 0644 deploy/debris-box.service /etc/systemd/system/debris-box.service
	systemctl daemon-reload
	@echo "next: the mission key as /etc/debris-box/mission.key (owner $(SERVICE_USER), mode 0600), /etc/debris-box/box.toml"
	@echo "      edited for this board, then: systemctl enable --now debris-box; journalctl -u debris-box -f"
