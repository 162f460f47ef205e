"""Signals that end a process become a request to stop, never an exception mid-cleanup.

rclpy's handlers (and Python's default) turn SIGINT into KeyboardInterrupt wherever the main
thread happens to be. A Ctrl-C under `ros2 launch` delivers two SIGINTs (the terminal's to the
whole process group, then launch's own to each child), and the second one used to land in
`finally:` and cut the driver's vent or the recorder's bag close short. Here SIGINT, SIGTERM
and SIGHUP only set a flag: the main loop sees it and runs its whole shutdown, and signals
that arrive while it does so are noted and otherwise ignored.

The handler takes no lock. Python runs a handler between two bytecodes of the main thread,
even inside another handler: when the handler set a threading.Event, a second signal could
interrupt the first handler while it held the Event's lock, and the second handler then waited
for that lock forever (the likely cause of a recorder that hung under a burst of signals in
CI). A flag and a byte written to a pipe need no lock.

No ROS here: fake_arduino uses it as is, nodes through pma_common.node.
"""

from __future__ import annotations

import importlib
import os
import select
import signal
import time
from collections.abc import Callable

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class StopRequest:
    """Set once by the first stop signal (or by the program itself); later ones are counted.

    `requested_at` and `last_signal_at` (time.monotonic(), None until then) let a waiting
    program tell a second Ctrl-C typed on purpose from two deliveries of one (a terminal's and
    `ros2 launch`'s come within milliseconds): `pma` ends its wait for a cancel's confirmation
    at a later signal (pma_cli.goals).
    """

    def __init__(self) -> None:
        self._requested = False
        self.reason = ''
        self.extra_signals = 0
        self.requested_at: float | None = None
        self.last_signal_at: float | None = None
        # Written once, never read: readable from the request on, for wait()'s select.
        self._readable_once_set, self._wake = os.pipe()
        os.set_blocking(self._wake, False)

    def install(self) -> StopRequest:
        """Route the stop signals here (main thread only; idempotent)."""
        for sig in STOP_SIGNALS:
            signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum: int, _frame) -> None:
        if self._requested:
            self.extra_signals += 1
            self.last_signal_at = time.monotonic()
            return
        self.request(signal.Signals(signum).name)

    def request(self, reason: str) -> None:
        """Ask the main loop to stop (the first reason is kept)."""
        if self._requested:
            return
        self._requested = True    # first: a signal arriving from here on only counts
        self.requested_at = time.monotonic()
        self.reason = reason
        try:
            os.write(self._wake, b'!')
        except BlockingIOError:   # a full pipe is readable already
            pass

    def ignore_further(self) -> None:
        """Ignore stop signals from now on: the shutdown is done and the interpreter exits.

        Python resets its own handlers to the default at exit, and a late SIGINT or SIGHUP
        would then kill a process that already finished cleanly; ignored ones stay ignored.
        """
        ignore_stop_signals()

    def is_set(self) -> bool:
        return self._requested

    def wait(self, timeout: float | None = None) -> bool:
        """True once requested, False if `timeout` seconds pass first."""
        if not self._requested:
            select.select([self._readable_once_set], [], [], timeout)
        return self._requested


def ignore_stop_signals() -> None:
    """SIGINT, SIGTERM and SIGHUP do nothing from now on (main thread only)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


# Signals belong to the process, so there is one request per process.
_REQUEST = StopRequest()


def stop_request() -> StopRequest:
    """The process's stop request, with its signal handlers installed."""
    return _REQUEST.install()


def entry_point(target: str) -> Callable[[], int]:
    """A console_scripts entry that installs the stop handlers before importing its main.

    Importing rclpy, numpy or scipy takes up to a second; a Ctrl-C in that time would otherwise
    end the process with a KeyboardInterrupt traceback. `target` is 'package.module:function'.
    """
    module_name, _, function_name = target.partition(':')

    def run() -> int:
        stop = stop_request()
        try:
            main = getattr(importlib.import_module(module_name), function_name)
            return main()
        finally:
            stop.ignore_further()

    run.__doc__ = f'Run {target} with stop signals turned into a clean-stop request.'
    return run
