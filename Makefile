# uav_vs: `make demo` and `make test` set up everything on a fresh machine.
PYTHON ?= python3.11
VENV := .venv
BIN := $(abspath $(VENV))/bin
STAMP := $(VENV)/.installed

# ROS 2 from the venv: ament index, Fast DDS shared-memory profile, local discovery.
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export FASTRTPS_DEFAULT_PROFILES_FILE := $(abspath config/fastdds_shm.xml)
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
SYSTEM_PATH := $(PATH)
export PATH := $(BIN):$(SYSTEM_PATH)

# An editable install: code and config are used from the checkout, so only these
# files (and the interface definitions built into the venv) change what is installed.
SOURCES := setup.py setup.cfg package.xml requirements-tools.txt \
	tools/install_ros_prefix.py $(wildcard config/*) $(wildcard launch/*) \
	tools/build_interfaces.py $(shell find tools/interfaces -type f)

# The same suite on the versions a ROS 2 Jazzy host on Ubuntu 24.04 installs from apt,
# in its own venv, with the environment above pointed at that venv.
UBUNTU_VENV := .venv-ubuntu2404
UBUNTU_BIN := $(abspath $(UBUNTU_VENV))/bin
UBUNTU_STAMP := $(UBUNTU_VENV)/.installed
# The whole suite by default; CI runs CORE_TESTS there (`make test-ubuntu2404
# UBUNTU_TESTS='$$(CORE_TESTS)'`): the algorithms, the simulator and the MAVLink session's
# limits, the code that calls NumPy, OpenCV and SciPy, without starting ROS processes (the
# session's real-time flights use the same pymavlink in both venvs: not again there).
UBUNTU_TESTS ?= test
CORE_TESTS := $(addprefix test/test_,$(addsuffix .py,body_pose calibration_error camera \
	camera_effects delay_line docs features frame_sync frames fuzzy_control fuzzy_engine \
	ground_scene homography klt landmarks landmarks_megamind liveness mavlink_limits \
	onboard_scene oxford plane_geometry plane_pose plane_pose_covariance pose_covariance \
	pose_filter rig_timing sensor_switches servo sim_world target_tracking template_align \
	triangulation))

.PHONY: install test test-loaded test-ubuntu2404 fuzz bench demo clean

install: $(STAMP)

# One recipe for both venvs: $(1) the venv, $(2) its requirements file. Both install the
# checkout in editable mode, which writes uav_vs.egg-info into it: one at a time (CI
# installs the two venvs side by side).
define install_venv
	test -x $(1)/bin/python || $(PYTHON) -m venv $(1)
	$(1)/bin/python -m pip install -q -r $(2)
	mkdir -p build
	flock build/editable-install.lock \
	  $(1)/bin/python -m pip install -q --no-deps --no-build-isolation -e .
	$(1)/bin/python tools/install_ros_prefix.py
	$(1)/bin/python tools/build_interfaces.py
	touch $(1)/.installed
endef

$(STAMP): $(SOURCES) requirements.txt requirements-dev.txt
	$(call install_venv,$(VENV),requirements-dev.txt)

$(UBUNTU_STAMP): $(SOURCES) requirements-ubuntu2404.txt
	$(call install_venv,$(UBUNTU_VENV),requirements-ubuntu2404.txt)

# --dist loadscope: a module's tests run in one worker, so a module-scoped fixture (a SITL
# flight, the fuzz harness's nodes) starts once, never twice on the same ports; in the
# order test/conftest.py gives (--no-loadscope-reorder), the heavy modules on one worker,
# the waiting ones on a third (test/scheduling.py). The JUnit record (for a CI's test view)
# gives each test's worker and start time.
test: $(STAMP)
	$(BIN)/python -m pytest -n 3 --dist loadscope --no-loadscope-reorder --durations=25 \
	  --junitxml=build/test-results.xml test

# The same suite with one core kept busy (a busy loop at nice 10), for anyone changing a
# test that depends on timing: it must pass here too, and count no rerun.
test-loaded: $(STAMP)
	nice -n 10 $(BIN)/python -c 'while True: pass' & busy=$$!; \
	$(BIN)/python -m pytest -n 3 --dist loadscope --no-loadscope-reorder test; rc=$$?; \
	  kill $$busy; exit $$rc

test-ubuntu2404: export AMENT_PREFIX_PATH := $(abspath $(UBUNTU_VENV))
test-ubuntu2404: export PATH := $(UBUNTU_BIN):$(SYSTEM_PATH)
test-ubuntu2404: $(UBUNTU_STAMP)
	$(UBUNTU_BIN)/python -m pytest -n 2 --dist loadscope $(UBUNTU_TESTS)

# The fuzz harness alone, with SCALE (default 10) times the examples `make test` runs.
fuzz: $(STAMP)
	UAV_VS_FUZZ_SCALE=$(or $(SCALE),10) $(BIN)/python -m pytest -n 2 test/test_fuzz_nodes.py

bench: $(STAMP)
	$(BIN)/python -m bench

demo: $(STAMP)
	$(BIN)/python -m uav_vs.demo $(if $(BAG),--bag $(BAG)) $(if $(AUTOPILOT),--autopilot $(AUTOPILOT)) $(if $(SITL),--sitl $(SITL)) $(if $(SENSORS),--sensors $(SENSORS)) $(if $(SCENARIO),--scenario $(SCENARIO)) $(if $(HOSTS),--hosts $(HOSTS)) $(if $(VEHICLES),--vehicles $(VEHICLES)) $(if $(CUT_LINK),--cut-link $(CUT_LINK)) $(if $(VIEW),--view)

clean:
	rm -rf $(VENV) $(UBUNTU_VENV) build install log *.egg-info bench-results.jsonl demo-output
