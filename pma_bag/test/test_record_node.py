"""The recorder node, in-process: what it does before any discovery has happened."""

from __future__ import annotations

import rclpy
from rclpy.context import Context

from pma_bag.record import DEFAULT_TOPICS, Recorder, RecordOptions


def test_the_pma_topics_are_subscribed_at_once_not_after_discovery():
    """rosbag2 subscribes what it can at start; the old recorder waited for a graph check to
    find publishers, and each bag missed its first 0.5-3 s of already streaming topics."""
    context = Context()
    rclpy.init(context=context)
    try:
        recorder = Recorder(RecordOptions(), context=context)
        try:
            subscribed = set(recorder.subscribed)
            assert {recorder.resolve_topic_name(t) for t in DEFAULT_TOPICS} <= subscribed
            assert all(e.subscription is not None for e in recorder.subscribed.values())
        finally:
            recorder.destroy_node()
    finally:
        rclpy.shutdown(context=context)
