# scanloc — set-up and everyday commands. Everything builds from crates.io
# with the machine's Rust toolchain; nothing needs installing by hand.

CARGO   ?= cargo
BIN     := target/release/scanloc
MANIFEST ?= experiments/paper.yaml

.PHONY: all build test python pytest lint fmt reproduce-paper bound tracking cv calibrate bench bench-registry fuzz clean

all: build

build:
	$(CARGO) build --release --locked

# The test suite: formatting, then every unit and integration test in the
# release profile (the simulator and the CNN are too slow unoptimised),
# then the Python package's tests (pytest in .venv, see `python`).
test:
	$(CARGO) fmt --check
	$(CARGO) test --release --locked
	$(MAKE) pytest

# The Python package (python/, docs/python.md) built into .venv: the
# virtual environment and the test requirements are made once (again when
# python/requirements-test.txt changes), the extension module is rebuilt
# by maturin on every call (a no-op build when nothing changed).
PYTHON ?= python3
VENV   := .venv
VENV_PY := $(VENV)/bin/python
$(VENV)/.requirements: python/requirements-test.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV_PY) -m pip install --quiet --disable-pip-version-check -r python/requirements-test.txt
	touch $@

python: $(VENV)/.requirements build
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" MATURIN_PEP517_ARGS="--locked" $(VENV_PY) -m pip install --quiet --disable-pip-version-check \
		--no-build-isolation --no-deps --force-reinstall ./python

# pytest over python/tests (exit 5, no test collected, is a failure).
pytest: python
	SCANLOC_BIN=$(BIN) $(VENV_PY) -m pytest python/tests -q -p no:cacheprovider; \
		status=$$?; if [ $$status -eq 5 ]; then echo "pytest collected no test"; exit 1; fi; exit $$status

lint:
	$(CARGO) clippy --release --locked --all-targets -- -D warnings

fmt:
	$(CARGO) fmt

# The paper's experiment end to end: simulate the datasets, run TrackPy's
# algorithm and train/run the CNN, print Table 1 beside the paper's, write
# the report. Everything is cached in registry/: a second run takes seconds.
# CALIBRATE=1 first reruns the brightness sweep (docs/metric.md).
reproduce-paper: build
	@if [ -n "$(CALIBRATE)" ]; then $(BIN) calibrate $(MANIFEST); fi
	$(BIN) run $(MANIFEST)
	$(BIN) report latest --out reports/paper
	@echo "report: reports/paper/report.md; audit with '$(BIN) registry runs', re-execute with '$(BIN) reproduce RUN'"

# The attainable bound on the whole of the paper's test sets beside the
# paper's TrackPy and CNN (experiments/bound.yaml): the likelihood detector
# told each set's D and told only the training range. After
# reproduce-paper only the two bounds are computed, about 22 minutes on 2
# idle cores (before it, the datasets and the CNN are made first, about 15
# more); the report says which of the paper's cells any method can win.
bound: build
	$(BIN) run experiments/bound.yaml
	$(BIN) report latest --out reports/bound
	@echo "report: reports/bound/report.md"

# From localisations to trajectories and D (experiments/tracking.yaml,
# docs/tracking.md): continuous recordings localised by crocker-grier and
# by a CNN trained for recordings, linked, D estimated; prints the
# tracking measures and the D table and writes the report. Cached in
# registry/: a second run takes seconds.
tracking: build
	$(BIN) run experiments/tracking.yaml
	$(BIN) report latest --out reports/tracking
	@echo "report: reports/tracking/report.md"

# Five-fold cross-validation of the paper's CNN (the manifest's
# cross_validation block; five trainings of its network, each, like the
# paper run's, 8 epochs on fresh frames only, selected on its held-out
# fifth of the training frames: about 80 minutes on 2 idle cores). Resumes
# where an interrupted sweep stopped.
# EXECUTOR=slurm runs the folds as a Slurm job array and waits for it
# (README, "Running on a cluster"); SWEEP_ARGS passes further options
# (--partition, --time, --max-parallel, --jobs, ...).
EXECUTOR ?= local
SWEEP_ARGS ?=
cv: build
	$(BIN) cv $(MANIFEST) --executor $(EXECUTOR) $(if $(filter slurm,$(EXECUTOR)),--wait) $(SWEEP_ARGS)

# The brightness sweep alone: N_qd against the paper's TrackPy row
# (docs/metric.md, "Calibrating the brightness").
calibrate: build
	$(BIN) calibrate $(MANIFEST)

# Benchmarks: throughput against the references, and run time against error.
bench: build
	$(BIN) bench simulate
	$(BIN) bench locate
	$(BIN) bench train
	$(BIN) bench link
	$(BIN) bench tradeoffs --out reports/bench

# A fully cached run of the paper manifest (blob verification included):
# the first run fills a scratch registry, the next three are timed.
bench-registry: build
	@rm -rf target/bench-registry
	$(BIN) run $(MANIFEST) --registry target/bench-registry > /dev/null
	@for i in 1 2 3; do /usr/bin/env time -f "cached run: %e s wall, %M KB max RSS" \
		$(BIN) run $(MANIFEST) --registry target/bench-registry --json > /dev/null; done

# Fuzzing: the manifest loader on arbitrary, YAML-like and mutated text,
# the .npy/.tif readers on damaged and random files, and the command line
# on random simulate/locate/score arguments and CSV/TIFF/.npy bytes, and
# `registry import` on damaged and crafted shards (called
# in-process, under a per-case allocation limit and time limit; case files
# in /dev/shm), FUZZ_CASES cases per property (proptest; `make test` runs a
# few dozen to a few thousand). Run at a low priority: it is long.
# Measured (2 cores shared with other work, nice 10): 300,000 cases of
# every property in about 22 minutes, simulate the slowest (~250 cases/s);
# a progress line every 10,000 command-line cases.
FUZZ_CASES ?= 300000
fuzz:
	SCANLOC_FUZZ_CASES=$(FUZZ_CASES) nice -n 10 $(CARGO) test --release --locked \
		--test it -- never_panic refused_cleanly

clean:
	$(CARGO) clean
