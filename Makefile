# Two commands do all the set-up on a fresh clone: `make demo` and `make test`.
# Both create .venv on first use and install the project (with its test extra) into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
DEMO   := demo-output

.PHONY: demo demo-pipeline test test-science bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	# lisagwresponse (outside reference of the GW response tests) pins lisaconstants < 2,
	# which lisainstrument cannot use; it only needs a few constants, so install it alone
	$(BIN)/python -m pip install --quiet --no-deps lisagwresponse healpy
	touch $(STAMP)

## demo: the batch job on an embedded default: simulate one mission day (Keplerian arms, all
## noises, paper coefficients), fit the 24 coefficients, subtract, and write the paper-style figures.
demo: $(STAMP)
	rm -rf $(DEMO) && mkdir -p $(DEMO)
	$(BIN)/ttl simulate --duration 1d --orbit keplerian --coeffs paper --seed 1 --out $(DEMO)/day.h5
	$(BIN)/ttl info $(DEMO)/day.h5
	$(BIN)/ttl analyze $(DEMO)/day.h5 --truth $(DEMO)/day.truth.h5 --out $(DEMO)/fit
	@echo "figures: $(DEMO)/fit/asd_X.png $(DEMO)/fit/coefficients.png; numbers: $(DEMO)/fit/fit.json"
	@echo "the streaming pipeline on three days with a drift and a step: make demo-pipeline"

## demo-pipeline: three mission days (a slow drift on two coefficients, a step on one) replayed
## through the five stage processes (ttl run), then ttl inspect against the truth.
demo-pipeline: $(STAMP)
	rm -rf $(DEMO)/pipeline && mkdir -p $(DEMO)/pipeline
	$(BIN)/ttl simulate --duration 3d --orbit keplerian --coeffs paper --seed 1 \
		--drift 12.phi.rx=0.05,13.eta.tx=-0.05 --step 1.5d:23.phi.tx=0.3 --out $(DEMO)/pipeline/mission.h5
	$(BIN)/ttl run --telemetry $(DEMO)/pipeline/mission.h5 --run-id demo --recordings $(DEMO)/pipeline/recordings --timeout 900
	$(BIN)/ttl inspect $(DEMO)/pipeline/recordings/demo --truth $(DEMO)/pipeline/mission.truth.h5
	@echo ""
	@echo "The monitor flagged a step at 1.5 d: refit the day around it with a step in the model"
	$(BIN)/ttl refit $(DEMO)/pipeline/recordings/demo --effects linear-ttl,step:t_step=1.5d --segments 24:47
	@echo ""
	@echo "Where to look:"
	@echo "  Rerun recording (ASDs, coefficient trends, alerts): $(BIN)/ttl view $(DEMO)/pipeline/recordings/demo"
	@echo "  MCAP logs of the five stages:                       $(DEMO)/pipeline/recordings/demo/*.mcap"

## test: the fast test suite (well under 20 minutes on 2 cores)
test: $(STAMP)
	$(BIN)/python -m pytest -q

## test-science: slow full-day science checks
test-science: $(STAMP)
	$(BIN)/python -m pytest -q -m science

## bench: benchmarks, each prints JSON
bench: $(STAMP)
	$(BIN)/python bench/simulate.py
	$(BIN)/python bench/tdi.py
	$(BIN)/python bench/fit.py
	$(BIN)/python bench/pipeline.py
	$(BIN)/python bench/gw.py
	$(BIN)/python bench/diagnose.py

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
