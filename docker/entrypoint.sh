#!/bin/bash
# Container entrypoint: source ROS 2 and the PMA workspace, then run the command as PID 1
# (exec), so `docker stop` signals the node itself and it can vent the muscle or close its bag.
set -e
# shellcheck disable=SC1090,SC1091
source "/opt/ros/${ROS_DISTRO:-jazzy}/setup.bash"
# shellcheck disable=SC1091
source /ws/install/setup.bash
exec "$@"
