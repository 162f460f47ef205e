"""pma_common.processes on real child processes: their own groups, the stop escalation, the
group's leftovers, and children that follow a parent that died without stopping them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pma_common.processes import Child, start_child, stop_children

pytestmark = pytest.mark.in_process

# A child that reports its pid, starts a grandchild in its group, and ignores what it is told to.
CHILD = textwrap.dedent('''
    import signal, subprocess, sys, time
    for name in sys.argv[1:]:
        signal.signal(getattr(signal, name), signal.SIG_IGN)
    grandchild = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)'])
    print('grandchild', grandchild.pid, flush=True)
    time.sleep(600)
''')


def running(pid: int) -> bool:
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except OSError:
        return False
    return state != 'Z'


def started(tmp_path: Path, *ignored: str) -> tuple[Child, int]:
    log = tmp_path / 'child.log'
    child = start_child('child', [sys.executable, '-c', CHILD, *ignored], log_path=log)
    deadline = time.monotonic() + 20
    while 'grandchild' not in log.read_text():
        assert time.monotonic() < deadline and child.running(), log.read_text()
        time.sleep(0.02)
    return child, int(log.read_text().split()[1])


def test_a_child_runs_in_a_group_of_its_own_and_a_sigint_ends_it_with_its_group(tmp_path):
    child, grandchild = started(tmp_path)
    assert os.getpgid(child.pid) == child.pid != os.getpgid(0)
    told = []
    stop_children([child], escalating=lambda still, sig: told.append(sig))
    assert child.popen.returncode == -signal.SIGINT and told == []
    assert not running(grandchild)


def test_a_child_that_ignores_sigint_and_sigterm_is_killed_after_the_deadlines(tmp_path):
    child, grandchild = started(tmp_path, 'SIGINT', 'SIGTERM')
    told = []
    began = time.monotonic()
    stop_children([child], ((signal.SIGINT, 0.3), (signal.SIGTERM, 0.3), (signal.SIGKILL, 5)),
                  escalating=lambda still, sig: told.append((still[0].name, sig)))
    assert child.popen.returncode == -signal.SIGKILL
    assert told == [('child', signal.SIGTERM), ('child', signal.SIGKILL)]
    assert 0.6 <= time.monotonic() - began < 5
    assert not running(grandchild)


def test_what_outlives_its_leader_is_killed_with_the_group(tmp_path):
    child, grandchild = started(tmp_path)
    os.kill(child.pid, signal.SIGKILL)            # only the leader: the grandchild stays
    child.popen.wait(5)
    assert running(grandchild)
    child.kill_leftovers()
    deadline = time.monotonic() + 5
    while running(grandchild) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not running(grandchild)


def test_a_child_started_to_die_with_its_parent_gets_sigterm_when_the_parent_is_killed(
        tmp_path):
    """The demo and `pma up` start their nodes so: a parent SIGKILLed leaves nothing behind."""
    log = tmp_path / 'orphan.log'
    parent = subprocess.Popen([sys.executable, '-c', textwrap.dedent(f'''
        import sys, time
        from pma_common.processes import start_child
        child = start_child('orphan', [sys.executable, '-c', 'import time; time.sleep(600)'],
                            log_path=__import__('pathlib').Path({str(log)!r}),
                            die_with_parent=True)
        print(child.pid, flush=True)
        time.sleep(600)
    ''')], stdout=subprocess.PIPE, text=True)
    orphan = int(parent.stdout.readline())
    assert running(orphan)
    parent.kill()
    parent.wait(5)
    deadline = time.monotonic() + 5
    while running(orphan) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not running(orphan), 'the child outlived its parent'
