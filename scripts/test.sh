#!/usr/bin/env bash
# The test command: the whole suite through `colcon test` (pytest under it), then
# `colcon test-result`. Exits non-zero when any test fails. Run after scripts/setup.sh
# (`make test` does both), or in an apt ROS 2 workspace with the package built.
set -uo pipefail
cd "$(dirname "$0")/.."
if [ -z "${ROS_DISTRO:-}" ] && [ -f .venv/bin/activate ]; then
  # shellcheck disable=SC1091
  source .venv/bin/activate  # no apt ROS 2 sourced: use the PyPI one in .venv
fi
set +u  # colcon's setup scripts read unset variables
# shellcheck disable=SC1091
source install/setup.bash
set -u
# DDS traffic stays on this machine, in a domain of this run's own.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( $$ % 90 + 5 ))}
# With pytest-xdist (requirements.txt; TEST_JOBS=1 turns it off) the tests that do not start
# nodes run TEST_JOBS at a time, one test file per process: most of them are small trainings and
# simulations that leave part of the CPU idle. Then the tests marked `serial` (nodes over real
# DDS, whose frame delivery and timing are part of what they check) run alone.
# FAST=1 (`make test-fast`) leaves out the tests marked `slow` (tests/conftest.py): the fast
# tier (under 3 minutes on 2 cores), for every change. Extra arguments go to pytest in both runs.
JOBS=${TEST_JOBS:-2}
if [ "${FAST:-0}" = 1 ]; then NOT_SLOW=" and not slow"; else NOT_SLOW=""; fi
run() {
  colcon test --base-paths . --packages-select inseggan_ros --return-code-on-test-failure \
    --event-handlers console_direct+ --pytest-args -ra "$@"
}
rm -f build/inseggan_ros/pytest*.xml
if [ "$JOBS" -gt 1 ] && python -c "import xdist" 2>/dev/null; then
  # one thread each (OMP_NUM_THREADS, which torch follows): JOBS processes share the cores
  # --no-loadscope-reorder: the files in the order tests/conftest.py collects them (the
  # longest first), not by their number of tests, which starts the loop's few long ones last
  OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} run -m "not serial$NOT_SLOW" -n "$JOBS" --dist loadfile \
    --no-loadscope-reorder "$@"
  rc=$?
  # colcon test writes build/inseggan_ros/pytest.xml each time: keep the first run's beside it
  [ -f build/inseggan_ros/pytest.xml ] && mv build/inseggan_ros/pytest.xml build/inseggan_ros/pytest_parallel.xml
  run -m "serial$NOT_SLOW" "$@" || rc=1
else
  if [ -n "$NOT_SLOW" ]; then run -m "not slow" "$@"; else run "$@"; fi
  rc=$?
fi
colcon test-result --test-result-base build/inseggan_ros --verbose || rc=${rc:-1}
exit $rc
