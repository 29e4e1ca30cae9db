# The workspace's commands. Every target sets the workspace up first (idempotent, seconds when
# nothing changed): see scripts/setup.sh.
SHELL := /bin/bash
ARGS ?=
PYTEST_ARGS ?=

.PHONY: help setup run test bench-sim bench-memory lock clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/:.*## /\t/'

setup:  ## create/refresh the venv (cached outside the clone), build with colcon, write env.sh
	@scripts/setup.sh

RUN_ARGS ?= -p total_steps:=20000 -p eval_every:=2500

run: setup  ## the main job: comcact_node's default on InvertedPendulum-v4, 20,000 steps (ARGS="-p name:=value ...")
	@. ./env.sh && ros2 run comper_agent comcact_node --ros-args $(RUN_ARGS) $(ARGS)

test: setup  ## the whole test suite (unit + ROS integration)
	@. ./env.sh && python -m pytest test $(PYTEST_ARGS)

bench-sim: setup  ## lock-step simulation throughput through ROS vs gymnasium direct
	@. ./env.sh && python benchmarks/sim_bench.py $(ARGS)

bench-memory: setup  ## compact-memory throughput, in-process and through ROS
	@. ./env.sh && python benchmarks/memory_core_bench.py $(ARGS) && python benchmarks/memory_ros_bench.py $(ARGS)

lock:  ## re-resolve requirements.in into requirements.lock (needs the registries)
	@scripts/lock.sh

clean:  ## remove build outputs (the cached venv stays)
	rm -rf build install log env.sh .venv .colcon-build.out
