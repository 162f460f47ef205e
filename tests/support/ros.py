"""An rclpy node inside the test process, spun in a background thread.

The nodes under test always run as separate processes; this node is the test's
own probe on the same DDS domain (subscriber, client, parameter caller).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node


class SpinningNode:
    def __init__(self, name: str):
        if not rclpy.ok():
            rclpy.init()
        self.node = Node(name)
        self.executor = MultiThreadedExecutor(num_threads=2)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        self._thread.join(2)


def wait_until(predicate: Callable[[], bool], timeout: float, what: str,
               period: float = 0.02) -> None:
    """Poll a condition (discovery, message arrival) instead of sleeping a fixed time."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(period)
    raise TimeoutError(f'timed out after {timeout} s waiting for {what}')


def shutdown() -> None:
    if rclpy.ok():
        rclpy.shutdown()
