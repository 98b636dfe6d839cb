# Two commands set everything up on a fresh machine:
#   make demo   -- simulate a small campaign, fit it into a results store, write the report
#   make test   -- run the whole test suite (slow tests included)
# Both create or reuse the virtual environment in .venv and install what they need, pinned by
# constraints.txt (the versions the suite passed with; regenerate with `make constraints`).
# Tests run with OMP_NUM_THREADS=1: two xdist workers on two cores, no thread oversubscription;
# --dist loadscope runs each test module on one worker: a module fixture (a fitted campaign,
# the hidden-effect cases) is computed once, not once per worker.

PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed-$(shell cat pyproject.toml constraints.txt | sha256sum | cut -c1-12)
JOBS   ?= 2

.PHONY: venv demo test test-fast bench sample-data clean constraints validate validate-campaign validate-diagnose

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test,dask,postgres]"
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m pipelines.demo

test: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -n $(JOBS) --dist loadscope -q

test-fast: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -n $(JOBS) --dist loadscope -q -m "not slow"

# The fit's verdict over many recordings of both generators and both mills (issue 12's
# figures): acceptance at the global optimum and in local minima, accepted-and-right,
# accepted-but-wrong, interval coverage, wall time.  Resumable (out/validate/fit_study.jsonl);
# VALIDATE_ARGS="--plant 16 --ident 4" sets the sample.
validate: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m validation.fit_study $(VALIDATE_ARGS)

# A 12-recording wear campaign from the independent generator through the campaign, the
# report and its status JSON (issue 13's figures); out/validate/campaign.
validate-campaign: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m validation.campaign_study $(CAMPAIGN_ARGS)

# 'ident diagnose' with its fit on plant recordings with wear drawn per element (good, worn
# or critical) and per bearing (issue 13's element, faulty and bearing figures, and the fit
# study's figures on those gaps).  About 10 min per recording on one core;
# DIAGNOSE_ARGS="--mills cold-s5 --per-mill 6 --first-seed 1400" sets the sample.
validate-diagnose: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m validation.diagnose_study --fit --bars 2 $(DIAGNOSE_ARGS)

bench: $(STAMP)
	$(PY) -m benchmarks

sample-data: $(STAMP)
	$(PY) -m pipelines.sample_data

constraints: $(STAMP)
	$(PY) -m pip freeze --exclude-editable | grep -v "^-e" | sort -f > constraints.txt

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
