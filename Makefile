# uav_vs: `make demo` and `make test` set up everything on a fresh machine.
PYTHON ?= python3.11
VENV := .venv
BIN := $(abspath $(VENV))/bin
STAMP := $(VENV)/.installed

# ROS 2 from the venv: ament index, Fast DDS shared-memory profile, local discovery.
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export FASTRTPS_DEFAULT_PROFILES_FILE := $(abspath config/fastdds_shm.xml)
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export PATH := $(BIN):$(PATH)

SOURCES := setup.py setup.cfg package.xml requirements.txt requirements-dev.txt \
	$(shell find uav_vs config resource -type f -not -name '*.pyc' 2>/dev/null)

.PHONY: install test bench demo clean

install: $(STAMP)

$(STAMP): $(SOURCES)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -r requirements-dev.txt
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation --force-reinstall .
	$(BIN)/python tools/link_ros_executables.py
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 test

bench: $(STAMP)
	$(BIN)/python -m bench

demo: $(STAMP)
	$(BIN)/python -m uav_vs.demo

clean:
	rm -rf $(VENV) build install log *.egg-info bench-results.jsonl demo-output
