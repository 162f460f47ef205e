"""One status on /diagnostics, the way every PMA node reports itself."""

from __future__ import annotations

from collections.abc import Mapping

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.publisher import Publisher


def publish_status(node: Node, publisher: Publisher, status: DiagnosticStatus,
                   values: Mapping[str, object]) -> None:
    """Publish `status` alone, stamped now, with `values` as its key/value pairs (str'd)."""
    status.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
    array = DiagnosticArray(status=[status])
    array.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(array)
