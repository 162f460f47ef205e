"""`pma watch`'s rate limit and exit code, and `pma` with a closed pipe; no ROS graph."""

import io
import os
import random
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest

from pma_cli.observe import RateLimit, Watch
from pma_cli.session import INTERRUPTED, NO_ANSWER, CliError, Interrupted, Session
from pma_common import names
from pma_interfaces.msg import PmaState


def shown(limit: RateLimit, stamps) -> int:
    return sum(limit.take(t) for t in stamps)


@pytest.mark.parametrize('rate_hz', [20.0, 5.0, 100.0])
def test_a_stream_at_the_limit_shows_every_sample_despite_jitter(rate_hz):
    # Nanosecond rounding: the repro saw every other sample of a 20 Hz stream at 20 Hz.
    period = 1.0 / rate_hz
    rounded = [k * period - 1e-9 * (k % 2) for k in range(2000)]
    assert shown(RateLimit(rate_hz), rounded) == 2000
    # Jitter of a fifth of a period either way, and a device clock 2 % fast.
    rng = random.Random(5)
    jittered = [k * period / 1.02 + rng.uniform(-0.2, 0.2) * period for k in range(2000)]
    assert shown(RateLimit(rate_hz), sorted(jittered)) == 2000
    slower = [k * period * 1.5 for k in range(200)]
    assert shown(RateLimit(rate_hz), slower) == 200


def test_a_faster_stream_is_thinned_to_about_the_limit():
    stamps = [k * 0.001 for k in range(10_000)]           # 1 kHz for 10 s
    count = shown(RateLimit(20.0), stamps)
    assert 200 <= count <= 20 * 10 * (1 + RateLimit.TOLERANCE) + RateLimit.BURST
    assert shown(RateLimit(0.0), stamps) == 10_000        # 0: no limit


class _Stopped:
    """A session whose first wait is interrupted (Ctrl-C), with a node that subscribes to
    nothing."""

    node = SimpleNamespace(create_subscription=lambda *args: None)

    def spin_until(self, done, timeout_s, interruptible=True):
        raise Interrupted('SIGINT')


def test_ctrl_c_ends_watch_with_the_interrupted_status():
    out = io.StringIO()
    assert Watch(_Stopped(), si=True, max_rate_hz=20.0, out=out).run(0, 10.0) == INTERRUPTED
    assert out.getvalue().startswith('   time_s')         # the header, then nothing


def test_the_root_namespace_is_suggested_as_a_usable_flag():
    session = Session.__new__(Session)                     # no node: only the graph is asked
    session.namespace = '/right'
    session.node = SimpleNamespace(get_topic_names_and_types=lambda: [
        ('/pma/state', ['pma_interfaces/msg/PmaState']),
        ('/left/pma/state', ['pma_interfaces/msg/PmaState'])])
    hint = session.where_hint(names.STATE, 'driver_node')
    assert 'It runs in /, /left: add --namespace /, --namespace left.' in hint


def test_a_reader_that_closes_the_pipe_ends_pma_quietly(tmp_path):
    from test_export import write_bag
    bag = write_bag(tmp_path / 'bag', count=3000)
    read, write = os.pipe()
    os.close(read)                                          # `| head` that has already left
    try:
        result = subprocess.run(
            [sys.executable, '-c', 'import sys; from pma_cli.main import main; '
             'sys.exit(main())', 'export', str(bag), '--csv', '-'],
            stdout=write, stderr=subprocess.PIPE, text=True, timeout=60, check=False)
    finally:
        os.close(write)
    assert result.returncode == 141, result.stderr
    assert result.stderr == ''


class _StopsStreaming:
    """A session that delivers `samples` states, one per wait, and then nothing: the driver
    ended under `pma watch`."""

    node = SimpleNamespace(create_subscription=lambda *args: None)

    def __init__(self, samples: int):
        self.left = samples
        self.watch = None

    def spin_until(self, done, timeout_s, interruptible=True):
        if self.left:
            self.left -= 1
            state = PmaState(seq=100 - self.left)
            state.header.stamp.sec = 100 - self.left
            self.watch._on_state(state)
        else:
            time.sleep(timeout_s)
        return False

    def where_hint(self, topic, what):
        return f'is {what} running?'


def test_a_counted_watch_whose_stream_stops_exits_3():
    """`pma watch --count 10` whose driver ended after 3 samples waited for ever."""
    session = _StopsStreaming(3)
    watch = session.watch = Watch(session, si=True, max_rate_hz=0.0, out=io.StringIO())
    started = time.monotonic()
    with pytest.raises(CliError) as stopped:
        watch.run(10, 0.3)
    assert stopped.value.code == NO_ANSWER
    assert 'pma/state stopped after 3 samples (none for 0.3 s; 3 of 10 lines shown)' \
        in str(stopped.value)
    assert time.monotonic() - started < 2.0


def test_an_endless_watch_says_the_stream_stopped_and_goes_on():
    session = _StopsStreaming(2)
    watch = session.watch = Watch(session, si=True, max_rate_hz=0.0, out=io.StringIO())
    said = io.StringIO()
    original, sys.stderr = sys.stderr, said
    try:
        calls = [0]
        spin = session.spin_until

        def until_a_second(done, timeout_s, interruptible=True):
            calls[0] += 1
            if calls[0] > 20:                                  # about a second: Ctrl-C
                raise Interrupted('SIGINT')
            return spin(done, timeout_s, interruptible)

        session.spin_until = until_a_second
        assert watch.run(0, 0.3) == INTERRUPTED
    finally:
        sys.stderr = original
    assert said.getvalue().count('no pma/state for 0.3 s (the driver ended, or is inactive); '
                                 'still watching') == 1, said.getvalue()
