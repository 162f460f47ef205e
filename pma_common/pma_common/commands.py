"""How to spell a command in a hint printed to the user, on the path they are on.

A full ROS 2 install has the `ros2` command line; the wheel-based setup (`make setup` without
/opt/ros/jazzy, tools/env.sh's PMA_ROS_MODE=wheels) has not, and `pma run PKG EXE` runs the
same executable there (docs/cli.md). Every hint that names a `ros2 run` command goes through
`run_command`, so a user on the wheels path is never told to type a command they do not have.

`installed_executable` is where `ros2 run` finds an executable: the one answer for the demo,
`pma run`, `pma up` and the tests. Only ament_index_python here, no ROS graph.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


class ExecutableNotFoundError(LookupError):
    """No such package or executable in the sourced workspace; the message says what there is."""


def installed_executable(package: str, executable: str) -> Path:
    """Where `ros2 run package executable` finds it: PREFIX/lib/PACKAGE/EXECUTABLE of the
    package's install prefix (ament index)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        prefix = Path(get_package_prefix(package))
    except PackageNotFoundError:
        raise ExecutableNotFoundError(f'no package {package} (is the workspace sourced: '
                                 '. tools/env.sh? built: make setup?)') from None
    path = prefix / 'lib' / package / executable
    if not os.access(path, os.X_OK):
        found = sorted(p.name for p in (prefix / 'lib' / package).glob('*')
                       if os.access(p, os.X_OK))
        raise ExecutableNotFoundError(f'{package} has no executable {executable} (it has: '
                                 f'{", ".join(found) or "none"})')
    return path


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
