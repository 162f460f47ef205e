"""A stop signal leaves rclpy's context valid for the cleanup that follows it.

rclpy.init's own handlers shut the context down from another thread as a SIGINT arrives;
a cleanup still using it (the demo's executor spinning in a thread) then crashed now and
then. Each case runs in a process of its own: signals and rclpy's default context are
per process.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

CASES = {
    'ros_context': '''
        from pma_common.node import ros_context
        with ros_context([]) as stop:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.3)
            print(stop.is_set(), rclpy.ok())
        ''',
    # The demo's way: its own handler raises KeyboardInterrupt to leave whatever it waits on.
    'own handler': '''
        from pma_common.node import init_without_signal_handlers
        def on_signal(*_):
            raise KeyboardInterrupt
        signal.signal(signal.SIGINT, on_signal)
        init_without_signal_handlers()
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.3)
        except KeyboardInterrupt:
            time.sleep(0.3)       # what rclpy's handler thread would have done by now
            print(True, rclpy.ok())
        rclpy.shutdown()
        ''',
}


@pytest.mark.parametrize('case', CASES)
def test_the_context_survives_a_sigint(case):
    code = 'import os, signal, time\nimport rclpy\n' + textwrap.dedent(CASES[case])
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=30, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ['True', 'True'], done.stderr
