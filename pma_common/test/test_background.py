"""A node spun in a background thread keeps spinning when entities go under its wait."""

from __future__ import annotations

import threading
import time

import pytest
from rclpy.action import ActionClient
from rclpy.node import Node
from std_msgs.msg import Int32

from pma_common.background import BackgroundSpin
from pma_common.service import poll
from pma_interfaces.action import Sweep


@pytest.fixture
def spun(context):
    node = Node('background_probe', context=context)
    spin = BackgroundSpin(node)
    yield spin
    spin.close()
    node.destroy_node()


def test_action_clients_destroyed_under_the_wait_do_not_end_the_spinning(spun):
    """The demo made and destroyed action clients while its node spun in a thread. One
    destroyed while the executor adds it to its wait set makes rclpy raise in the spinning
    thread ("action client pointer is invalid"), and a plain `executor.spin()` died of it:
    under load the demo's second sweep was never sent."""
    node = spun.node
    received = []
    node.create_subscription(Int32, 'count', lambda m: received.append(m.data), 10)
    publisher = node.create_publisher(Int32, 'count', 10)
    for _ in range(300):
        ActionClient(node, Sweep, 'nobody').destroy()
    publisher.publish(Int32(data=7))
    assert poll(lambda: 7 in received, 5.0), 'the node stopped spinning'


def test_call_runs_on_the_spinning_thread_and_passes_back_result_and_error(spun):
    assert spun.call(threading.current_thread) is not threading.current_thread()
    assert spun.call(lambda a, b=0: a + b, 2, b=3) == 5
    with pytest.raises(ZeroDivisionError):
        spun.call(lambda: 1 / 0)


def test_close_stops_the_thread_promptly(context):
    node = Node('background_closed', context=context)
    spin = BackgroundSpin(node)
    started = time.monotonic()
    spin.close()
    assert time.monotonic() - started < 1.0
    assert not spin._thread.is_alive()
    node.destroy_node()
