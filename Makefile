# point_gn_ros: the README's commands. Every target creates .venv on first use.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
SHARED ?= ../shared
MODELNET := $(SHARED)/datasets/modelnet40_1024
STAMP := $(VENV)/.installed

.PHONY: venv demo test lint bench default-bank colcon-build clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt -r requirements-dev.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

# The node with the shipped default bank, fed real held-out ModelNet40 objects.
demo: $(STAMP)
	$(PY) -m point_gn_ros.clients.demo

test: $(STAMP)
	$(PY) -m pytest -q test

lint: $(STAMP)
	$(VENV)/bin/ruff check point_gn_ros test scripts

bench: $(STAMP)
	$(VENV)/bin/point_gn bench

# Rebuild the shipped default bank from ../shared (when the encoder version or the bank format
# changes): yaw-aligned, float16, standardised, PCA width (512 or 640) and discriminant head
# chosen by 5-fold CV on the train split. CACHE=DIR reuses encoded features.
CACHE ?=
default-bank: $(STAMP)
	$(VENV)/bin/point_gn bank build $(MODELNET) --split train --default-bank --yaw-align \
		$(if $(CACHE),--cache $(CACHE)) -o point_gn_ros/data/modelnet40_default.npz

colcon-build: $(STAMP)
	source $(VENV)/bin/activate && colcon build --base-paths . --build-base build \
		--install-base install

clean:
	rm -rf build install log .pytest_cache
