"""`pma up`: the launch file's nodes as real processes, up, watched and stopped in order.

`pma up` is started as a user's shell starts a foreground command: its own process group,
default signal dispositions (support.procs), and signalled the way a terminal would (Ctrl-C,
SIGTERM, a node killed under it). Its nodes run in sessions of their own; every one of them
is looked up by the pid `pma up` printed, and must be gone after the stop.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import pytest

from support.procs import INSTALL, kill_group, kill_own_group, popen_in_own_group, running

pytestmark = pytest.mark.integration

PMA = INSTALL / 'pma_cli' / 'lib' / 'pma_cli' / 'pma'
READY_S = 30.0
STOPPED_S = 30.0
PID_LINE = re.compile(r'^\s+(\w+)\s+pid (\d+)\s+log (\S+)$', re.MULTILINE)


class Up:
    """One `pma up --simulated` on a pty link under tmp_path."""

    def __init__(self, procs, tmp_path: Path, *flags: str):
        self.port = tmp_path / 'pma0'
        self.proc = procs.start([PMA, 'up', '--simulated', '--port', self.port,
                                 '--runs-dir', tmp_path / 'runs', *flags], name='pma_up')
        self.pids: dict[str, int] = {}
        self.logs: dict[str, Path] = {}

    def wait_ready(self) -> None:
        self.proc.wait_for_line('pma up: ready', READY_S)
        for name, pid, log in PID_LINE.findall(self.proc.output):
            self.pids[name] = int(pid)
            self.logs[name] = Path(log)

    def wait_exit(self) -> int:
        try:
            return self.proc.popen.wait(STOPPED_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f'pma up still runs {STOPPED_S:g} s later:\n{self.proc.output}')

    def assert_nothing_left(self) -> None:
        assert self.pids, 'pma up printed no process'
        left = {name: pid for name, pid in self.pids.items() if running(pid)}
        assert not left, f'still running: {left}\n{self.proc.output}'
        for pid in self.pids.values():        # each led a group of its own: empty now
            with pytest.raises(ProcessLookupError):
                os.killpg(pid, 0)
        assert not os.path.lexists(self.port), 'the simulated device left its pty link'

    def cleanup(self) -> None:
        """A failed test's leftovers (the procs fixture stops `pma up` itself)."""
        for pid in self.pids.values():
            if running(pid):
                kill_group(pid)


@pytest.fixture
def up(procs, tmp_path):
    made = []

    def start(*flags: str) -> Up:
        made.append(Up(procs, tmp_path, *flags))
        return made[-1]
    yield start
    for each in made:
        each.cleanup()


def stop_lines(output: str) -> list[str]:
    return re.findall(r'stopped (\w+):', output)


def test_ctrl_c_stops_every_process_in_order_and_the_driver_vents(up):
    rig = up()
    rig.wait_ready()
    assert set(rig.pids) == {'fake_arduino', 'driver_node', 'model_node', 'length_controller'}
    # A second process sees the rig: pma status, as a user would run it in another terminal.
    status = subprocess.run([str(PMA), 'status'], capture_output=True, text=True, timeout=30,
                            stdin=subprocess.DEVNULL, check=False)
    assert status.returncode == 0, status.stdout + status.stderr
    assert 'streaming' in status.stdout, status.stdout
    for node in ('driver_node', 'model_node', 'length_controller'):
        assert node in status.stdout, status.stdout

    rig.proc.signal(signal.SIGINT)         # Ctrl-C: the terminal signals the foreground group
    assert rig.wait_exit() == 0, rig.proc.output
    rig.assert_nothing_left()
    # The controller first (it stops commanding), then the driver (it vents through the
    # device), then the rest, the simulated device last.
    assert stop_lines(rig.proc.output) == ['length_controller', 'driver_node', 'model_node',
                                           'fake_arduino'], rig.proc.output
    assert '(vented)' in rig.logs['driver_node'].read_text()
    assert 'every process stopped' in rig.proc.output


def test_sigterm_stops_every_process_and_the_recorder_closes_its_bag(up, tmp_path):
    bag = tmp_path / 'bag'
    rig = up('--record', str(bag), '--no-control')
    rig.wait_ready()
    assert set(rig.pids) == {'fake_arduino', 'driver_node', 'model_node', 'recorder'}
    rig.proc.signal(signal.SIGTERM)
    assert rig.wait_exit() == 0, rig.proc.output
    rig.assert_nothing_left()
    assert stop_lines(rig.proc.output)[0] == 'driver_node'
    assert stop_lines(rig.proc.output)[-1] == 'fake_arduino'
    assert '(vented)' in rig.logs['driver_node'].read_text()
    assert (bag / 'metadata.yaml').is_file(), sorted(p.name for p in bag.iterdir())


def test_a_node_that_dies_is_reported_and_the_rest_are_stopped(up):
    rig = up()
    rig.wait_ready()
    os.killpg(rig.pids['model_node'], signal.SIGKILL)
    assert rig.wait_exit() == 1, rig.proc.output
    out = rig.proc.output
    assert re.search(r'model_node \(pid \d+\) was killed by SIGKILL while up; its log', out), out
    assert f'its log ({rig.logs["model_node"]}) ends:' in out, out
    rig.assert_nothing_left()
    assert stop_lines(out) == ['length_controller', 'driver_node', 'fake_arduino'], out
    assert 'model_node had ended already' in out
    assert '(vented)' in rig.logs['driver_node'].read_text()


def test_a_rig_that_does_not_come_up_names_what_is_missing(procs, tmp_path):
    missing = tmp_path / 'no_such_port'
    proc = procs.start([PMA, 'up', '--port', missing, '--no-control', '--wait', '3s',
                        '--runs-dir', tmp_path / 'runs'], name='pma_up')
    code = proc.popen.wait(STOPPED_S)
    assert code == 1, proc.output
    assert f'driver_node: no pma/state within 3 s (there is no {missing}' in proc.output
    assert "driver_node's log" in proc.output
    pids = [int(pid) for _, pid, _ in PID_LINE.findall(proc.output)]
    assert len(pids) == 2 and not any(running(pid) for pid in pids), proc.output


def test_a_closed_terminal_stops_every_process(tmp_path):
    """SIGHUP, with the output gone (a closed terminal: every write fails), still stops all
    in order and cleanly; up.log in the run directory keeps what could not be printed."""
    port = tmp_path / 'pma0'
    popen = popen_in_own_group([str(PMA), 'up', '--simulated', '--port', str(port),
                                '--runs-dir', str(tmp_path / 'runs')], text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL)
    printed, pids = '', []
    try:
        for line in popen.stdout:
            printed += line
            if 'pma up: ready' in line:
                break
        pids = [int(pid) for _, pid, _ in PID_LINE.findall(printed)]
        assert len(pids) == 4, printed
        popen.stdout.close()
        popen.send_signal(signal.SIGHUP)
        assert popen.wait(STOPPED_S) == 0
        assert not any(running(pid) for pid in pids) and not os.path.lexists(port)
        [log] = (tmp_path / 'runs').glob('*/up.log')
        assert 'SIGHUP: stopping every process' in log.read_text()
        assert 'every process stopped' in log.read_text()
    finally:
        kill_own_group(popen)
        for pid in pids:
            if running(pid):
                kill_group(pid)
