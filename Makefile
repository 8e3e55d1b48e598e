# fednav: two commands on a fresh machine with python3 and make.
#   make demo   service + simulator as processes on the demo scenario -> recordings/*.rrd + summary
#   make test   the whole test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench lint schemas screenshots clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip==25.3
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev,ros,replay,screenshots]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m fednav.simulators.demo

# one worker per core plus one, at most 4 (each file's tests on one worker: module fixtures built
# once). The tests' processes wait on Zenoh leases and sleeps: on 2 cores 3 workers kept the CPU
# 173 % busy and took 10:26 against 12:20 with 2 (docs/DESIGN-NOTES.md, "Tests").
TEST_WORKERS ?= $(shell $(PYTHON) -c 'import os; print(min(4, (os.cpu_count() or 1) + 1))')
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# every recording family in Rerun's web viewer, each tab captured by headless system chromium
# (apt-get install -y chromium); PNGs in docs/images/
screenshots: $(STAMP)
	$(PY) -m fednav.dashboards.screenshots --out docs/images

schemas: $(STAMP)
	$(PY) -m fednav.service.messages --write docs/schemas

clean:
	rm -rf $(VENV) build *.egg-info
