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

# An editable install: code and config are used from the checkout, so only these
# files change what is installed.
SOURCES := setup.py setup.cfg package.xml requirements.txt requirements-dev.txt \
	tools/install_ros_prefix.py $(wildcard config/*)

.PHONY: install test bench demo clean

install: $(STAMP)

$(STAMP): $(SOURCES)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -r requirements-dev.txt
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	$(BIN)/python tools/install_ros_prefix.py
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 test

bench: $(STAMP)
	$(BIN)/python -m bench

demo: $(STAMP)
	$(BIN)/python -m uav_vs.demo $(if $(BAG),--bag $(BAG)) $(if $(AUTOPILOT),--autopilot $(AUTOPILOT))

clean:
	rm -rf $(VENV) build install log *.egg-info bench-results.jsonl demo-output
