# Source this file (bash) to get the project's ROS 2 environment:
#   . tools/env.sh
# With ROS 2 Jazzy installed (/opt/ros/jazzy), that install is used; otherwise the
# wheel-based core in .venv/ that `make setup` creates. Then the workspace overlay
# (ros2_ws/install) is sourced when it has been built.
# Safe under `set -u` callers: nounset is switched off while sourcing ROS scripts.

PMA_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export PMA_ROOT
PMA_VENV="${PMA_ROOT}/.venv"
PMA_WS="${PMA_ROOT}/ros2_ws"
PMA_ROS_SETUP="${PMA_ROS_SETUP:-/opt/ros/jazzy/setup.bash}"

__pma_nounset=0
case $- in *u*) __pma_nounset=1; set +u ;; esac

if [ "${PMA_FORCE_WHEELS:-0}" != "1" ] && [ -f "${PMA_ROS_SETUP}" ]; then
    PMA_ROS_MODE=system
    # shellcheck disable=SC1090
    . "${PMA_ROS_SETUP}"
    # Pure-Python extras (mcap, rosbags, pytest plugins) live in a venv that can
    # still see the system's rclpy.
    if [ -x "${PMA_VENV}/bin/python" ]; then
        export VIRTUAL_ENV="${PMA_VENV}"
        export PATH="${PMA_VENV}/bin:${PATH}"
    fi
else
    PMA_ROS_MODE=wheels
    export VIRTUAL_ENV="${PMA_VENV}"
    export PATH="${PMA_VENV}/bin:${PATH}"
    # The venv root is the ament prefix of the wheel-based core.
    export AMENT_PREFIX_PATH="${PMA_VENV}${AMENT_PREFIX_PATH:+:${AMENT_PREFIX_PATH}}"
    export CMAKE_PREFIX_PATH="${PMA_VENV}${CMAKE_PREFIX_PATH:+:${CMAKE_PREFIX_PATH}}"
    # What the wheels' .pth bootstrap would do by re-executing every Python
    # process; doing it once here makes process start deterministic.
    __pma_ld="${PMA_VENV}/lib"
    for __pma_d in "${PMA_VENV}"/lib/python3*/site-packages/ros_*.libs; do
        [ -d "${__pma_d}" ] && __pma_ld="${__pma_ld}:${__pma_d}"
    done
    export LD_LIBRARY_PATH="${__pma_ld}${LD_LIBRARY_PATH:+:${LD_LIBRARY_PATH}}"
    export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
    export ROS_DISTRO=jazzy
    unset __pma_ld __pma_d
fi
export PMA_ROS_MODE
export COLCON_DEFAULTS_FILE="${PMA_WS}/colcon_defaults.yaml"

if [ -f "${PMA_WS}/install/setup.bash" ]; then
    # shellcheck disable=SC1091
    . "${PMA_WS}/install/setup.bash"
fi
# The `pma` command line (pma_cli). colcon installs it where `ros2 run pma_cli pma` looks,
# install/pma_cli/lib/pma_cli, which no setup script puts on PATH; that directory holds `pma`
# alone, so adding it puts nothing else on PATH.
__pma_cli="${PMA_WS}/install/pma_cli/lib/pma_cli"
if [ -x "${__pma_cli}/pma" ]; then
    case ":${PATH}:" in
        *":${__pma_cli}:"*) ;;
        *) export PATH="${__pma_cli}:${PATH}" ;;
    esac
fi
unset __pma_cli

[ "${__pma_nounset}" = 1 ] && set -u
unset __pma_nounset
