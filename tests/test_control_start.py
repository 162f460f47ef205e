"""A goal sent while the length controller starts (the user guide's order: start it, then
`pma move` at once) is followed once the first pma/state sample comes, not aborted because
none had come yet; with no driver at all the goal is aborted with the reason after
FIRST_SAMPLE_WAIT_S. Real processes over DDS, as `ros2 run` starts them."""

from __future__ import annotations

import subprocess
import time

import pytest

from pma_control.length_controller import FIRST_SAMPLE_WAIT_S
from support.procs import INSTALL

pytestmark = pytest.mark.integration

PMA = INSTALL / 'pma_cli' / 'lib' / 'pma_cli' / 'pma'


def pma(*args: str, namespace: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([str(PMA), *args, '--namespace', namespace], capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL, check=False)


def test_a_goal_sent_while_the_controller_starts_is_followed(procs, tmp_path):
    port = tmp_path / 'pma'
    procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port), '--seed', '7'
                   ).wait_for_line('device at', 20)
    driver = procs.ros2_run('pma_driver', 'driver_node',
                            ros_args=['-r', '__ns:=/start', '-p', f'port:={port}'])
    driver.wait_for_line('active: publishing', 30)
    procs.ros2_run('pma_control', 'length_controller', ros_args=['-r', '__ns:=/start'])
    try:
        # Not waiting for `ready`: pma waits for the action server, which comes before the
        # controller has heard the driver.
        result = pma('move', '27.5cm', '--goal-timeout', '20s', namespace='start')
        assert result.returncode == 0, f'{result.stdout}\n{result.stderr}'
        assert 'move succeeded' in result.stdout
    finally:
        pma('vent', '--wait', namespace='start')


def test_a_goal_with_no_driver_is_aborted_with_the_reason_after_the_first_sample_wait(procs):
    procs.ros2_run('pma_control', 'length_controller', ros_args=['-r', '__ns:=/nodriver']
                   ).wait_for_line('length_controller ready', 30)
    began = time.monotonic()
    result = pma('move', '27cm', namespace='nodriver')
    took = time.monotonic() - began
    assert result.returncode == 1, f'{result.stdout}\n{result.stderr}'
    said = result.stdout + result.stderr
    assert 'move aborted: no usable pma/state sample' in said and 'latest: none yet' in said
    assert FIRST_SAMPLE_WAIT_S <= took < FIRST_SAMPLE_WAIT_S + 10, took
