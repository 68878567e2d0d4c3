# ecmgen: `make demo` and `make test` set up their own virtual environment.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out
JOBS   ?= 2

.PHONY: demo test bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/ecmgen build examples/panasonic-temperature/config.toml --out $(DEMO_OUT)

test: $(STAMP)
	$(PY) -m pytest -n $(JOBS) -q

bench: $(STAMP)
	$(PY) bench/bench_fit.py
	-$(PY) bench/bench_c.py
	-$(PY) bench/bench_diagnose.py
	-$(PY) bench/diagnose_suite.py
	-$(PY) bench/real_cells.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info src/*.egg-info .pytest_cache
