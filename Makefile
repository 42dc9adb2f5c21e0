# kf_train developer entry points (GNU make).
#
#   make setup   create/refresh $(VENV) with ROS 2 Jazzy wheels + dev tools,
#                install kf_train editable (console scripts in $(VENV)/bin)
#   make test    full pytest suite, DDS traffic kept on localhost
#   make lint    only the ament_flake8 / ament_pep257 tests
#   make colcon  colcon build in a throwaway workspace ($(COLCON_WS))
#   make demo / bench / clean / distclean

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test

VENV ?= .venv
PY = $(VENV)/bin/python
PIP = $(PY) -m pip
PYTHON3 ?= python3
# Inside the clone (build/ is ignored by git and the linters), so parallel clones
# never share a workspace.
COLCON_WS ?= $(REPO_ROOT)/build/colcon_ws
PYTEST_ARGS ?=

REPO_ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))

.PHONY: setup venv demo test lint colcon bench clean distclean

$(VENV)/.stamp: requirements-ros.txt requirements-dev.txt setup.py package.xml
	@test -x $(PY) || { echo "creating $(VENV)"; $(PYTHON3) -m venv $(VENV); }
	@# keep linters and colcon out of the venv (both crawl the repo)
	@touch $(VENV)/AMENT_IGNORE $(VENV)/COLCON_IGNORE
	$(PIP) install -q --disable-pip-version-check -r requirements-dev.txt
	$(PIP) install -q --disable-pip-version-check -e .
	@test -x $(VENV)/bin/kf-train || { echo "console scripts missing from $(VENV)/bin" >&2; exit 1; }
	@touch $@

setup venv: $(VENV)/.stamp

demo: setup
	$(VENV)/bin/kf-train demo

# ROS_DOMAIN_ID must stay in 0..101 (Fast DDS port math); 1..100 here. Tests
# may override it per test.
test: colcon
	export COLCON_WS=$(COLCON_WS); \
	export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; \
	export ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-$$(( $$$$ % 100 + 1 ))}; \
	echo "ROS_DOMAIN_ID=$$ROS_DOMAIN_ID"; \
	$(PY) -m pytest test -q -p no:cacheprovider $(PYTEST_ARGS)

lint: setup
	$(PY) -m pytest test -q -p no:cacheprovider -m linter $(PYTEST_ARGS)

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

clean:
	rm -rf build/ install/ log/ *.egg-info

distclean: clean
	rm -rf $(VENV)
