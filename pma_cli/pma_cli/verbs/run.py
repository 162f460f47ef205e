"""`pma run PACKAGE EXECUTABLE ARGS`: `ros2 run` without the ros2 command line."""

from __future__ import annotations

import argparse
import os
import sys

from pma_cli.session import FAILED, USAGE
from pma_common.commands import ExecutableNotFoundError, installed_executable

NAME = 'run'
HELP = '`ros2 run` without the ros2 CLI: run PACKAGE EXECUTABLE'
DESCRIPTION = ('Start ros2_ws/install/PACKAGE/lib/PACKAGE/EXECUTABLE with ARGS, exactly what '
               '`ros2 run PACKAGE EXECUTABLE ARGS` starts.')
OFFLINE = True
COMMON_FLAGS = False      # every argument after EXECUTABLE is the executable's own


def add_arguments(p) -> None:
    p.add_argument('package')
    p.add_argument('executable')
    p.add_argument('args', nargs=argparse.REMAINDER)


def run(args) -> int:
    """exec the installed executable, as `ros2 run` does (same process: signals go to it)."""
    try:
        path = installed_executable(args.package, args.executable)
    except ExecutableNotFoundError as error:
        print(f'pma run: {error}', file=sys.stderr)
        return USAGE
    sys.stdout.flush()
    os.execv(path, [str(path), *args.args])
    return FAILED    # not reached
