# twinmon: two commands on a fresh machine -- `make run` and `make test`.
# Each stage output is a file target with its real dependencies, so `make` re-runs only
# what changed (the make-driven batch runs users have).

PYTHON  ?= python3
VENV    ?= .venv
PY      := $(VENV)/bin/python
TWINMON := $(VENV)/bin/twinmon
STAMP   := $(VENV)/.twinmon-installed
OUT     ?= out
CONFIG  ?= configs/pump.yaml
OBS     ?= data/fleet.h5
TEST_JOBS ?= 2
TRUTH   ?= data/fleet_truth.h5
GAP_OBS ?= data/fleet_gap.h5
FMU_SRC := $(wildcard fmus/PumpCircuit/modelDescription.xml fmus/PumpCircuit/sources/*)
PKG_SRC := $(shell find twinmon -name '*.py')

.PHONY: all setup fmu run test bench data example clean help
all: run

help:
	@echo "make run    set up, build the FMU, run the whole pipeline on $(OBS), print the report path"
	@echo "make test   set up, then the test suite (TEST_JOBS=2 processes)"
	@echo "make bench  the long statistical checks (tests marked slow), then the benchmarks (figures printed)"
	@echo "make data   regenerate the shipped fleet data from configs/fleet.yaml and fleet_gap.yaml"
	@echo "make example  the second worked example (a DC drive, fmus/DCDrive) end to end"
	@echo "make $(OUT)/report/index.html   stage by stage, only what changed"

# --- set-up: a virtualenv with the package installed (editable) ------------------------
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $@

# The package's bytecode written once here: where Python does not write it on import
# (PYTHONDONTWRITEBYTECODE, a read-only checkout) every twinmon command would otherwise
# compile its modules again (0.4 s a command; the suite starts a few hundred).
setup: $(STAMP) fmu
	@$(PY) -m compileall -q twinmon

fmu: $(STAMP)
	$(TWINMON) build-fmu fmus/PumpCircuit

# --- the pipeline, one target per stage output ------------------------------------------
$(OUT)/simulations.h5: $(CONFIG) $(FMU_SRC) | $(STAMP)
	$(TWINMON) simulate -c $(CONFIG) -o $@

$(OUT)/surrogate.h5: $(OUT)/simulations.h5 $(CONFIG)
	$(TWINMON) reduce -c $(CONFIG) --simulations $< -o $@

$(OUT)/posterior.h5: $(OUT)/surrogate.h5 $(OBS) $(CONFIG)
	$(TWINMON) calibrate -c $(CONFIG) --surrogate $< --observations $(OBS) -o $@

$(OUT)/forecast.h5: $(OUT)/posterior.h5 $(OUT)/surrogate.h5 $(CONFIG)
	$(TWINMON) forecast -c $(CONFIG) --posterior $< --surrogate $(OUT)/surrogate.h5 -o $@

$(OUT)/gap.h5: $(GAP_OBS) $(CONFIG) $(FMU_SRC) | $(STAMP)
	$(TWINMON) diagnose -c $(CONFIG) --observations $(GAP_OBS) -o $@

$(OUT)/report/index.html: $(OUT)/forecast.h5 $(OUT)/posterior.h5 $(OUT)/surrogate.h5 $(OUT)/simulations.h5 $(OUT)/gap.h5 $(OBS)
	$(TWINMON) report -c $(CONFIG) --workdir $(OUT) --observations $(OBS) --truth $(TRUTH) -o $(OUT)/report

# --- the two commands of the README ----------------------------------------------------
run: setup
	$(TWINMON) run -c $(CONFIG) --observations $(OBS) --truth $(TRUTH) \
	    --gap-observations $(GAP_OBS) --workdir $(OUT)

# The suite on TEST_JOBS processes (pytest-xdist): CI has two cores, and most tests use one.
# Each module on one worker (--dist loadscope): its fixtures are made once, not once per
# worker that runs some of its tests (20-50 s each for the pipelines they run).
# The long statistical checks (marked slow) run with the benchmarks.
test: setup
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadscope -m "not slow" tests

bench: setup
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadscope -m slow tests
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

data: setup
	$(TWINMON) fabricate -c configs/fleet.yaml -o data/fleet.h5 --truth data/fleet_truth.h5
	$(TWINMON) fabricate -c configs/fleet_gap.yaml -o data/fleet_gap.h5 --truth data/fleet_gap_truth.h5

# --- the second worked example: a DC drive, not a pump (README, "A second machine") ------
EXAMPLE_OUT ?= out-dcdrive
example: setup
	$(TWINMON) build-fmu fmus/DCDrive
	$(TWINMON) fabricate -c configs/dcdrive_fleet.yaml -o $(EXAMPLE_OUT)/fleet.h5 \
	    --truth $(EXAMPLE_OUT)/fleet_truth.h5
	$(TWINMON) fabricate -c configs/dcdrive_gap.yaml -o $(EXAMPLE_OUT)/gap_fleet.h5 \
	    --truth $(EXAMPLE_OUT)/gap_fleet_truth.h5
	$(TWINMON) run -c configs/dcdrive.yaml --observations $(EXAMPLE_OUT)/fleet.h5 \
	    --truth $(EXAMPLE_OUT)/fleet_truth.h5 --gap-observations $(EXAMPLE_OUT)/gap_fleet.h5 \
	    --workdir $(EXAMPLE_OUT)

clean:
	rm -rf $(OUT) $(EXAMPLE_OUT) fmus/*/.build
