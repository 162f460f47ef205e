"""Asking a service a question when its answer can be lost in discovery.

A brand-new client's first request can be answered into the void: Fast DDS drops a reply
when the server's reply writer has not matched the client's reply reader yet, and a loaded
machine makes that likely (ros2/rmw_fastrtps#842, open). `wait_for_service` cannot tell,
since it only sees the request side. A *query* (a request without side effects: a model
lookup, a parameter read) is therefore sent again until it is answered. A command is not:
doing it twice is not doing it once, so callers send commands once and report no answer.

SERVICE_QOS is the queue of every service the project serves (and of its action servers'
goal, cancel and result services).
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Mapping

from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

# A service queues a burst instead of dropping it. With rclpy's default (keep last 10),
# of 200 requests in flight from 4 clients model_node answered only 11-41, and of 300 sent
# at once the recorder's, the player's and the driver's services 11-49: the rest were lost
# without an error.
# Keep-last 1000, deep enough for a burst from several clients, rather than keep-all: a
# client that stops reading its responses can never make a reply block the node's executor.
# A client that bursts needs a queue as deep on its side (its request writer and response
# reader): `create_client(..., qos_profile=SERVICE_QOS)`.
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE)

# A query unanswered this long is sent again. The server gives up on an unmatched reply
# reader after 100 ms; a second's wait leaves room for a busy server's queue.
RESEND_QUERY_S = 1.0


def ask(client, request, timeout_s: float,
        wait: Callable[[Callable[[], bool], float], bool],
        resend_s: float = RESEND_QUERY_S):
    """The response to a query, resent every `resend_s` until `timeout_s`; None if none came.

    `wait(done, seconds)` waits (spinning, or polling a node spun elsewhere) until `done()`
    or the time is up, and says which.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        future = client.call_async(request)
        remaining = deadline - time.monotonic()
        if wait(future.done, max(0.0, min(resend_s, remaining))):
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() >= deadline:
            return None


def start_recording_request(bag_path: str, custom_data: Mapping[str, str]):
    """A recorder's StartRecording request under a fresh request_id, so that it may be sent
    again while unanswered (`ask`): the recorder answers a resend for the bag the first
    one opened instead of opening another."""
    from diagnostic_msgs.msg import KeyValue

    from pma_interfaces.srv import StartRecording

    return StartRecording.Request(
        bag_path=bag_path, request_id=uuid.uuid4().hex,
        custom_data=[KeyValue(key=k, value=v) for k, v in custom_data.items()])


def poll(done: Callable[[], bool], seconds: float, period_s: float = 0.02) -> bool:
    """`wait` for a node spun by another thread: poll `done()` for up to `seconds`."""
    deadline = time.monotonic() + seconds
    while not done():
        if time.monotonic() >= deadline:
            return False
        time.sleep(period_s)
    return True
