"""foxglove_live: the PMA topics, live, in Foxglove (docs/live-view.md).

    ros2 run pma_bringup foxglove_live [--ros-args -p host:=127.0.0.1 -p port:=8765
                                        -p topics:="['pma/state', '/*/pma/state']"]

Foxglove (desktop or web app) -> Open connection -> Foxglove WebSocket -> the ws:// URL this
prints. Each topic is subscribed raw, with the QoS its publishers offer (pma_bag's recorder
rule), as soon as the graph shows it, and its CDR bytes are passed through untouched on a
channel that carries the type's `ros2msg` schema, built from the installed interface files
(pma_bag.schemas): nothing is decoded on the way and any message type works. Topic names are
the ROS names, as foxglove_bridge and our bags have them, so one layout
(share/pma_bringup/foxglove/pma_testbed.json) serves all three.

A publisher that restarts is heard again on the same channel; one that comes back with other
QoS is subscribed again to match it, one with another type gets a new channel. A viewer that
subscribes to a latched topic (pma/model_params) gets its last message at once.

Read-only: clients cannot publish, call services or set parameters. It listens on localhost
unless `host` says otherwise; docs/live-view.md explains opening it to the lab network.

Viewers offering the WebSocket subprotocol `foxglove.websocket.v1` (the published spec's name,
PlotJuggler, older Lichtblick and Foxglove Studio) and `foxglove.sdk.v1` are both served: the
public port is a thin handshake layer (ws_handshake.py) in front of foxglove-sdk's server on an
ephemeral loopback port, since foxglove-sdk accepts only its own name.
"""

from __future__ import annotations

import fnmatch
import ipaddress
import re
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import foxglove
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.validate_topic_name import validate_topic_name

from pma_bag.errors import SchemaError
from pma_bag.record import DEFAULT_TOPICS as RECORDED_TOPICS
from pma_bag.record import message_class, subscription_qos
from pma_bag.schemas import message_schema
from pma_common import names
from pma_common.diagnostics import publish_status
from pma_common.node import ros_context, spin_until_stopped
from pma_common.parameters import node_or_exit

from .ws_handshake import SUBPROTOCOLS, HandshakeProxy

DEFAULT_HOST = '127.0.0.1'
DEFAULT_PORT = 8765
DEFAULT_TOPICS = list(RECORDED_TOPICS)   # what a bag of the rig holds: one layout for both
GRAPH_PERIOD_S = 0.25     # how often new topics, restarted publishers and QoS changes are seen
QUEUE_DEPTH = 100         # per subscription; a viewer is not a recorder
LAYOUT = Path('foxglove') / 'pma_testbed.json'   # under the package's share directory
_GLOB = re.compile(r'[*?\[]')
_HOSTNAME = re.compile(r'^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?'
                       r'(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$')


# -- plain helpers (no ROS) ----------------------------------------------------------------

def is_pattern(entry: str) -> bool:
    return bool(_GLOB.search(entry))


def check_host(host: str) -> str:
    """'' if `host` is an address or host name to listen on, else why not."""
    try:
        ipaddress.ip_address(host)
        return ''
    except ValueError:
        pass
    if _HOSTNAME.match(host):
        return ''
    return f'host {host!r} is neither an IP address nor a host name'


def check_topic_entry(entry: str) -> str:
    """'' if `entry` is a topic name or an absolute glob ('/*/pma/state'), else why not."""
    if is_pattern(entry):
        if not entry.startswith('/'):
            return (f'topic pattern {entry!r} must be absolute (start with /), e.g. '
                    "'/*/pma/state' for every muscle's state")
        return ''
    try:
        validate_topic_name(entry)
    except Exception as exc:  # rclpy raises its own InvalidTopicNameException (a subclass)
        return f'topic {entry!r}: {str(exc).splitlines()[0]}'
    return ''


def matches(topic: str, names: set[str], patterns: list[str]) -> bool:
    """A topic is forwarded if named, or matched by a pattern (fnmatch: '*' spans '/' too)."""
    return topic in names or any(fnmatch.fnmatchcase(topic, p) for p in patterns)


def viewer_urls(host: str, port: int) -> list[str]:
    """The ws:// URLs to give a viewer; for a wildcard address, this machine's name too."""
    if host in ('0.0.0.0', '::'):
        return [f'ws://{socket.gethostname()}:{port}', f'ws://127.0.0.1:{port}']
    shown = f'[{host}]' if ':' in host else host
    return [f'ws://{shown}:{port}']


# -- the node --------------------------------------------------------------------------------

@dataclass
class _Forwarded:
    """One ROS topic and the Foxglove channel its bytes go to."""

    topic: str
    type_name: str
    channel: foxglove.Channel
    qos: QoSProfile
    subscription: object = None
    latched: bool = False
    last: tuple[bytes, int] | None = None     # latched topics: (data, log time) for late viewers
    count: int = 0


class _Viewers:
    """The server's listener: who subscribes to what (called from the server's threads)."""

    def __init__(self, on_first_subscribe):
        self._lock = threading.Lock()
        self._subscriptions: set[tuple[int, int]] = set()    # (client id, channel id)
        self._on_first_subscribe = on_first_subscribe

    def on_subscribe(self, client, channel) -> None:
        with self._lock:
            self._subscriptions.add((client.id, channel.id))
        self._on_first_subscribe(client.id, channel.id)

    def on_unsubscribe(self, client, channel) -> None:
        with self._lock:
            self._subscriptions.discard((client.id, channel.id))

    def clients(self) -> int:
        with self._lock:
            return len({client for client, _ in self._subscriptions})


class FoxgloveLive(Node):
    """Forwards the wanted topics, raw, to a Foxglove WebSocket server."""

    def __init__(self, **kwargs):
        super().__init__('foxglove_live', **kwargs)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.declare_parameter('host', DEFAULT_HOST, ParameterDescriptor(
            description='address to listen on: 127.0.0.1 = this machine only; 0.0.0.0 = '
                        'every interface (the lab network, see docs/live-view.md)',
            read_only=True))
        self.declare_parameter('port', DEFAULT_PORT, ParameterDescriptor(
            description='TCP port of the WebSocket server (0 = any free port)',
            integer_range=[IntegerRange(from_value=0, to_value=65535, step=1)],
            read_only=True))
        self.declare_parameter('topics', DEFAULT_TOPICS, ParameterDescriptor(
            description='topics to forward; relative names are resolved in the node '
                        "namespace; absolute glob patterns ('/*/pma/state') match any topic",
            read_only=True))
        wanted = self.get_parameter('topics').value
        self.names = {self.resolve_topic_name(t) for t in wanted if not is_pattern(t)}
        self.patterns = [t for t in wanted if is_pattern(t)]
        self.forwarded: dict[str, _Forwarded] = {}
        self.by_channel: dict[int, _Forwarded] = {}
        self.skipped: dict[str, str] = {}          # topic -> why it is not forwarded
        self.viewers = _Viewers(self.send_latched)
        self.fg_context = foxglove.Context()
        host = self.get_parameter('host').value
        # foxglove-sdk's server, on loopback only; viewers reach it through the handshake
        # layer on the public (host, port), which also accepts foxglove.websocket.v1.
        self.server = foxglove.start_server(
            name=f'PMA testbed ({self.get_fully_qualified_name()})', host='127.0.0.1',
            port=0, context=self.fg_context, server_listener=self.viewers, capabilities=[])
        try:
            self.proxy = HandshakeProxy(host, self.get_parameter('port').value,
                                        self.server.port)
        except OSError as exc:      # port in use, an address not of this machine
            self.server.stop()
            raise RuntimeError(str(exc)) from exc
        self.urls = viewer_urls(host, self.proxy.port)
        self.diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        self.create_timer(GRAPH_PERIOD_S, self.check_graph)
        self.create_timer(1.0, self.publish_status)
        self.check_graph()

    def _validate_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            reason = ''
            if parameter.name == 'host':
                reason = check_host(parameter.value)
            elif parameter.name == 'topics':
                reason = next(filter(None, map(check_topic_entry, parameter.value or [])), '')
                if not parameter.value:
                    reason = 'topics is empty: nothing to forward'
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    # -- topics ----------------------------------------------------------------------------

    def check_graph(self) -> None:
        """Forward every wanted topic that has publishers; follow their QoS and type."""
        for topic, _types in self.get_topic_names_and_types():
            if topic in self.skipped or not matches(topic, self.names, self.patterns):
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue          # nobody publishes (now): keep what we have, if anything
            type_name = publishers[0].topic_type
            offered = [p.qos_profile for p in publishers if p.topic_type == type_name]
            qos = subscription_qos(offered, QUEUE_DEPTH)
            entry = self.forwarded.get(topic)
            if entry is not None and entry.type_name == type_name:
                if (entry.qos.reliability, entry.qos.durability) != (qos.reliability,
                                                                     qos.durability):
                    self.resubscribe(entry, qos)
                continue
            self.forward(topic, type_name, qos)

    def forward(self, topic: str, type_name: str, qos: QoSProfile) -> None:
        """Advertise `topic` with its schema and subscribe it raw (a new type: a new channel)."""
        try:
            schema = message_schema(type_name)
            msg_type = message_class(type_name)
        except (SchemaError, ImportError, AttributeError, ValueError) as exc:
            self.skipped[topic] = f'{type_name}: {exc}'
            self.get_logger().error(f'not forwarding {topic} [{type_name}]: {exc}')
            return
        old = self.forwarded.pop(topic, None)
        if old is not None:
            self.get_logger().warning(f'{topic} changed type {old.type_name} -> {type_name}: '
                                      'new channel')
            self.destroy_subscription(old.subscription)
            self.by_channel.pop(old.channel.id(), None)
            old.channel.close()
        channel = foxglove.Channel(
            topic, message_encoding='cdr', context=self.fg_context,
            schema=foxglove.Schema(name=schema.type_name, encoding=schema.encoding,
                                   data=schema.text.encode()))
        entry = _Forwarded(topic, type_name, channel, qos)
        entry.subscription = self._subscribe(entry, msg_type)
        self.forwarded[topic] = entry
        self.by_channel[channel.id()] = entry
        self.get_logger().info(f'forwarding {topic} [{type_name}] '
                               f'{qos.reliability.name.lower()} {qos.durability.name.lower()}')

    def resubscribe(self, entry: _Forwarded, qos: QoSProfile) -> None:
        """Publishers came back with other QoS: match them, on the same channel."""
        self.get_logger().info(f'{entry.topic}: publishers now offer '
                               f'{qos.reliability.name.lower()} {qos.durability.name.lower()}; '
                               'subscribing again')
        self.destroy_subscription(entry.subscription)
        entry.qos = qos
        entry.subscription = self._subscribe(entry, message_class(entry.type_name))

    def _subscribe(self, entry: _Forwarded, msg_type):
        entry.latched = entry.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        channel = entry.channel

        def on_message(data: bytes, info: dict) -> None:
            # Foxglove's receive time is when DDS delivered it (as rosbag2's recv_timestamp).
            log_time = info.get('received_timestamp') or time.time_ns()
            entry.count += 1
            if entry.latched:
                entry.last = (data, log_time)
            channel.log(data, log_time=log_time)

        return self.create_subscription(msg_type, entry.topic, on_message, entry.qos, raw=True)

    def send_latched(self, client_id: int, channel_id: int) -> None:
        """A viewer subscribed: a latched topic's value in force goes to that viewer only."""
        entry = self.by_channel.get(channel_id)
        last = entry.last if entry is not None else None
        if last is not None:
            entry.channel.log(last[0], log_time=last[1], sink_id=client_id)

    # -- status ------------------------------------------------------------------------------

    def publish_status(self) -> None:
        forwarded = sorted(self.forwarded)
        viewers = self.viewers.clients()
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: live view',
                                  hardware_id=self.urls[0])
        values = {'url': ' '.join(self.urls), 'viewers': str(viewers),
                  'connections': str(self.proxy.open_connections()),
                  'topics forwarded': ' '.join(forwarded) or '-',
                  'messages forwarded': str(sum(e.count for e in self.forwarded.values()))}
        for topic, reason in sorted(self.skipped.items()):
            values[f'not forwarded: {topic}'] = reason
        if self.skipped:
            status.level = DiagnosticStatus.WARN
            status.message = (f'{len(self.skipped)} topics not forwarded (no message definition '
                              'installed); see values')
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{len(forwarded)} topics to {viewers} viewers'
        publish_status(self, self.diagnostics, status, values)

    def close(self) -> None:
        self.proxy.close()
        self.server.stop()
        for entry in self.forwarded.values():
            entry.channel.close()


def layout_path() -> Path | None:
    """The installed layout file (a symlink into the source tree in a symlink install)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        path = Path(get_package_share_directory('pma_bringup')) / LAYOUT
    except PackageNotFoundError:
        return None
    return path.resolve() if path.exists() else None


def main(args: list[str] | None = None) -> int:
    with ros_context(args) as stop:
        try:
            node = node_or_exit(FoxgloveLive, 'foxglove_live')
        except RuntimeError as exc:   # the server could not listen (port in use, bad address)
            print(f'foxglove_live: cannot start the WebSocket server: {exc}. Is another '
                  'foxglove_live or foxglove_bridge on that port? Choose another with '
                  '--ros-args -p port:=N', file=sys.stderr, flush=True)
            return 1
        try:
            print(f'foxglove_live: Foxglove WebSocket at {" or ".join(node.urls)} '
                  '(Foxglove: Open connection -> Foxglove WebSocket)', flush=True)
            print(f'foxglove_live: subprotocols {", ".join(SUBPROTOCOLS)} (foxglove-sdk '
                  f'serves them on 127.0.0.1:{node.server.port}, behind the public port)',
                  flush=True)
            layout = layout_path()
            if layout is not None:
                print(f'foxglove_live: layout: {layout} (Foxglove: Layouts -> Import from '
                      'file)', flush=True)
            spin_until_stopped(SingleThreadedExecutor(), node, stop)
        finally:
            node.close()
            node.destroy_node()
    print('foxglove_live: stopped', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
