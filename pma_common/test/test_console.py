"""A plain command whose reader closes the pipe early ends as a shell tool does."""

from __future__ import annotations

import os
import subprocess
import sys

from pma_common.console import CLOSED_PIPE_EXIT

PRINTS_A_LOT = ('import sys\n'
                'from pma_common.console import closed_pipe_ends_quietly\n'
                '@closed_pipe_ends_quietly\n'
                'def main():\n'
                '    for i in range(100000):\n'
                '        print(i)\n'
                '    return 0\n'
                'sys.exit(main())\n')


def run_into_a_closed_pipe(argv: list[str]) -> subprocess.CompletedProcess:
    """`argv | head` once head has left: stdout's reader is gone before the first write."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run(argv, stdout=write, stderr=subprocess.PIPE, text=True,
                              timeout=60, check=False)
    finally:
        os.close(write)


def test_a_closed_pipe_ends_the_command_quietly_with_141():
    result = run_into_a_closed_pipe([sys.executable, '-c', PRINTS_A_LOT])
    assert (result.returncode, result.stderr) == (CLOSED_PIPE_EXIT, '')
    assert CLOSED_PIPE_EXIT == 141
