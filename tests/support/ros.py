"""An rclpy node inside the test process, spun in a background thread.

The nodes under test always run as separate processes; this node is the test's
own probe on the same DDS domain (subscriber, client, parameter caller).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.node import Node

from pma_common.background import BackgroundSpin
from pma_common.service import ask, poll

# Fast DDS's server waits only 100 ms for a new client's reply reader to match before it
# drops the reply (ros2/rmw_fastrtps#467); wait_for_service sees only the client's side of
# the match. A command is sent once, so a new client gives the server's side this long.
NEW_CLIENT_SETTLE_S = 0.5


def wait_for_action_server(client, timeout: float = 20.0) -> None:
    """`client.wait_for_server`, then NEW_CLIENT_SETTLE_S. SpinningNode.send_goal makes sure
    the goal's answers come back, but feedback is a topic: the server's feedback writer may
    not have matched a new client's reader yet, and what it publishes before is not heard."""
    assert client.wait_for_server(timeout_sec=timeout), f'no action server ({timeout:g} s)'
    time.sleep(NEW_CLIENT_SETTLE_S)


class SpinningNode:
    def __init__(self, name: str):
        if not rclpy.ok():
            rclpy.init()
        self.node = Node(name)
        # Spinning on through entities a test destroys under the wait, and action requests
        # made from the executor's thread (in_executor): pma_common.background.
        self._spin = BackgroundSpin(self.node)
        self.in_executor = self._spin.call
        self._clients: dict[str, object] = {}

    def send_goal(self, client, goal, *, timeout: float = 10.0, feedback_callback=None):
        """The handle of `goal`, sent as the product's tools send one (BackgroundSpin)."""
        return self._spin.send_goal(client, goal, timeout, feedback_callback=feedback_callback)

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

    def close(self) -> None:
        self._clients.clear()   # destroy_node destroys them
        self._spin.close()
        self.node.destroy_node()


def wait_until(predicate: Callable[[], bool], timeout: float, what: str,
               period: float = 0.02) -> None:
    """Poll a condition (discovery, message arrival) instead of sleeping a fixed time."""
    if not poll(predicate, timeout, period):
        raise TimeoutError(f'timed out after {timeout} s waiting for {what}')


def publish_until(publisher, message, done: Callable[[], bool], timeout: float, what: str, *,
                  period: float = 0.3) -> None:
    """Publish `message` every `period` until `done()`, as `pma set` does: the driver takes
    pma/pressure_setpoint best-effort, so one message may be lost (a new publisher's first,
    before the driver's reader has matched it)."""
    wait_until(lambda: done() or publisher.publish(message) or False, timeout, what, period)


def shutdown() -> None:
    if rclpy.ok():
        rclpy.shutdown()
