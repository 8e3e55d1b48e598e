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

# one worker per core, at most 4 (each file's tests on one worker: module fixtures built once)
test: $(STAMP)
	$(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile

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
