"""A test that waits for Ctrl-C with two stubborn processes in `procs` (not collected by
itself: tests/test_signals.py runs it in a pytest of its own and stops that pytest as a
second Ctrl-C at `make test` would, in the middle of the teardown)."""

import os
import sys
import time
from pathlib import Path

# Shrugs off SIGINT and SIGTERM, so Proc.stop waits on it until SIGKILL.
STUBBORN = ('import signal, time\n'
            'for stop in (signal.SIGINT, signal.SIGTERM):\n'
            '    signal.signal(stop, signal.SIG_IGN)\n'
            'print("ready", flush=True)\n'
            'time.sleep(600)\n')


def test_waits_for_ctrl_c(procs):
    pids = []
    for name in ('first', 'second'):
        proc = procs.start([sys.executable, '-c', STUBBORN], name=name)
        proc.wait_for_line('ready', 20)
        pids.append(proc.popen.pid)
    Path(os.environ['PMA_PIDS_FILE']).write_text(' '.join(map(str, pids)))
    time.sleep(600)
