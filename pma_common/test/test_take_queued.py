"""take_queued over real DDS: what is queued behind a message comes in order, at most the limit,
in the form the subscription's callback gets (raw bytes or a message), and a destroyed
subscription ends it quietly."""

from __future__ import annotations

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int32

from pma_common.node import take_queued
from pma_common.service import poll

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def queued_node(context, name: str, raw: bool, count: int):
    """A node with a subscription that `count` messages (0, 1, ...) have reached, unspun."""
    node = rclpy.create_node(name, context=context)
    subscription = node.create_subscription(Int32, name, lambda _msg: None, QOS, raw=raw)
    publisher = node.create_publisher(Int32, name, QOS)
    assert poll(lambda: publisher.get_subscription_count() >= 1, 10), 'never matched'
    for value in range(count):
        publisher.publish(Int32(data=value))
    assert publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=10))
    return node, subscription


def test_the_queue_comes_in_order_up_to_the_limit_then_the_rest(context):
    node, subscription = queued_node(context, 'take_queued_messages', raw=False, count=30)
    first = [msg.data for msg, _info in take_queued(subscription, 20)]
    rest = [msg.data for msg, _info in take_queued(subscription, 20)]
    assert first == list(range(20)) and rest == list(range(20, 30))
    assert list(take_queued(subscription, 20)) == []
    node.destroy_node()


def test_a_raw_subscription_gets_bytes_and_the_times_dds_received_them(context):
    node, subscription = queued_node(context, 'take_queued_raw', raw=True, count=3)
    taken = list(take_queued(subscription, 10))
    assert [deserialize_message(data, Int32).data for data, _info in taken] == [0, 1, 2]
    received = [info['received_timestamp'] for _data, info in taken]
    assert received == sorted(received) and received[0] > 0
    node.destroy_node()


def test_a_destroyed_subscription_ends_the_taking(context):
    node, subscription = queued_node(context, 'take_queued_gone', raw=False, count=5)
    taken = take_queued(subscription, 10)
    assert next(taken)[0].data == 0
    node.destroy_subscription(subscription)
    assert list(taken) == []
    node.destroy_node()
