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
colcon test --base-paths . --packages-select inseggan_ros --return-code-on-test-failure \
  --event-handlers console_direct+ --pytest-args -ra "$@"
rc=$?
colcon test-result --test-result-base build/inseggan_ros --verbose || rc=${rc:-1}
exit $rc
