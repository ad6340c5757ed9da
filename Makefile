# Two commands do all the set-up on a fresh clone: `make demo` and `make test`.
# Both create .venv on first use and install the project (with its test extra) into it.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
DEMO   := demo-output

.PHONY: demo demo-batch lint test coverage test-science test-ops bench clean lock pip-check

# the project with its test and gw extras, every package at the version pinned in
# constraints.txt (resolved by pip with dependencies; `pip check` must be clean)
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,gw]'
	# (.ci/pip_check.py: plain `pip check`, but for the known line of the no-deps install
	# below, which an existing venv set up again already holds)
	$(BIN)/python .ci/pip_check.py
	# the `blind` extra (lisaglitch, lisa-gap) without dependencies: both declare torch, which the
	# tests never import (pyproject.toml says why); pinned in constraints.txt like the rest
	$(BIN)/python -m pip install --quiet --no-deps -c constraints.txt 'lisaglitch>=2.0' 'lisa-gap>=0.4'
	touch $(STAMP)

## pip-check: `pip check` of the venv as set up, every time `make test` or `make demo` runs: clean
## but for the one line the no-deps install above makes on purpose (lisaglitch requires torch),
## which .ci/pip_check.py prints as known; any other broken requirement stops the set-up
pip-check: $(STAMP)
	$(BIN)/python .ci/pip_check.py

## lock: refresh constraints.txt: the newest versions pip resolves for pyproject.toml in a fresh
## venv (then `make clean test` before committing the new pins)
lock:
	rm -rf .venv-lock && $(PYTHON) -m venv .venv-lock
	.venv-lock/bin/python -m pip install --quiet --upgrade pip
	.venv-lock/bin/python -m pip install --quiet -e '.[test,gw]'
	.venv-lock/bin/python -m pip check
	.venv-lock/bin/python -m pip install --quiet --no-deps 'lisaglitch>=2.0' 'lisa-gap>=0.4'
	{ sed -n '/^#/p' constraints.txt; .venv-lock/bin/python -m pip freeze --exclude-editable; } > constraints.txt.new
	mv constraints.txt.new constraints.txt && rm -rf .venv-lock

## demo: the main job on an embedded default: three mission days (Keplerian arms, all noises,
## paper coefficients, a slow drift on two coefficients and a 0.3 mm/rad step on one at 1.5 d)
## replayed through the five stage processes (ttl run), the coefficient table against the
## truth (ttl inspect), and the day around the flagged step refitted with a step in the model.
## The live fitter diagnoses its window at segments 23, 47 (the end of day 2, where the step is)
## and 71, the run's last (--diagnose-every 48: the first at half of it, then every 48, and the
## last segment; stages/fitter/schedule.py). Measured 2026-11-27 on a fresh clone, the venv
## included: `time make demo` 5 min 9 s, 657 MB in demo-output/ (README.md).
demo: $(STAMP) pip-check
	rm -rf $(DEMO)/pipeline && mkdir -p $(DEMO)/pipeline
	$(BIN)/ttl simulate --duration 3d --orbit keplerian --coeffs paper --seed 1 \
		--drift 12.phi.rx=0.05,13.eta.tx=-0.05 --step 1.5d:23.phi.tx=0.3 --telemetry $(DEMO)/pipeline/mission.h5
	$(BIN)/ttl run --telemetry $(DEMO)/pipeline/mission.h5 --run-id demo --recordings $(DEMO)/pipeline/recordings \
		--diagnose-every 48 --timeout 900
	$(BIN)/ttl inspect $(DEMO)/pipeline/recordings/demo --truth $(DEMO)/pipeline/mission.truth.h5
	@echo ""
	@echo "The monitor flagged a step at 1.5 d: refit the day around it with a step in the model"
	$(BIN)/ttl refit $(DEMO)/pipeline/recordings/demo --effects linear-ttl,step:t_step=1.5d --segments 24:47
	@echo ""
	@echo "Where to look:"
	@echo "  Rerun recording (noise vs requirement, coefficient trends, adequacy, alerts, diagnosis): $(BIN)/ttl view $(DEMO)/pipeline/recordings/demo (--web without a display)"
	@echo "  MCAP logs of the five stages:                                 $(DEMO)/pipeline/recordings/demo/*.mcap"
	@echo "  the batch analysis of one day, with the paper's figures:       make demo-batch"

## demo-batch: one mission day simulated, the 24 coefficients fitted, the TTL subtracted,
## the paper-style figures written (about 30 s).
demo-batch: $(STAMP)
	rm -rf $(DEMO)/batch && mkdir -p $(DEMO)/batch
	$(BIN)/ttl simulate --duration 1d --orbit keplerian --coeffs paper --seed 1 --telemetry $(DEMO)/batch/day.h5
	$(BIN)/ttl info $(DEMO)/batch/day.h5
	$(BIN)/ttl analyze $(DEMO)/batch/day.h5 --truth $(DEMO)/batch/day.truth.h5 --out $(DEMO)/batch/fit
	@echo "figures: $(DEMO)/batch/fit/asd_X.png $(DEMO)/batch/fit/coefficients.png; numbers: $(DEMO)/batch/fit/fit.json"

## test: the fast test suite, on every core (pytest-xdist, --dist worksteal: the tests are shared
## out in collection order and an idle worker takes half of a busy one's queue, so the workers
## finish together without a table of module timings; measured on the idle 2-core machine, with
## coverage: 519 s against 512 s for whole modules handed out longest first by such a table;
## a module's fixtures are made again on each worker that takes one of its tests, so make them
## cheap). 835 tests in 564 s without coverage on a fresh clone (2026-11-28).
## One BLAS thread per process: the workers already fill the cores, and OpenBLAS threads that
## wait for a busy core spin (measured on a loaded machine: docs/diagnostics.md, "Measured")
## The lint checks first (about a minute, mostly mypy), then the tests. Line coverage is
## `make coverage`'s: it costs 30-40 % more CPU in the in-process tests (measured on six ttlcore
## modules: 35-39 s -> 48-50 s user), which took the suite past its 10 minutes on 2 cores.
test: lint $(STAMP) pip-check
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --dist worksteal --durations=25

## coverage: the fast suite with line coverage of ttlcore, streamer and stages measured in the
## test processes, not in the stage processes they start (a summary of the files not fully
## covered, and the total)
coverage: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --dist worksteal --cov --cov-report=term:skip-covered

## lint: ruff (lint rules and the formatting, checked not applied) over the tree and mypy over
## ttlcore, streamer and stages (configured in pyproject.toml: [tool.mypy] files); `ruff check --fix .
## && ruff format .` applies the fixes
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

## test-science: slow full-day science checks
test-science: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n auto --dist worksteal -m science

## test-ops: long operations tests (live runs under attack: hostile-message fuzz, NaN gap, kills of each
## stage, of the router and of the launcher; three hosts in network namespaces; the chaos test, 2 days
## in 10-min segments with 20+ random kills, ~50 min alone): about 1.5 hours on 2 cores
test-ops: $(STAMP)
	$(BIN)/python -m pytest -q -m ops

## bench: benchmarks, each prints JSON
bench: $(STAMP)
	$(BIN)/python bench/simulate.py
	$(BIN)/python bench/tdi.py
	$(BIN)/python bench/analyze.py
	$(BIN)/python bench/fit.py
	$(BIN)/python bench/pipeline.py
	$(BIN)/python bench/rolling.py
	$(BIN)/python bench/gw.py
	$(BIN)/python bench/diagnose.py
	$(BIN)/python bench/mission.py

clean:
	rm -rf $(VENV) .venv-lock $(DEMO) *.egg-info
