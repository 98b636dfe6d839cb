# Two commands set everything up on a fresh machine:
#   make demo   -- simulate a small campaign, fit it into a results store, write the report
#   make test   -- run the whole test suite (slow tests included)
# Both create or reuse the virtual environment in .venv and install what they need.
# Tests run with OMP_NUM_THREADS=1: two xdist workers on two cores, no thread oversubscription;
# --dist loadscope runs each test module on one worker: a module fixture (a fitted campaign,
# the hidden-effect cases) is computed once, not once per worker.

PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed-$(shell cat pyproject.toml | sha256sum | cut -c1-12)
JOBS   ?= 2

.PHONY: venv demo test test-fast bench sample-data clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,dask,postgres]"
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m pipelines.demo

test: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -n $(JOBS) --dist loadscope -q

test-fast: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -n $(JOBS) --dist loadscope -q -m "not slow"

bench: $(STAMP)
	$(PY) -m benchmarks

sample-data: $(STAMP)
	$(PY) -m pipelines.sample_data

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
