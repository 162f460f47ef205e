"""An rclpy node inside the test process, spun in a background thread.

The nodes under test always run as separate processes; this node is the test's
own probe on the same DDS domain (subscriber, client, parameter caller).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import rclpy
from rclpy._rclpy_pybind11 import InvalidHandle, RCLError
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from pma_common.service import ask, poll

# Fast DDS's server waits only 100 ms for a new client's reply reader to match before it
# drops the reply (ros2/rmw_fastrtps#467); wait_for_service sees only the client's side of
# the match. A command is sent once, so a new client gives the server's side this long.
NEW_CLIENT_SETTLE_S = 0.5


class SpinningNode:
    def __init__(self, name: str):
        if not rclpy.ok():
            rclpy.init()
        self.node = Node(name)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._clients: dict[str, object] = {}
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until closed, surviving entities destroyed under the executor.

        A test that destroys a subscription or client while the executor is waiting on it
        makes rclpy raise InvalidHandle in this thread (an action client: RCLError "action
        client pointer is invalid"); plain `executor.spin()` would die of it and every later
        test in the module would time out waiting for messages. The destroyed entity is out
        of the next wait set, so spinning on is safe.
        """
        while not self._stopping.is_set() and rclpy.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except InvalidHandle:
                continue
            except RCLError as error:
                if 'pointer is invalid' not in str(error):
                    raise
                continue
            except ExternalShutdownException:
                return

    def collect(self, msg_type, topic: str, qos=10):
        """(list that every message on `topic` is appended to, the subscription)."""
        received = []
        lock = threading.Lock()

        def on_msg(msg):
            with lock:
                received.append(msg)

        return received, self.node.create_subscription(msg_type, topic, on_msg, qos)

    def call(self, srv_type, name: str, request=None, *, timeout: float = 20.0,
             idempotent: bool = False):
        """Call a service and wait for its answer; clients are kept per name.

        An idempotent request (a query) is resent while unanswered, as the product's tools
        do (pma_common.service: Fast DDS can drop the first reply to a new client); a
        command is sent once, since sending it twice would change what the test measures,
        and a new client first lets discovery settle (NEW_CLIENT_SETTLE_S).
        """
        client = self._clients.get(name)
        new_client = client is None
        if new_client:
            client = self._clients[name] = self.node.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f'{name} not available'
        request = srv_type.Request() if request is None else request
        if idempotent:
            response = ask(client, request, timeout, poll)
            if response is None:
                raise TimeoutError(f'no answer from {name} within {timeout} s')
            return response
        if new_client:
            time.sleep(NEW_CLIENT_SETTLE_S)
        future = client.call_async(request)
        wait_until(future.done, timeout, f'{name} answer')
        return future.result()

    def in_executor(self, function, *args, timeout: float = 10.0, **kwargs):
        """`function(*args, **kwargs)` run on the spinning thread; what it returns.

        For rclpy's ActionClient requests (send_goal_async, cancel_goal_async,
        get_result_async): they register the request only after sending it, with no lock
        against the executor, so an answer the spinning thread takes in between is dropped
        ('Ignoring unexpected goal response') and the future never completes (seen in CI:
        test_pipeline's sweep, goal never accepted). From the executor's own thread there is
        no in between.
        """
        done, outcome = threading.Event(), {}

        def run():
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

    def close(self) -> None:
        self._clients.clear()   # destroy_node destroys them
        self._stopping.set()
        self._thread.join(2)
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()


def wait_until(predicate: Callable[[], bool], timeout: float, what: str,
               period: float = 0.02) -> None:
    """Poll a condition (discovery, message arrival) instead of sleeping a fixed time."""
    if not poll(predicate, timeout, period):
        raise TimeoutError(f'timed out after {timeout} s waiting for {what}')


def shutdown() -> None:
    if rclpy.ok():
        rclpy.shutdown()
