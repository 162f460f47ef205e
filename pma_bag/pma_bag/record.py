"""record: record PMA topics into a rosbag2-compatible MCAP bag (docs/bags.md).

    ros2 run pma_bag record [-o BAG_DIR] [--topics T ...] [--ros-args -r __ns:=/rig1]
    ros2 run pma_bag recover BAG [-o OUT]           (a bag cut short by a crash)

Messages are subscribed raw and stored as received, without decode/re-encode. Each topic is
subscribed once a publisher shows up (a periodic graph check), with the reliability and
durability its publishers offer, so latched pma/model_params is caught too. SIGINT/SIGTERM
close the bag; a write failure is logged and reported on /diagnostics, and the node stays up.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from datetime import datetime
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from pma_bag import BagError, BagWriteError, BagWriter
from pma_bag.recover import main as recover_main
from pma_common.node import ros_context, spin_until_stopped

FLUSH_AGE_S = 0.75
FLUSH_CHECK_S = 0.25
DEFAULT_TOPICS = ['pma/state', 'pma/pressure', 'pma/range', 'pma/prediction',
                  'pma/model_params', '/diagnostics']


def message_class(type_name: str):
    """The Python class of 'pkg/msg/Type' (needed for the typesupport of raw subscriptions)."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def subscription_qos(offered: list[QoSProfile], depth: int) -> QoSProfile:
    """Request what every publisher can match (rosbag2's adapt_request_to_offers).

    Reliable topics are kept in full (KEEP_ALL): when the recorder falls behind for a moment
    the backlog queues instead of overwriting samples it has not written yet.
    """
    reliable = all(p.reliability == ReliabilityPolicy.RELIABLE for p in offered)
    latched = all(p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if reliable else HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class Recorder(Node):
    """Subscribes the wanted topics as their publishers appear and writes them to a BagWriter."""

    def __init__(self, output: Path, topics: list[str], queue_depth: int = 1000,
                 graph_period_s: float = 0.5, fsync: bool = False):
        super().__init__('recorder')
        self.output = output
        self.queue_depth = queue_depth
        wanted = self.declare_parameter('topics', topics).value
        self.wanted = list(dict.fromkeys(self.resolve_topic_name(t) for t in wanted))
        self.subscriptions_by_topic: dict[str, object] = {}
        self.skipped: set[str] = set()
        self.error = ''
        self.announced = -1
        self.diagnostics = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        try:
            # Flushed when 0.75 s old, checked every 0.25 s: on disk within 1 s of arrival.
            self.writer: BagWriter | None = BagWriter(output, flush_interval_s=FLUSH_AGE_S,
                                                      fsync=fsync)
        except BagError as exc:
            self.writer = None
            self.fail(str(exc))
        self.create_timer(graph_period_s, self.check_graph)
        self.create_timer(FLUSH_CHECK_S, self.flush)
        self.create_timer(1.0, self.publish_status)
        self.check_graph()

    def fail(self, reason: str) -> None:
        """Stop writing, say why (log + /diagnostics ERROR) and keep the node alive."""
        if not self.error:
            self.error = reason
            self.get_logger().error(f'recording stopped: {reason}')
            print(f'recorder: ERROR {reason}', flush=True)
        self.publish_status()

    def check_graph(self) -> None:
        """Subscribe every wanted topic that now has publishers."""
        if self.writer is None or self.error:
            return
        for topic in self.wanted:
            if topic in self.subscriptions_by_topic or topic in self.skipped:
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if publishers:
                self.subscribe(topic, publishers)
        count = len(self.subscriptions_by_topic)
        if count != self.announced:
            self.announced = count
            print(f'recorder: recording {count} topics to {self.output}', flush=True)

    def subscribe(self, topic: str, publishers) -> None:
        type_name = publishers[0].topic_type
        offered = [p.qos_profile for p in publishers if p.topic_type == type_name]
        try:
            msg_type = message_class(type_name)
            self.writer.add_topic(topic, type_name, offered)
        except (ImportError, AttributeError, ValueError, BagError) as exc:
            self.skipped.add(topic)
            self.get_logger().error(f'not recording {topic} [{type_name}]: {exc}')
            return
        qos = subscription_qos(offered, self.queue_depth)
        self.subscriptions_by_topic[topic] = self.create_subscription(
            msg_type, topic, lambda data, info, topic=topic: self.on_message(topic, data, info),
            qos, raw=True)
        self.get_logger().info(
            f'recording {topic} [{type_name}] {qos.reliability.name.lower()} '
            f'{qos.durability.name.lower()}')

    def on_message(self, topic: str, data: bytes, info) -> None:
        if self.writer is None or self.error:
            return
        # log_time = when DDS received it (rosbag2's recv_timestamp), not when this callback
        # ran: a backlog in the executor must not bunch the timeline up.
        received_ns = info.get('received_timestamp') or time.time_ns()
        try:
            self.writer.write(topic, data, received_ns, info.get('source_timestamp'))
        except BagWriteError as exc:
            self.fail(str(exc))

    def flush(self) -> None:
        """Push the current chunk to disk once it is FLUSH_AGE_S old (a SIGKILL loses <= 1 s)."""
        if self.writer is not None and not self.error:
            try:
                self.writer.flush_if_due()
            except BagWriteError as exc:
                self.fail(str(exc))

    def publish_status(self) -> None:
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: bag recorder',
                                  hardware_id=str(self.output))
        if self.error:
            status.level, status.message = DiagnosticStatus.ERROR, self.error
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'recording {len(self.subscriptions_by_topic)} topics'
        written = self.writer.message_count if self.writer is not None else 0
        status.values = [KeyValue(key='bag', value=str(self.output)),
                         KeyValue(key='messages_written', value=str(written))]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics.publish(array)

    def close_bag(self) -> None:
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        try:
            writer.close()
        except BagError as exc:
            print(f'recorder: ERROR closing {self.output}: {exc}', flush=True)
            return
        print(f'recorder: wrote {writer.message_count} messages to {self.output}', flush=True)


def default_bag_name() -> Path:
    return Path(datetime.now().strftime('pma_bag_%Y_%m_%d-%H_%M_%S'))


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='record', description=__doc__.split('\n')[0])
    parser.add_argument('-o', '--output', type=Path,
                        help='bag directory to create (default pma_bag_<date-time>)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='topics to record (default: the PMA topics; relative names are '
                             'resolved in the node namespace)')
    parser.add_argument('--queue-depth', type=int, default=1000,
                        help='subscription queue depth per topic')
    parser.add_argument('--fsync', action='store_true',
                        help='fsync after every flush, so a power cut also loses at most ~1 s '
                             '(costs disk bandwidth on slow media)')
    parser.add_argument('--recover', type=Path, metavar='BAG',
                        help='same as `ros2 run pma_bag recover BAG`')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    user_args = rclpy.utilities.remove_ros_args(argv)[1:]
    if user_args[:1] == ['recover']:
        return recover_main(user_args[1:])
    args = parse_args(user_args)
    if args.recover is not None:
        return recover_main([str(args.recover)]
                            + (['-o', str(args.output)] if args.output else []))
    with ros_context(argv) as stop:
        node = Recorder(args.output or default_bag_name(), args.topics or DEFAULT_TOPICS,
                        queue_depth=args.queue_depth, fsync=args.fsync)
        try:
            spin_until_stopped(SingleThreadedExecutor(), node, stop)
        finally:
            node.close_bag()
            node.destroy_node()
    return 0


def legacy_main() -> int:
    """`ros2 run pma_driver recorder`: the old name, kept for one release."""
    print('recorder: `ros2 run pma_driver recorder` is now `ros2 run pma_bag record` '
          '(and `... recover`); the old name goes in the next release', file=sys.stderr)
    return main()


if __name__ == '__main__':
    sys.exit(main())
