# fullperc — see README.md. Every recipe runs in bash with scripts/env.sh sourced.
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
PYTHON ?= python3
VENV ?= .venv
export PYTHON VENV

ENV := source scripts/env.sh &&
COLCON_FLAGS ?= --symlink-install --event-handlers console_direct- summary+
PYTEST_ARGS ?=
# `make test` runs the suite on this many pytest-xdist workers (1 = no workers): three on the 2-core CI machine, as
# its multi-process tests spend about a fifth of their time waiting (DDS discovery, timers) and a third worker fills
# that (docs/testing.md). Whole test modules go to one worker (--dist loadscope): a module's fixtures are built once.
TEST_WORKERS ?= 3
XDIST = $(if $(filter-out 0 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadscope)
TASK ?= P-B-G-P

.PHONY: setup build test unit system lint clean demo bench dataset eval accuracy twin-report lock

setup:
	@scripts/setup.sh

# flock: parallel `make build` calls (several terminals, helpers) must not share build/ at once.
# colcon_skip.sh: with a system ROS, src/tf2_msgs (the wheels' missing tf2_msgs) is skipped for the system's.
build: setup
	@$(ENV) flock .build.lock colcon build $(COLCON_FLAGS) $$(scripts/colcon_skip.sh) \
	    --cmake-args -DPython3_EXECUTABLE=$$Python3_EXECUTABLE

lint: setup
	@$(ENV) ruff check src test bench scripts soak

test: build lint
	@$(ENV) python -m pytest $(XDIST) $(PYTEST_ARGS)

unit: build
	@$(ENV) python -m pytest $(XDIST) src $(PYTEST_ARGS)

system: build
	@$(ENV) python -m pytest $(XDIST) test $(PYTEST_ARGS)

demo: build
	@$(ENV) install/fullperc_eval/lib/fullperc_eval/supervisor demo --task $(TASK) --profile $(PROFILE) $(if $(CALIBRATION),--calibration $(CALIBRATION)) $(DEMO_ARGS)

bench: build
	@$(ENV) python bench/run_all.py

# Soak tests (minutes, not part of `make test`): every soak/soak_*.py, one JSON line per figure like `make bench`.
.PHONY: soak
soak: build
	@$(ENV) python soak/run_all.py

# Twin profile (paper | spec) and seed of `make dataset`; OUT defaults to bags/<profile>. `make eval` reads BAGS and
# writes JSON (default: the committed sample bags of PROFILE).
PROFILE ?= paper
SEED ?= 0
OUT ?= bags/$(PROFILE)
BAGS ?= bags/$(PROFILE)
JSON ?= $(BAGS)/eval.json
dataset: build
	@$(ENV) python -m fullperc_eval.sim.dataset --out $(OUT) --seed $(SEED) --profile $(PROFILE)

eval: build
	@$(ENV) python -m fullperc_eval.evaluation.evaluate_all --bags $(BAGS) --json $(JSON)

# Six tasks x SEEDS per profile (PROFILE=paper|spec|both), Table 1 as mean +- sd; FUSION=<fusion yaml> evaluates
# with another fusion configuration (e.g. static_links: calibrate).
# NOISE=builtin|calibrated|<noise-model file>: fullperc's noise model (calibrated: fitted per profile with
# fit_noise_model on calibration seeds 100-102, other twin installations than the evaluated ones).
SEEDS ?= 0-9
FUSION ?=
NOISE ?= builtin
accuracy: build
	@$(ENV) python -m fullperc_eval.evaluation.accuracy --seeds $(SEEDS) --profile $(PROFILE) \
	    $(if $(FUSION),--fusion-config $(FUSION)) --noise-model $(NOISE) --json bags/accuracy.json

# Raw-sensor statistics of a twin profile next to its targets (PROFILE=paper|spec|both, SEEDS default 0-1 here;
# with the default seeds it stores bags/<profile>/twin_report.json, which the suite checks).
twin-report: build
	@$(ENV) python -m fullperc_eval.evaluation.twin_report --profile $(PROFILE) \
	    $(if $(filter command line environment,$(origin SEEDS)),--seeds $(SEEDS),--seeds 0-1 --store bags)

# Re-pin requirements/lock-cpXY.txt from what is installed in the venv.
lock: setup
	@$(ENV) python scripts/lock.py

clean:
	rm -rf build install log .pytest_cache .ruff_cache
