"""Start and stop real processes the way `ros2 run` does.

`ros2 run PKG EXE` executes `install/PKG/lib/PKG/EXE`; tests do exactly that, each
process in its own process group so SIGINT reaches it like a Ctrl-C would.

In its own group, a process does not get the Ctrl-C typed at `make test`: its test ends it.
A second Ctrl-C can cut that teardown short, so every group started here is remembered and
killed when the test process ends (`kill_leftovers`): no node outlives the test run.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pma_common.commands import ExecutableNotFoundError, installed_executable
from pma_common.processes import Child, stop_children

ROOT = Path(__file__).resolve().parents[2]
WORKSPACE = ROOT / 'ros2_ws'
INSTALL = WORKSPACE / 'install'


_GROUPS: dict[int, subprocess.Popen] = {}   # the process groups started here, by leader


def popen_in_own_group(argv: list[str], **kwargs) -> subprocess.Popen:
    """subprocess.Popen in a session of its own (signals reach it only as a test sends
    them), remembered for kill_leftovers."""
    popen = subprocess.Popen(argv, start_new_session=True, **kwargs)
    _GROUPS[popen.pid] = popen
    return popen


def kill_group(pid: int) -> None:
    """SIGKILL the process group `pid` leads (gone already: nothing to do)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)


def kill_own_group(popen: subprocess.Popen) -> None:
    """SIGKILL the group `popen` leads while it is still ours (Child.kill_leftovers)."""
    Child('', popen).kill_leftovers()


@atexit.register
def kill_leftovers() -> None:
    """SIGKILL every group started here that still runs, with SIGINT held off meanwhile: a
    test process ends here after a teardown cut short too."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        while _GROUPS:
            kill_own_group(_GROUPS.popitem()[1])
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def executable(package: str, name: str) -> Path:
    """Path of an installed node executable, as `ros2 run` resolves it."""
    try:
        return installed_executable(package, name)
    except ExecutableNotFoundError as error:
        raise FileNotFoundError(f'{error}: run `make setup` to build the workspace') from None


class Proc:
    """A started process whose combined output is captured line by line."""

    def __init__(self, name: str, popen: subprocess.Popen, log_path: Path):
        self.name = name
        self.popen = popen
        self.log_path = log_path
        self._lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        with open(self.log_path, 'w', encoding='utf-8') as log:
            for raw in iter(self.popen.stdout.readline, b''):
                line = raw.decode('utf-8', errors='replace').rstrip('\n')
                log.write(line + '\n')
                log.flush()
                with self._cond:
                    self._lines.append(line)
                    self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    @property
    def output(self) -> str:
        with self._cond:
            return '\n'.join(self._lines)

    def mark(self) -> int:
        """Where the output is now: `wait_for_line(..., after=mark)` and `lines_since(mark)`
        look only at what came after (a test's own lines, not an earlier test's)."""
        with self._cond:
            return len(self._lines)

    def lines_since(self, mark: int) -> str:
        with self._cond:
            return '\n'.join(self._lines[mark:])

    def wait_for_line(self, predicate: Callable[[str], bool] | str, timeout: float = 20.0,
                      after: int = 0) -> str:
        """Block until an output line after line `after` (a `mark()`) matches (substring or
        predicate); return it."""
        test = (lambda line: predicate in line) if isinstance(predicate, str) else predicate
        deadline = time.monotonic() + timeout
        seen = after
        with self._cond:
            while True:
                for line in self._lines[seen:]:
                    if test(line):
                        return line
                seen = len(self._lines)
                remaining = deadline - time.monotonic()
                exited = self.popen.poll() is not None and not self._reader.is_alive()
                if remaining <= 0 or exited:
                    since = '\n'.join(self._lines[after:])[-4000:]
                    raise TimeoutError(
                        f'{self.name}: no line matching {predicate!r} within {timeout} s '
                        f'(exit code {self.popen.poll()}); output'
                        f'{" since the mark" if after else ""}:\n{since}')
                self._cond.wait(min(remaining, 0.2))

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.killpg(self.popen.pid, sig)

    def abort_with_stacks(self) -> str:
        """End a hung process with SIGABRT, which makes Python print every thread's stack."""
        if self.alive():
            self.popen.send_signal(signal.SIGABRT)
            try:
                self.popen.wait(5)
            except subprocess.TimeoutExpired:
                self.popen.kill()
        self._reader.join(5)
        return self.output

    def stop(self, timeout: float = 5.0) -> int:
        """SIGINT, then SIGTERM, then SIGKILL to the process group; return the exit code."""
        stop_children([Child(self.name, self.popen)],
                      ((signal.SIGINT, timeout), (signal.SIGTERM, timeout), (signal.SIGKILL, 5)))
        _GROUPS.pop(self.popen.pid, None)
        self._reader.join(2)
        return self.popen.returncode


def children_of(pid: int) -> list[int]:
    """Pids of the processes whose parent is `pid` now, from /proc."""
    found = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / 'stat').read_text()
        except OSError:              # it ended meanwhile
            continue
        # pid (comm) state ppid ...: comm may hold spaces and brackets, so after the last ')'.
        if int(stat.rsplit(')', 1)[1].split()[1]) == pid:
            found.append(int(entry.name))
    return found


def running(pid: int) -> bool:
    """True while `pid` exists and is not a zombie."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except OSError:
        return False
    return stat.rsplit(')', 1)[1].split()[0] != 'Z'


class ProcessGroup:
    """Owns every process a test starts; `stop_all` ends them in reverse order."""

    def __init__(self, log_dir: Path):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: list[Proc] = []

    def start(self, argv: list[str | os.PathLike], name: str | None = None,
              env: dict[str, str] | None = None, cwd: Path | None = None) -> Proc:
        argv = [str(a) for a in argv]
        name = name or Path(argv[0]).name
        full_env = dict(os.environ)
        full_env['PYTHONUNBUFFERED'] = '1'
        full_env['PYTHONFAULTHANDLER'] = '1'    # SIGABRT prints every thread's stack (hangs)
        if env:
            full_env.update(env)
        popen = popen_in_own_group(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=full_env, cwd=cwd)
        proc = Proc(name, popen, self.log_dir / f'{len(self.procs):02d}-{name}.log')
        self.procs.append(proc)
        return proc

    def ros2_run(self, package: str, exe: str, *args: str | os.PathLike,
                 ros_args: list[str] | None = None, **kwargs) -> Proc:
        """Like `ros2 run package exe args --ros-args ros_args`."""
        argv = [executable(package, exe), *args]
        if ros_args:
            argv += ['--ros-args', *ros_args]
        return self.start(argv, name=kwargs.pop('name', exe), **kwargs)

    def python(self, script: Path | str, *args: str, **kwargs) -> Proc:
        return self.start([sys.executable, str(script), *args], **kwargs)

    def stop_all(self) -> None:
        """Each process stopped as Ctrl-C would (Proc.stop), the last started first. Cut short
        (a second Ctrl-C at `make test`), the rest are killed at once."""
        try:
            for proc in reversed(self.procs):
                proc.stop()
        except BaseException:
            for proc in self.procs:
                kill_own_group(proc.popen)
            raise
