"""The main loop every PMA node shares: spin until asked to stop, then shut down completely.

    def main(args=None) -> int:
        with ros_context(args) as stop:
            node = MyNode()
            try:
                spin_until_stopped(SingleThreadedExecutor(), node, stop)
            finally:
                node.destroy_node()       # runs whole, whatever signals arrive meanwhile
        return 0

rclpy's own signal handlers are not installed (pma_common.stop handles SIGINT, SIGTERM and
SIGHUP), so the context stays valid through the shutdown: logging, a last diagnostics message
and the device commands of the cleanup still work, and rclpy is shut down exactly once.
"""

from __future__ import annotations

import concurrent.futures
import re
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

import rclpy
from rclpy.exceptions import InvalidHandle
from rclpy.executors import (
    ConditionReachedException,
    Executor,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.utilities import remove_ros_args

from pma_common.stop import StopRequest, stop_request

SPIN_PERIOD_S = 0.1   # how soon a stop request is seen while nothing else happens
HANDOVER_CHECK_S = 0.1   # how often a pool-executor waiting for a free worker checks for shutdown


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(the program's own arguments, argv for rclpy.init): only `--ros-args ... [--]`
    sections go to ROS.

    rclpy.utilities.remove_ros_args would also swallow a bare `a:=b` outside them (it takes
    it for a legacy remap rule): a program's `--remap /a:=/b`, or the `port:=...` of a
    `-p port:=...` written without --ros-args. So the split is done here.
    """
    ours, ros, inside = [], argv[:1], False
    for arg in argv[1:]:
        if arg == '--ros-args':
            inside = True
            ros.append(arg)
        elif inside and arg == '--':
            inside = False
        elif inside:
            ros.append(arg)
        else:
            ours.append(arg)
    return ours, ros


def refuse_stray_arguments(argv: list[str]) -> None:
    """End a node that takes only ROS arguments when it is given others: rcl would ignore
    `driver_node -p port:=/dev/pma0` (no --ros-args) without a word, and the node would run
    on its defaults."""
    stray, _ = split_ros_args(argv)
    if stray:
        program = Path(argv[0]).name
        example = ' '.join(stray) if stray[0] in ('-p', '-r') else '-p NAME:=VALUE'
        exit_before_start(program, f'unexpected argument(s) {" ".join(stray)!r}: this node '
                          f'takes only ROS arguments, after --ros-args (`{program} --ros-args '
                          f'{example}`); nothing was started')


@contextmanager
def ros_context(args: list[str] | None = None, *,
                own_arguments: bool = False) -> Iterator[StopRequest]:
    """rclpy initialised without its signal handlers; shut down on the way out.

    Arguments rcl cannot start with (a params file that is missing or not YAML, a malformed
    --ros-args rule) end the process with exit code 2 and rcl's reason on one line, as a bad
    parameter does, not with a traceback from rclpy.init. So do arguments outside --ros-args,
    unless the program parses `own_arguments` itself.
    """
    if not own_arguments:
        refuse_stray_arguments(sys.argv if args is None else args)
    stop = stop_request()
    try:
        init_without_signal_handlers(args)
    except rclpy_implementation.RCLError as error:
        stop.ignore_further()
        _cannot_start(error)
    try:
        yield stop
    finally:
        rclpy.try_shutdown()
        stop.ignore_further()


def init_without_signal_handlers(args: list[str] | None = None) -> None:
    """rclpy.init for a process that handles its own stop signals.

    With its handlers, rclpy shuts the context down from a thread of its own the moment a
    SIGINT or SIGTERM arrives, under a cleanup that still uses it: the demo, stopped by a
    Ctrl-C while its executor spun in another thread, ended in a segfault now and then.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)


def without_ros_args(argv: list[str]) -> list[str]:
    """`argv` (program name first) without its --ros-args part, for a program's own parser;
    ROS arguments rcl cannot parse end the process as in ros_context."""
    try:
        return remove_ros_args(argv)
    except rclpy_implementation.RCLError as error:
        _cannot_start(error)


def _cannot_start(error: Exception) -> NoReturn:
    exit_before_start(Path(sys.argv[0]).name, f'cannot start: {rcl_reason(error)}')


def exit_before_start(program: str, reason: str) -> NoReturn:
    """End a process that could not start: `program: reason` on stderr, exit code 2."""
    print(f'{program}: {reason}', file=sys.stderr, flush=True)
    raise SystemExit(2) from None


def rcl_reason(error: Exception) -> str:
    """rcl's message without its prefix and the C source locations it appends."""
    text = str(error).removeprefix('failed to initialize rcl: ').removeprefix(
        'Failed to parse ROS arguments: ')
    return re.sub(r'(, at [^,]+:\d+)+$', '', text.strip())


def spin_until_stopped(executor: Executor, node: Node | None, stop: StopRequest,
                       until: Callable[[], bool] | None = None) -> None:
    """Spin `node` on `executor` until a stop signal, `until()` or an external shutdown."""
    if node is not None:
        executor.add_node(node)
    try:
        while not stop.is_set() and executor.context.ok():
            if until is not None and until():
                return
            executor.spin_once(timeout_sec=SPIN_PERIOD_S)
    except ExternalShutdownException:
        return


def take_queued(subscription: Subscription, limit: int) -> Iterator[tuple[object, dict]]:
    """(message, info) of up to `limit` messages already queued on `subscription`, taken as
    its executor takes them, in order; ends early when the queue is empty or it is destroyed.

    rclpy's executor takes one message per wait and rebuilds its wait set for each (tens
    of microseconds in Python per entity of the node); a 1 kHz callback that takes what is
    queued behind its message catches up on a backlog at the cost of the callbacks alone.
    """
    for _ in range(limit):
        try:
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type,
                                                         subscription.raw)
        except InvalidHandle:
            return
        if taken is None:
            return
        yield taken


def run_single_threaded(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """The whole main() of a node that needs nothing else: build, spin, destroy; exit 0."""
    with ros_context(args) as stop:
        node = make_node()
        try:
            spin_until_stopped(SingleThreadedExecutor(), node, stop)
        finally:
            node.destroy_node()
    return 0


class WorkerPoolExecutor(Executor):
    """Callbacks on a pool of worker threads, for a node whose callbacks may block.

    Use it instead of rclpy's MultiThreadedExecutor. That one (rclpy 7.1, Jazzy) hands a ready
    callback to its pool and looks for work again at once; until a worker has started the
    callback it still counts as pending work, so it is handed out again, without waiting, over
    and over. Under steady traffic the pool's queue fills with copies and the process spins at
    100 % CPU (ros2/rclpy#1452): a driver_node at 50 Hz, starved of the GIL, published samples
    up to 3 s late. Here the spinning thread waits until a worker has taken the callback
    before it looks for more.
    """

    def __init__(self, num_threads: int, *, context=None):
        super().__init__(context=context)
        self._pool = concurrent.futures.ThreadPoolExecutor(
            num_threads, thread_name_prefix='pma-callback')
        self._running: list[tuple[concurrent.futures.Future, object]] = []   # (run, Task)
        self._closed = threading.Event()
        self.handed_out = 0    # callbacks given to a worker (a test sees none handed out twice)

    def spin_once(self, timeout_sec: float | None = None) -> None:
        self._spin_once_impl(timeout_sec)

    def spin_once_until_future_complete(self, future, timeout_sec: float | None = None) -> None:
        future.add_done_callback(lambda _: self.wake())
        self._spin_once_impl(timeout_sec, future.done)

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except (ShutdownException, TimeoutException, ConditionReachedException):
            return
        taken = threading.Event()

        def run() -> None:
            taken.set()
            handler()

        self._running.append((self._pool.submit(run), handler))
        self.handed_out += 1
        # Every worker busy (a long callback each): wait for one, but not past a shutdown.
        while not taken.wait(HANDOVER_CHECK_S) and not self._closed.is_set():
            pass
        finished = [task for run_, task in self._running if run_.done()]
        self._running = [pair for pair in self._running if not pair[0].done()]
        for task in finished:
            task.result()   # a callback's exception ends spin(), as SingleThreadedExecutor's does

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        self._closed.set()
        done = super().shutdown(timeout_sec)
        self._pool.shutdown(wait=False)
        return done
