# ecmgen: `make demo` and `make test` set up their own virtual environment.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
FLEET_OUT ?= fleet-demo
JOBS   ?= 2

.PHONY: demo fleet-demo test bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/ecmgen build examples/panasonic-temperature/config.toml --out $(DEMO_OUT)

# a synthetic ageing study (6 cells x 4 check-ups, one cell ageing 3x faster) built by
# `ecmgen fleet` on a local Dask cluster: $(FLEET_OUT)/fleet/fleet.csv and trend plots
fleet-demo: $(STAMP)
	$(PY) -c "from ecmgen.diagnosis.synthstudy import make_study, write_study; \
	write_study(make_study(cells=6, checkups=4, seed=1), '$(FLEET_OUT)/study')"
	$(VENV)/bin/ecmgen fleet $(FLEET_OUT)/study/manifest.csv --out $(FLEET_OUT)/fleet

test: $(STAMP)
	$(PY) -m pytest -n $(JOBS) -q

bench: $(STAMP)
	$(PY) bench/bench_fit.py
	-$(PY) bench/bench_c.py
	-$(PY) bench/bench_diagnose.py
	-$(PY) bench/diagnose_suite.py
	-$(PY) bench/real_cells.py
	-$(PY) bench/bench_speed.py --check

clean:
	rm -rf $(VENV) $(DEMO_OUT) $(FLEET_OUT) build *.egg-info src/*.egg-info .pytest_cache
