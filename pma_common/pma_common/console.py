"""Plain commands whose output may go into a pipe that closes early (`info BAG | head`).

Python raises BrokenPipeError at the next write, or at the interpreter's own flush at exit,
and prints a traceback. A shell tool ends quietly instead (its SIGPIPE), so these do too, with
the exit status such a tool has: 128 + SIGPIPE. The recipe is the Python documentation's
(library/signal, "Note on SIGPIPE"): stdout is pointed at /dev/null so the exit's flush cannot
raise again.

No ROS here.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
from collections.abc import Callable

CLOSED_PIPE_EXIT = 128 + signal.SIGPIPE     # 141


def closed_pipe_ends_quietly(main: Callable[..., int]) -> Callable[..., int]:
    """`main`, returning CLOSED_PIPE_EXIT without a traceback when its reader went away."""
    @functools.wraps(main)
    def wrapped(*args, **kwargs) -> int:
        try:
            code = main(*args, **kwargs)
            sys.stdout.flush()          # inside the try: a pipe closed at the end shows here
            return code
        except BrokenPipeError:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return CLOSED_PIPE_EXIT
    return wrapped
