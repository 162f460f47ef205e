"""A node spun in a thread of its own, for a program whose main thread waits on results.

The demo and the tests' probe work this way: the main thread sends goals and calls
services and polls their futures while a background thread runs the callbacks. rclpy
(Jazzy) is not safe for that pattern in two places (the first lost the demo a sweep under
load, the second lost the tests a goal in CI):
- An entity destroyed by one thread while the other waits on it makes rclpy raise in the
  spinning thread (InvalidHandle; an action client: RCLError "action client pointer is
  invalid", ros2/rclpy#1385), and a plain `executor.spin()` dies of it: nothing is received
  after. The destroyed entity is out of the next wait set, so spinning on is safe.
- An ActionClient registers a goal, result or cancel request only after sending it, with no
  lock against the executor, so an answer the spinning thread takes in between is dropped
  ('Ignoring unexpected goal response') and the future never completes (ros2/rclpy#1123;
  fixed in later rclpy releases, seen in CI with this one). Made from the executor's own
  thread (`call`), the request has no in between.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any

from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

SPIN_PERIOD_S = 0.1   # how soon close() is seen while nothing else happens
RESULT_POLL_S = 0.05  # wait_for_result looks at the server this often


class BackgroundSpin:
    """`node` on a SingleThreadedExecutor spun by a daemon thread until close()."""

    def __init__(self, node: Node):
        self.node = node
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f'spin {node.get_name()}',
                                        daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._closing.is_set() and self.executor.context.ok():
            try:
                self.executor.spin_once(timeout_sec=SPIN_PERIOD_S)
            except rclpy_implementation.InvalidHandle:
                continue
            except rclpy_implementation.RCLError as error:
                if 'pointer is invalid' not in str(error):
                    raise
                continue
            except ExternalShutdownException:
                return

    def call(self, function: Callable[..., Any], *args, timeout: float = 10.0,
             **kwargs) -> Any:
        """`function(*args, **kwargs)` run on the spinning thread; what it returns (or raises).

        For rclpy's ActionClient requests: send_goal_async, get_result_async,
        cancel_goal_async.
        """
        done, outcome = threading.Event(), {}

        def run() -> None:
            try:
                outcome['value'] = function(*args, **kwargs)
            except BaseException as error:   # re-raised in the caller's thread
                outcome['error'] = error
            finally:
                done.set()

        self.executor.create_task(run)
        if not done.wait(timeout):
            raise TimeoutError(f'the executor did not run {function} within {timeout} s')
        if 'error' in outcome:
            raise outcome['error']
        return outcome['value']

    def send_goal(self, client, goal, timeout: float, what: str = 'the goal', *,
                  feedback_callback: Callable[[Any], None] | None = None):
        """`goal`'s handle from `client`'s server (ready), sent again under its goal ID while
        unanswered so it runs once (pma_common.action); TimeoutError if none came in time."""
        from pma_common.action import send_goal
        from pma_common.service import poll

        handle = send_goal(client, goal, timeout, poll, feedback_callback=feedback_callback,
                           call=self.call)
        if handle is None:
            raise TimeoutError(f'timed out after {timeout:g} s waiting for {what} (a cancel '
                               'for the goal was sent, as it may run all the same)')
        return handle

    def wait_for_result(self, client, handle, timeout: float, what: str = 'the result', *,
                        server: str = 'the action server', watch=None):
        """The result response of an accepted goal (`handle`, from send_goal).

        TimeoutError after `timeout` (a cancel for the goal is sent then: it may still run),
        ServerGone if its server left the graph or stopped answering meanwhile (ServerWatch;
        pass the one whose `alive()` the goal's feedback calls, or a fresh one is made).
        """
        from pma_common.action import ServerGone, ServerWatch
        from pma_common.service import poll

        watch = watch or ServerWatch(client, call=self.call)
        watch.alive()                       # the acceptance was just heard
        future = self.call(handle.get_result_async)
        deadline = time.monotonic() + timeout
        while not poll(future.done, RESULT_POLL_S):
            how = watch.poll()
            if how:
                raise ServerGone(f'{server} {how} while waiting for {what} ({watch.detail}): '
                                 'the result is lost')
            if time.monotonic() >= deadline:
                with contextlib.suppress(Exception):
                    self.call(handle.cancel_goal_async)
                raise TimeoutError(f'timed out after {timeout:g} s waiting for {what} (a '
                                   'cancel for the goal was sent, as it may run all the same)')
        return future.result()

    def close(self, timeout: float = 2.0) -> None:
        """Stop spinning; the node may be destroyed after this (the caller's to do)."""
        self._closing.set()
        self._thread.join(timeout)
        self.executor.shutdown(timeout_sec=timeout)
