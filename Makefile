# Two commands do all the set-up on a fresh clone: `make demo` and `make test`.
# Both create .venv on first use and install the project (with its test extra) into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
DEMO   := demo-output

.PHONY: demo test test-science bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	# lisagwresponse (outside reference of the GW response tests) pins lisaconstants < 2,
	# which lisainstrument cannot use; it only needs a few constants, so install it alone
	$(BIN)/python -m pip install --quiet --no-deps lisagwresponse healpy
	touch $(STAMP)

## demo: the main job on an embedded default. Simulate three mission days (Keplerian arms,
## paper coefficients, a slow drift on two coefficients and a step on one), replay them through
## the five stage processes (ttl run), then print the run's summary and coefficient trends
## (ttl inspect) with the truth beside them, and say where to look.
demo: $(STAMP)
	rm -rf $(DEMO) && mkdir -p $(DEMO)
	$(BIN)/ttl simulate --duration 3d --orbit keplerian --coeffs paper --seed 1 \
		--drift 12.phi.rx=0.05,13.eta.tx=-0.05 --step 1.5d:23.phi.tx=0.3 --out $(DEMO)/mission.h5
	$(BIN)/ttl run --telemetry $(DEMO)/mission.h5 --run-id demo --recordings $(DEMO)/recordings
	$(BIN)/ttl inspect $(DEMO)/recordings/demo --truth $(DEMO)/mission.truth.h5
	@echo ""
	@echo "Where to look:"
	@echo "  Rerun recording (ASDs, coefficient trends, alerts): $(BIN)/ttl view $(DEMO)/recordings/demo"
	@echo "  MCAP logs of the five stages:                       $(DEMO)/recordings/demo/*.mcap"
	@echo "  Batch analysis of the mission with paper-style figures:"
	@echo "      $(BIN)/ttl analyze $(DEMO)/mission.h5 --truth $(DEMO)/mission.truth.h5 --out $(DEMO)/fit"

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

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
