# kf_train developer entry points (GNU make).
#
#   make setup        create/refresh $(VENV) with ROS 2 Jazzy wheels + dev tools,
#                     install kf_train editable (console scripts in $(VENV)/bin)
#   make test         full pytest suite, DDS traffic kept on localhost
#   make test-core    only test/unit: the tests that need neither ROS nor processes
#   make test-noros   test/unit in $(CORE_VENV), a venv with no ROS wheel at all,
#                     holding a plain `pip install '.[plot,bag]'` (what core users get)
#   make lint         only the ament_flake8 / ament_pep257 tests
#   make jit-cache    compile (once) the rail IMM's numba kernels (kf_train.filters.rail_fast)
#                     and the tuner's (kf_train.filters.rail_likelihood_kernel)
#   make colcon       colcon build in a throwaway workspace ($(COLCON_WS))
#   make ros2cli      install the `ros2` CLI and launch wheels from $(ROS2CLI_WHEELS)
#                     into $(VENV) (when that folder exists, `make test` does it first)
#   make constraints  refresh constraints.txt from a fresh resolve (see docs/testing.md)
#   make soak         both nodes at 1 kHz for $(SOAK_S) s (default 3600): RSS slope,
#                     drops, latency over time, CPU, NaN (benchmarks/soak.py)
#   make demo / bench / clean / distclean
#
# Every install goes through constraints.txt (pip -c): the exact versions of every
# Python dependency, direct and transitive, ROS wheels included. Upgrading one is a
# deliberate commit of a refreshed constraints.txt.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test

VENV ?= .venv
CORE_VENV ?= .venv-core
PY = $(VENV)/bin/python
PIP = $(PY) -m pip
CONSTRAINTS := constraints.txt
PIP_FLAGS := -q --disable-pip-version-check -c $(CONSTRAINTS)
# The optional features the test suite exercises (setup.py extras_require).
EXTRAS := plot,bag,fast,dask,tune,progress,track,jit
# Every extra, for the constraints resolve.
ALL_EXTRAS := plot,bag,fast,dask,tune,progress,track,jit
PYTHON3 ?= python3
# Inside the clone (build/ is ignored by git and the linters), so parallel clones
# never share a workspace.
COLCON_WS ?= $(REPO_ROOT)/build/colcon_ws
PYTEST_ARGS ?=

REPO_ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))

# Wheels of the Jazzy `ros2` CLI and launch (not on the package index), beside the
# clone; see their README. Installed --no-deps (launch_ros asks for a name the index
# does not have); their pure-Python dependencies are in requirements-ros2cli.txt.
ROS2CLI_WHEELS ?= $(abspath $(REPO_ROOT)/../shared/ros2cli-wheels)
ROS2CLI_PACKAGES = rosidl_runtime_py ros2cli ros2action ros2component ros2doctor \
  ros2interface ros2lifecycle ros2multicast ros2node ros2param ros2pkg ros2run ros2service \
  ros2topic launch launch_xml launch_yaml launch_ros ros2launch ament_copyright \
  ros-composition-interfaces
# `make test` installs them first when the folder is there.
TEST_PREREQUISITES = colcon jit-cache $(if $(wildcard $(ROS2CLI_WHEELS)/ros2cli-*.whl),ros2cli)

.PHONY: setup venv demo test test-core test-noros lint colcon ros2cli constraints bench soak \
	jit-cache \
	clean distclean

REQUIREMENTS := requirements-ros.txt requirements-test.txt requirements-dev.txt

$(VENV)/.stamp: $(REQUIREMENTS) $(CONSTRAINTS) setup.py package.xml
	@test -x $(PY) || { echo "creating $(VENV)"; $(PYTHON3) -m venv $(VENV); }
	@# keep linters and colcon out of the venv (both crawl the repo)
	@touch $(VENV)/AMENT_IGNORE $(VENV)/COLCON_IGNORE
	$(PIP) install $(PIP_FLAGS) -r requirements-dev.txt
	$(PIP) install $(PIP_FLAGS) -e '.[$(EXTRAS)]'
	@test -x $(VENV)/bin/kf-train || { echo "console scripts missing from $(VENV)/bin" >&2; exit 1; }
	@touch $@

setup venv: $(VENV)/.stamp

$(VENV)/.ros2cli-stamp: $(VENV)/.stamp requirements-ros2cli.txt $(wildcard $(ROS2CLI_WHEELS)/*.whl)
	@test -d $(ROS2CLI_WHEELS) || { echo "no $(ROS2CLI_WHEELS)" >&2; exit 1; }
	$(PIP) install $(PIP_FLAGS) -r requirements-ros2cli.txt
	$(PIP) install $(PIP_FLAGS) --no-deps --no-index --find-links $(ROS2CLI_WHEELS) \
	  $(ROS2CLI_PACKAGES)
	@test -x $(VENV)/bin/ros2 || { echo "ros2 missing from $(VENV)/bin" >&2; exit 1; }
	@touch $@

ros2cli: $(VENV)/.ros2cli-stamp

demo: setup
	$(VENV)/bin/kf-train demo

# ROS_DOMAIN_ID must stay in 0..101 (Fast DDS port math); 1..100 here. Tests
# may override it per test.
test: $(TEST_PREREQUISITES)
	export COLCON_WS=$(COLCON_WS); \
	export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; \
	export ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-$$(( $$$$ % 100 + 1 ))}; \
	echo "ROS_DOMAIN_ID=$$ROS_DOMAIN_ID"; \
	$(PY) -m pytest test -q -p no:cacheprovider $(PYTEST_ARGS)

lint: setup
	$(PY) -m pytest test/lint -q -p no:cacheprovider $(PYTEST_ARGS)

# Compile (once) or load the rail IMM's numba kernels, so that no test and no node
# started by one pays the compile (tens of seconds) at its first fix; a no-op without numba.
jit-cache: setup
	$(PY) -c 'import kf_train.filters as f; f.numba_available() and \
	  (f.FastRailModel().warm_up() or f.rail_likelihood_kernel.warm_up())'

test-core: setup jit-cache
	$(PY) -m pytest test/unit -q -p no:cacheprovider $(PYTEST_ARGS)

# A venv without ROS: requirements-test.txt (pure test tools and oracles) and a plain,
# non-editable install of the package. pytest runs from its own script, not
# `python -m`, so the installed kf_train is tested, not the source tree.
$(CORE_VENV)/.stamp: requirements-test.txt $(CONSTRAINTS) setup.py
	@test -x $(CORE_VENV)/bin/python || $(PYTHON3) -m venv $(CORE_VENV)
	@touch $(CORE_VENV)/AMENT_IGNORE $(CORE_VENV)/COLCON_IGNORE
	$(CORE_VENV)/bin/python -m pip install $(PIP_FLAGS) -r requirements-test.txt '.[$(EXTRAS)]'
	@touch $@

test-noros: $(CORE_VENV)/.stamp
	@# the package itself afresh every time: the stamp only tracks its dependencies
	$(CORE_VENV)/bin/python -m pip install $(PIP_FLAGS) --no-deps --force-reinstall .
	@! $(CORE_VENV)/bin/python -c 'import rclpy' 2>/dev/null || \
	  { echo "$(CORE_VENV) has rclpy; it must not" >&2; exit 1; }
	$(CORE_VENV)/bin/pytest test/unit -q -p no:cacheprovider $(PYTEST_ARGS)

# Refresh constraints.txt: resolve requirements-dev.txt and the extras afresh (ignoring
# the current pins) in a throwaway venv and freeze it. Review the diff, run make test,
# commit it on its own.
CONSTRAINTS_VENV := build/constraints-venv
constraints:
	rm -rf $(CONSTRAINTS_VENV)
	$(PYTHON3) -m venv $(CONSTRAINTS_VENV)
	$(CONSTRAINTS_VENV)/bin/python -m pip install -q --disable-pip-version-check \
	  -r requirements-dev.txt -r requirements-ros2cli.txt '.[$(ALL_EXTRAS)]'
	{ echo '# Exact versions of every Python dependency of kf_train, direct and transitive,'; \
	  echo '# ROS 2 Jazzy wheels included. Generated by `make constraints` from a fresh'; \
	  echo '# resolve of requirements-dev.txt, requirements-ros2cli.txt and the extras'; \
	  echo '# [$(ALL_EXTRAS)]: do not edit by hand.'; \
	  $(CONSTRAINTS_VENV)/bin/python -m pip freeze --all --exclude-editable \
	    | grep -viE '^(kf[-_]train|pip|setuptools|wheel)[=@ ]' | LC_ALL=C sort -f; \
	} > $(CONSTRAINTS).new
	mv $(CONSTRAINTS).new $(CONSTRAINTS)
	rm -rf $(CONSTRAINTS_VENV)
	git diff --stat -- $(CONSTRAINTS) || true

# Throwaway workspace outside the repo: src/kf_train -> repo root.
colcon: setup
	mkdir -p $(COLCON_WS)/src
	ln -sfn $(REPO_ROOT) $(COLCON_WS)/src/kf_train
	. $(VENV)/bin/activate && cd $(COLCON_WS) && \
	  colcon list && \
	  colcon build --symlink-install --event-handlers console_cohesion+
	@ls -l $(COLCON_WS)/install/kf_train/lib/kf_train/

bench: setup
	$(PY) benchmarks/bench.py

SOAK_S ?= 3600
soak: setup
	$(PY) benchmarks/soak.py --duration $(SOAK_S)

clean:
	rm -rf build/ install/ log/ *.egg-info

distclean: clean
	rm -rf $(VENV) $(CORE_VENV)
