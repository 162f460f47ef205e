"""Child processes the way `ros2 launch` treats its nodes: the one supervision helper of the
demo, `pma up` and the tests.

Each child runs in a session (and process group) of its own, out of a terminal's reach, so
that its parent stops the children in an order of its choosing (the driver before the
simulated device, so that the driver can vent). Stopping is SIGINT, then SIGTERM, then
SIGKILL, each with a deadline, to the child's whole group; what is left of a group after its
leader ended is killed while the group is still the child's own. A parent that dies without
stopping its children can have them follow (`die_with_parent`: Linux's PR_SET_PDEATHSIG);
only for a parent that starts its children before it has a second thread, as preexec_fn
requires. No ROS here.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

PR_SET_PDEATHSIG = 1   # linux/prctl.h
# Per child: how long each signal is given before the next (the driver vents on SIGINT).
STOP_STEPS: tuple[tuple[signal.Signals, float], ...] = (
    (signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0))
POLL_S = 0.05


def ended_with(parent_pid: int) -> Callable[[], None] | None:
    """A preexec_fn: the child gets SIGTERM when `parent_pid` ends, however it ends.

    Children in sessions of their own are out of reach of a terminal's Ctrl-C; a parent that
    crashed or was killed left them all running (seen: an hour at 70 % of a core after a
    segfault). SIGTERM is a stop request to each of them (the driver vents). Linux only.
    """
    if not sys.platform.startswith('linux'):
        return None

    def arm() -> None:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:     # it ended before the line above
            os._exit(1)

    return arm


@dataclass
class Child:
    """A started child: its name, its Popen and where its output goes (None: a pipe)."""

    name: str
    popen: subprocess.Popen
    log_path: Path | None = None
    argv: list[str] = field(default_factory=list)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def running(self) -> bool:
        return self.popen.poll() is None

    def signal_group(self, sig: int) -> None:
        """Send `sig` to the child's process group (gone already: nothing to do)."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.popen.pid, sig)

    def kill_leftovers(self) -> None:
        """SIGKILL what is left of the child's group while the group is still its own: its
        leader not yet reaped, or reaped and its pid not taken since. Linux gives no new
        process a pid still in use as a group's ID, so a group whose leader's pid is free
        holds only what the leader started; a taken pid means the group ended and the number
        came round again."""
        if self.popen.poll() is None or not Path(f'/proc/{self.popen.pid}').exists():
            self.signal_group(signal.SIGKILL)


def start_child(name: str, argv: Sequence[str | os.PathLike], *,
                log_path: Path | None = None, env: dict[str, str] | None = None,
                cwd: Path | None = None, die_with_parent: bool = False) -> Child:
    """Start `argv` in a session of its own, its output (stdout and stderr) into `log_path`,
    or into a pipe (`child.popen.stdout`) when None; `env` is added to this environment."""
    argv = [str(a) for a in argv]
    full_env = {**os.environ, 'PYTHONUNBUFFERED': '1', **(env or {})}
    preexec = ended_with(os.getpid()) if die_with_parent else None
    output = (open(log_path, 'w') if log_path is not None
              else contextlib.nullcontext(subprocess.PIPE))
    with output as stdout:
        popen = subprocess.Popen(argv, stdout=stdout, stderr=subprocess.STDOUT,
                                 stdin=subprocess.DEVNULL, start_new_session=True,
                                 preexec_fn=preexec, env=full_env, cwd=cwd)  # noqa: PLW1509
    return Child(name, popen, log_path, argv)


def stop_children(children: Iterable[Child],
                  steps: Sequence[tuple[int, float]] = STOP_STEPS,
                  escalating: Callable[[list[Child], int], None] | None = None) -> None:
    """Stop the children together: each signal of `steps` to every group still running,
    then up to its deadline for them to end; `escalating(still_running, signal)` is told
    before every signal after the first. What is left of each group is killed at the end."""
    children = list(children)
    running = [child for child in children if child.running()]
    for index, (sig, wait_s) in enumerate(steps):
        if not running:
            break
        if index and escalating is not None:
            escalating(running, sig)
        for child in running:
            child.signal_group(sig)
        deadline = time.monotonic() + wait_s
        while running and time.monotonic() < deadline:
            time.sleep(POLL_S)
            running = [child for child in running if child.running()]
    for child in children:
        child.kill_leftovers()
