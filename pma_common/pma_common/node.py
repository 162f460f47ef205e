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

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import rclpy
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from pma_common.stop import StopRequest, stop_request

SPIN_PERIOD_S = 0.1   # how soon a stop request is seen while nothing else happens


@contextmanager
def ros_context(args: list[str] | None = None) -> Iterator[StopRequest]:
    """rclpy initialised without its signal handlers; shut down on the way out."""
    stop = stop_request()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield stop
    finally:
        rclpy.try_shutdown()
        stop.ignore_further()


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


def run_single_threaded(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """The whole main() of a node that needs nothing else: build, spin, destroy; exit 0."""
    with ros_context(args) as stop:
        node = make_node()
        try:
            spin_until_stopped(SingleThreadedExecutor(), node, stop)
        finally:
            node.destroy_node()
    return 0
