"""How to spell a command in a hint printed to the user, on the path they are on.

A full ROS 2 install has the `ros2` command line; the wheel-based setup (`make setup` without
/opt/ros/jazzy, tools/env.sh's PMA_ROS_MODE=wheels) has not, and `pma run PKG EXE` runs the
same executable there (docs/cli.md). Every hint that names a `ros2 run` command goes through
`run_command`, so a user on the wheels path is never told to type a command they do not have.

No ROS here.
"""

from __future__ import annotations

import os
import shutil


def has_ros2_cli(environ: dict | None = None) -> bool:
    """Whether `ros2` works here: not on the wheels path (PMA_ROS_MODE=wheels, as tools/env.sh
    sets it), and a `ros2` on PATH."""
    environ = os.environ if environ is None else environ
    if environ.get('PMA_ROS_MODE') == 'wheels':
        return False
    return shutil.which('ros2', path=environ.get('PATH', os.defpath)) is not None


def run_command(package: str, executable: str, *args: object,
                environ: dict | None = None) -> str:
    """`ros2 run PACKAGE EXECUTABLE ARGS` with a ros2 command line, else `pma run ...`."""
    prefix = 'ros2 run' if has_ros2_cli(environ) else 'pma run'
    return ' '.join([prefix, package, executable, *(str(a) for a in args)])
