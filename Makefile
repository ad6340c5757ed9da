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

## demo: simulate one mission day (Keplerian arms, all noises, paper coefficients), fit and subtract TTL
demo: $(STAMP)
	mkdir -p $(DEMO)
	$(BIN)/ttl simulate --duration 1d --orbit keplerian --coeffs paper --seed 1 --out $(DEMO)/day.h5
	$(BIN)/ttl info $(DEMO)/day.h5
	$(BIN)/ttl analyze $(DEMO)/day.h5 --truth $(DEMO)/day.truth.h5 --out $(DEMO)/fit
	@echo "figures: $(DEMO)/fit/asd_X.png $(DEMO)/fit/coefficients.png; numbers: $(DEMO)/fit/fit.json"

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

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
