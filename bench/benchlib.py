"""What the process benchmarks share: their own ROS graph, child processes, CPU time, report.

Not a benchmark itself (run_all.py runs bench_*.py only); the scripts import it from their
own directory, which Python puts first on sys.path.
"""

from __future__ import annotations

import os
import random
import select
import signal
import subprocess
from pathlib import Path

CLK_TCK = os.sysconf('SC_CLK_TCK')

Row = tuple[str, str, str]      # measure, value, target (or context)


def isolate_ros_graph() -> None:
    """A domain of its own, localhost only, so a bench neither sees nor disturbs other runs."""
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.SystemRandom().randint(120, 200)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


def stop(proc: subprocess.Popen) -> None:
    """SIGINT (what Ctrl-C sends: ROS nodes shut down cleanly), SIGKILL after 10 s."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Processes:
    """The processes a benchmark starts: stdout piped, stderr in WORK/NAME.log, each in its
    own session (a Ctrl-C at the terminal reaches the benchmark only); close() stops them."""

    def __init__(self, work: Path):
        self.work = work
        self._procs: list[subprocess.Popen] = []
        self._logs = []

    def start(self, argv: list[str], name: str) -> subprocess.Popen:
        log = open(self.work / f'{name}.log', 'w')  # closed in close()
        self._logs.append(log)
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=log, text=True,
                                start_new_session=True)
        self._procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in reversed(self._procs):
            stop(proc)
        for log in self._logs:
            log.close()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process, from /proc (no psutil needed)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def read_line(proc: subprocess.Popen, timeout: float, what: str) -> str:
    """The child's next stdout line, or TimeoutError naming what was awaited."""
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    line = proc.stdout.readline().strip() if ready else ''
    if not line:
        raise TimeoutError(f'{what}: nothing within {timeout:.0f} s (exit {proc.poll()})')
    return line


def serve(node) -> None:
    """A helper process's main: say 'ready', spin until Ctrl-C or SIGTERM, clean up."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    print('ready', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    node.destroy_node()
    rclpy.try_shutdown()


def check(ok: bool, target: str) -> str:
    return target if ok else f'MISSED ({target})'


def load_row() -> Row:
    """The machine's load, so a reader can tell a noisy run from a slow program."""
    return ('machine load average (1 min, all cores)', f'{os.getloadavg()[0]:.1f}',
            f'({os.cpu_count()} cores)')


def print_table(rows: list[Row]) -> None:
    width = max(len(r[0]) for r in rows)
    print(f'{"measure":<{width}}  {"value":>8}  target')
    for name, value, target in rows:
        print(f'{name:<{width}}  {value:>8}  {target}')
