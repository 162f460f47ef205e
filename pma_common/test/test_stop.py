"""Stop signals set a request and never raise, however many arrive."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from pma_common.stop import STOP_SIGNALS, StopRequest


@pytest.fixture
def request_installed():
    saved = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    yield StopRequest().install()
    for sig, handler in saved.items():
        signal.signal(sig, handler)


@pytest.mark.parametrize('first', STOP_SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_the_first_signal_names_the_request_and_later_ones_are_counted(request_installed,
                                                                      first):
    stop = request_installed
    os.kill(os.getpid(), first)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGINT):
        os.kill(os.getpid(), sig)
    assert stop.wait(1.0)
    assert stop.reason == signal.Signals(first).name
    assert stop.extra_signals == 3
    # When: a program tells a second Ctrl-C from one delivered twice (pma_cli.goals).
    assert stop.requested_at <= stop.last_signal_at < stop.requested_at + 1.0


def test_a_request_from_the_program_is_kept_over_later_signals(request_installed):
    stop = request_installed
    stop.request('finished')
    os.kill(os.getpid(), signal.SIGINT)
    assert stop.reason == 'finished' and stop.extra_signals == 1


def test_an_entry_point_is_protected_while_its_module_imports(tmp_path):
    """A SIGINT during the (slow) import of the target ends it quietly, not in a traceback."""
    (tmp_path / 'slow_target.py').write_text(textwrap.dedent('''
        import os, signal, time
        os.kill(os.getpid(), signal.SIGINT)     # Ctrl-C while "importing rclpy"
        time.sleep(0.2)

        def main():
            from pma_common.stop import stop_request
            return 0 if stop_request().reason == 'SIGINT' else 1
        '''))
    code = 'import sys; from pma_common.stop import entry_point; ' \
        "sys.exit(entry_point('slow_target:main')())"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    done = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                          text=True, timeout=30, check=False)
    assert (done.returncode, done.stderr) == (0, '')


NESTED_SIGNAL_TRIALS = '''
import os, signal, sys
from pma_common.stop import StopRequest

def trial(line):
    """SIGINT, then a SIGTERM at the given line of the SIGINT handler's execution."""
    stop, seen, fired = StopRequest().install(), [0], [False]
    handler = StopRequest._on_signal.__code__

    def at_each_line(frame, event, _arg):
        if event == 'line' and not fired[0]:
            seen[0] += 1
            if seen[0] == line:
                fired[0] = True
                os.kill(os.getpid(), signal.SIGTERM)
        return at_each_line

    def inside_the_handler(frame, _event, _arg):
        traced = frame.f_code is handler or frame.f_back is not None and (
            frame.f_back.f_trace is not None)
        return at_each_line if traced else None

    sys.settrace(inside_the_handler)
    os.kill(os.getpid(), signal.SIGINT)
    sys.settrace(None)
    assert stop.wait(1.0), line
    assert stop.reason in ('SIGINT', 'SIGTERM') and stop.extra_signals <= 1, line
    return fired[0]

line = 1
while trial(line):
    line += 1
print(line - 1)
'''


def test_a_signal_inside_the_handling_of_another_never_hangs():
    """A second signal at every line the first one's handler runs (and whatever it calls).

    Python runs handlers between bytecodes, nested too; a handler that took a lock (as
    threading.Event.set does) deadlocked when the second arrived while the first held it.
    """
    done = subprocess.run([sys.executable, '-c', NESTED_SIGNAL_TRIALS], capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) >= 3, done.stdout     # the handler's lines were all reached
