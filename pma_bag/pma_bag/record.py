"""record: record PMA topics into a rosbag2-compatible MCAP bag (docs/bags.md).

    ros2 run pma_bag record [-o BAG_DIR] [--topics T ...] [--compression zstd|lz4|none]
                            [--max-bag-size BYTES] [--max-bag-duration S]
                            [--note TEXT] [--custom KEY=VALUE ...] [--start-paused]
    ros2 run pma_bag record --idle          (no bag until a ~/start service call)
    ros2 run pma_bag recover BAG [-o OUT]   (a bag cut short by a crash)

Messages are subscribed raw and stored as received, without decode/re-encode. Wanted topics
are looked up in the graph at once and then every 0.1 s (rosbag2's topic polling interval),
and subscribed with the reliability and durability their publishers offer, so latched
pma/model_params is caught too. Subscriptions outlive a bag: a bag started with ~/start on a
running recorder records from the moment the call returns, and gets the latched messages
the recorder already holds.

Services (rosbag2's recorder services, plus start/stop): ~/start (pma_interfaces/srv/
StartRecording), ~/stop (StopRecording), ~/pause, ~/resume, ~/toggle_paused, ~/split_bagfile
(std_srvs/srv/Trigger), ~/is_paused (pma_interfaces/srv/IsPaused). A ~/start without topics
records the `topics` parameter as it is then (a run-time set applies to the next bag). A
refused ~/start is answered and logged (WARN); the open bag, if any, goes on.

The node is the ROS side (parameters, subscriptions and their QoS, services, /diagnostics);
each bag is a RecordingSession (session.py, no rclpy) that the node hands every message to.

SIGINT, SIGTERM and SIGHUP finish the bag (summary, metadata.yaml); signals during that are
ignored. A write failure (disk full) is logged and reported on /diagnostics and the node stays
up; it then exits with code 1 and says how to recover what reached the disk.
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.task import Future
from std_srvs.srv import Trigger

from pma_bag import BagError
from pma_bag.recover import main as recover_main
from pma_bag.session import (
    RIG_DIAGNOSTIC_KEYS,
    STATE_TYPE,
    RecordingSession,
    RecordOptions,
    rig_info_from,
)
from pma_bag.state_seq import pma_state_seq, state_seq_reader  # noqa: F401 (re-exported)
from pma_common import experiment, names
from pma_common.commands import run_command
from pma_common.diagnostics import publish_status
from pma_common.node import ros_context, spin_until_stopped, take_queued, without_ros_args
from pma_common.parameters import node_or_exit
from pma_common.service import SERVICE_QOS
from pma_interfaces.srv import IsPaused, StartRecording, StopRecording

FLUSH_CHECK_S = 0.25
GRAPH_PERIOD_S = 0.1         # rosbag2's default --topic-polling-interval
START_MATCH_TIMEOUT_S = 3.0  # ~/start waits at most this long for its topics to be heard
START_POLL_S = 0.01
# ~/stop lets a lagging model's predictions of the bag's samples arrive: at most this long
# (under the 5 s its callers wait for the answer), and only while they keep coming.
STOP_CATCH_UP_S = 3.0
DERIVED_QUIET_S = 1.0
LOST_WARNING_PERIOD_S = 1.0  # message-lost warnings are summed over this long
QUEUED_LIMIT = 100           # messages of one topic taken at once, so others get a turn
DEFAULT_TOPICS = list(names.RECORDED)
DIAGNOSTICS_TYPE = 'diagnostic_msgs/msg/DiagnosticArray'
# Types of the PMA topics (and whether they are latched), subscribed before discovery.
KNOWN_TOPICS = {
    names.STATE: (STATE_TYPE, False),
    names.PRESSURE: ('sensor_msgs/msg/FluidPressure', False),
    names.RANGE: ('sensor_msgs/msg/Range', False),
    names.PREDICTION: ('pma_interfaces/msg/PmaPrediction', False),
    names.MODEL_PARAMS: ('pma_interfaces/msg/ModelParams', True),
    names.CONTROL_STATE: ('pma_interfaces/msg/ControlState', False),
    names.PRESSURE_SETPOINT: ('std_msgs/msg/Float64', False),
    names.LENGTH_SETPOINT: ('pma_interfaces/msg/LengthSetpoint', False),
    names.SWEEP_RECORD: ('pma_interfaces/msg/SweepRecord', True),
    names.COMMANDER_LEASE: ('pma_interfaces/msg/CommanderLease', False),
    names.DIAGNOSTICS: (DIAGNOSTICS_TYPE, False),
}
# Transient local too, but records of what happened (a sweep's START, LEVELs, END), not a
# value in force: a new bag does not get the last one written again, and what a reader
# matched while a bag is open gets from before it opened (an earlier sweep's records, from
# the driver's history) is not written into it (session.EVENT_HISTORY_SLACK_NS).
EVENT_TOPICS = (names.SWEEP_RECORD,)
# Published with every sample while the rig runs. A reader can match a writer before that
# writer knows of it (discovery is per side), and only the writer's knowing delivers samples:
# a message heard is the one proof, so ~/start waits for one on these (waiting for the
# reader's side only, a bag on a loaded CI machine missed predictions after the sweep began).
PER_SAMPLE_TOPICS = (names.STATE, names.PRESSURE, names.RANGE, names.PREDICTION)
# Published for each pma/state sample with its header (docs/bags.md, "Stopping").
DERIVED_TOPICS = (names.PREDICTION,)
COMPRESSION_CHOICES = ('none', 'zstd', 'lz4')


def message_class(type_name: str):
    """The Python class of 'pkg/msg/Type' (needed for the typesupport of raw subscriptions)."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def assumed_qos(latched: bool, depth: int) -> QoSProfile:
    """What the PMA nodes offer (reliable; latched = transient local), for presubscribing."""
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


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


@dataclass
class _Subscribed:
    topic: str
    type_name: str
    offered: list | None           # publishers' QoS; None until discovery found them
    subscription: object
    qos: QoSProfile
    latched: bool
    received: int = 0                                 # messages so far
    last_received: float = -math.inf                  # monotonic time of the latest
    lost_unsaid: int = 0            # lost since the last warning (LOST_WARNING_PERIOD_S)
    lost_said_at: float = -math.inf
    last_latched: tuple[bytes, dict] | None = None   # (data, info) of a latched topic


class Recorder(Node):
    """Subscribes the wanted topics as their publishers appear; the open bag's session writes.

    What happens to a message once received (pause, loss, splits, flushing) is the
    session's: the node keeps only what outlives a bag (subscriptions, rig info, the last
    error and the bags that failed).
    """

    def __init__(self, options: RecordOptions, topics: list[str] | None = None,
                 graph_period_s: float = GRAPH_PERIOD_S, **node_kwargs):
        super().__init__('recorder', **node_kwargs)
        self.event_topics = set(self.resolve_topics(EVENT_TOPICS))
        self.derived_topics = set(self.resolve_topics(DERIVED_TOPICS))
        self.options = options
        self.default_topics: list[str] = []
        self.subscribed: dict[str, _Subscribed] = {}
        self.skipped: set[str] = set()
        self.bag: RecordingSession | None = None
        self._idle_paused = False              # ~/pause while no bag is open
        self.failed_bags: list[str] = []      # bags that could not be finished (recover them)
        self.error = ''                        # the last error, for /diagnostics
        self.target: Path | None = None        # the bag asked for last (in /diagnostics)
        # The request_id of the ~/start that opened self.bag ('' = none given): a resend of
        # that start answers for the bag instead of opening another.
        self.bag_request_id = ''
        self.rig_info: dict[str, str] = {}     # firmware/protocol seen on /diagnostics
        self.announced = -1
        self.last_message = 0.0                # monotonic time of the last message received
        # One thread runs every callback (a two-thread executor doubled the recorder's CPU
        # at 1 kHz); the lock only guards against a signal-time finish_bag.
        self._lock = threading.RLock()
        # pma/state's seq is read at its byte offset only if that reads a PmaState right.
        self.read_seq, why = state_seq_reader()
        if why:
            self.get_logger().warning(f'pma/state loss accounting: {why}')
        # A set applies to the next bag, as ~/start without topics reads it then; a bad
        # name is refused with the reason (at start: node_or_exit's one line, no start).
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.declare_parameter('topics', topics or DEFAULT_TOPICS, ParameterDescriptor(
            description='topics a bag records when ~/start names none; relative names '
                        'resolve in the node namespace. A change applies to the next bag; '
                        'the open one keeps its topics'))
        self.diagnostics = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 10)
        # ~/start awaits its topics while the messages' callbacks (default group) run on.
        # Every service queues a burst (SERVICE_QOS): with the default 10, of 300 requests
        # sent at once 11-39 were answered, the rest lost without an error.
        self.create_service(StartRecording, '~/start', self.on_start, qos_profile=SERVICE_QOS,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(StopRecording, '~/stop', self.on_stop, qos_profile=SERVICE_QOS,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self.create_service(Trigger, '~/split_bagfile', self.on_split, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/pause', self.on_pause, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/resume', self.on_resume, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/toggle_paused', self.on_toggle, qos_profile=SERVICE_QOS)
        self.create_service(IsPaused, '~/is_paused', self.on_is_paused, qos_profile=SERVICE_QOS)
        self.create_timer(graph_period_s, self.check_graph)
        self.create_timer(FLUSH_CHECK_S, self.flush)
        self.create_timer(1.0, self.publish_status)
        self.per_sample_topics = set(self.resolve_topics(PER_SAMPLE_TOPICS))

    def resolve_topics(self, topics) -> list[str]:
        return list(dict.fromkeys(self.resolve_topic_name(t) for t in topics))

    def topics_problem(self, topics) -> str:
        """Why `topics` cannot be recorded ('' if they can): rcl's reason for a bad name."""
        if not topics:
            return 'no topics given: a bag needs at least one'
        for topic in topics:
            try:
                self.resolve_topic_name(topic)
            except RuntimeError as exc:   # rclpy's RCLError: 'failed to resolve name: ..., at'
                reason = str(exc).removeprefix('failed to resolve name: ').rsplit(', at ', 1)[0]
                return f'{topic!r} is not a valid topic name: {reason}'
        return ''

    def _validate_parameters(self, parameters) -> SetParametersResult:
        """Check only; the change is made in _apply_parameters."""
        for parameter in parameters:
            if parameter.name == 'topics':
                reason = self.topics_problem(parameter.value)
                if reason:
                    return SetParametersResult(successful=False, reason=f'topics: {reason}')
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters) -> None:
        for parameter in parameters:
            if parameter.name != 'topics':
                continue
            changed = bool(self.default_topics)      # not the declaration at start-up
            with self._lock:
                self.default_topics = self.resolve_topics(parameter.value)
                bag = self.bag
            self.presubscribe()
            if changed:
                self.get_logger().info(
                    f'topics: the next bag records {" ".join(self.default_topics)}'
                    + (f' (the open bag {bag.path} keeps its {len(bag.topics)})'
                       if bag is not None else ''))

    # -- bags ------------------------------------------------------------------------------

    def start_bag(self, path: Path | None, topics: list[str] | None = None,
                  custom_data: dict[str, str] | None = None,
                  paused: bool = False, request_id: str = '') -> RecordingSession:
        """Open a new bag, then finish the open one, if any.

        BagError if the new bag cannot be made (bad topics, a path that holds a bag, ...):
        the open bag, if any, then goes on recording.
        """
        path = (path or default_bag_name()).absolute()
        reason = self.topics_problem(topics) if topics else ''
        if reason:
            raise BagError(reason)
        with self._lock:
            bag = RecordingSession(
                path, self.resolve_topics(topics) if topics else self.default_topics,
                self.options, read_seq=self.read_seq, custom_data=custom_data,
                rig_info=self.rig_info, event_topics=self.event_topics,
                derived_topics=self.derived_topics, on_fail=self._report_failure)
            if self.bag is not None:
                self.finish_bag()
            self.bag, self.error, self.target = bag, '', path
            self.bag_request_id = request_id
            self.set_paused(paused)
            now = time.time_ns()
            for entry in self.subscribed.values():
                if entry.topic in bag.topics:
                    self._add_to_bag(bag, entry)
                    if entry.last_latched is not None:
                        # The value in force when the bag started, stamped with the start.
                        data, info = entry.last_latched
                        bag.write(entry.topic, data, now, info.get('source_timestamp'))
        self.check_graph()
        return bag

    def finish_bag(self) -> tuple[RecordingSession | None, str]:
        """Close the open bag; (bag, '') or (bag, error) when it could not be finished."""
        with self._lock:
            bag, self.bag = self.bag, None
            if bag is None:
                return None, ''
            self._idle_paused = bag.paused
            summary = bag.finish()
        if summary.error:
            self.failed_bags.append(str(bag.path))
        for line in summary.lines():
            print(f'recorder: {line}', flush=True)
        return bag, summary.error

    def fail(self, bag: RecordingSession | None, reason: str) -> None:
        """Stop writing `bag` (None: no bag could be opened), say why and stay alive."""
        if bag is not None:
            bag.fail(reason)            # reports through _report_failure, the first time
        else:
            self._report_failure(reason)

    def _report_failure(self, reason: str) -> None:
        """Log it, print it and show it on /diagnostics (ERROR); the node stays up."""
        self.error = reason
        self.get_logger().error(f'recording stopped: {reason}')
        print(f'recorder: ERROR {reason}', flush=True)
        self.publish_status()

    # -- topics ----------------------------------------------------------------------------

    def wanted_topics(self) -> list[str]:
        bag = self.bag
        extra = [t for t in bag.topics if t not in self.default_topics] if bag else []
        return self.default_topics + extra

    def check_graph(self) -> None:
        """Subscribe every wanted topic that now has publishers."""
        wanted = [t for t in self.wanted_topics() if t not in self.skipped]
        unknown = [t for t in wanted
                   if t not in self.subscribed or self.subscribed[t].offered is None]
        if unknown:
            present = {name for name, _ in self.get_topic_names_and_types()}
            for topic in unknown:
                if topic in present:
                    publishers = self.get_publishers_info_by_topic(topic)
                    if publishers:
                        self.subscribe_offered(topic, publishers)
        bag = self.bag
        if bag is not None:
            count = sum(1 for t in bag.topics
                        if t in self.subscribed and self.subscribed[t].offered is not None)
            if count != self.announced:
                self.announced = count
                print(f'recorder: recording {count} topics to {bag.path}', flush=True)

    def presubscribe(self) -> None:
        """Subscribe the PMA topics of known type at once, before discovery finds them.

        A reader created after its writer was discovered is found by that writer only
        through another discovery round, which took 0.5-3 s (and lost those samples); a
        reader that exists from the start matches as a plain subscriber's does. The QoS is
        what the PMA nodes offer; subscribe_offered() adapts it when the offers differ.
        """
        for name, (type_name, latched) in KNOWN_TOPICS.items():
            topic = self.resolve_topic_name(name)
            if topic in self.default_topics and topic not in self.subscribed:
                self._subscribe(topic, type_name, None, assumed_qos(latched,
                                                                   self.options.queue_depth))

    def subscribe_offered(self, topic: str, publishers) -> None:
        """Subscribe (or adapt a presubscription) to what the publishers of `topic` offer."""
        type_name = publishers[0].topic_type
        offered = [p.qos_profile for p in publishers if p.topic_type == type_name]
        qos = subscription_qos(offered, self.options.queue_depth)
        entry = self.subscribed.get(topic)
        if entry is not None:
            same = (entry.type_name == type_name and entry.qos.reliability == qos.reliability
                    and entry.qos.durability == qos.durability)
            if same:
                with self._lock:
                    entry.offered = offered
                    if self.bag is not None and topic in self.bag.topics:
                        self._add_to_bag(self.bag, entry)
                return
            self.get_logger().info(f'{topic}: publishers offer {type_name} '
                                   f'{qos.reliability.name.lower()} '
                                   f'{qos.durability.name.lower()}; subscribing again')
            with self._lock:
                self.destroy_subscription(entry.subscription)
                del self.subscribed[topic]
        self._subscribe(topic, type_name, offered, qos)

    def _subscribe(self, topic: str, type_name: str, offered, qos: QoSProfile) -> None:
        try:
            msg_type = message_class(type_name)
        except (ImportError, AttributeError, ValueError) as exc:
            self.skipped.add(topic)
            self.get_logger().error(f'not recording {topic} [{type_name}]: {exc}')
            return
        entry = _Subscribed(topic, type_name, offered, None, qos,
                            qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
                            and topic not in self.event_topics)

        def on_message(data, info, entry=entry):
            self.on_message(entry, data, info)
            # A backlog is written now, not one executor wait per message (take_queued).
            for queued, queued_info in take_queued(entry.subscription, QUEUED_LIMIT):
                self.on_message(entry, queued, queued_info)

        def on_lost(event, entry=entry):
            self.on_message_lost(entry, event.total_count_change)

        with self._lock:
            if self.bag is not None and topic in self.bag.topics:
                try:
                    self._add_to_bag(self.bag, entry)
                except BagError as exc:
                    self.skipped.add(topic)
                    self.get_logger().error(f'not recording {topic} [{type_name}]: {exc}')
                    return
            try:
                entry.subscription = self.create_subscription(
                    msg_type, topic, on_message, qos, raw=True,
                    event_callbacks=SubscriptionEventCallbacks(message_lost=on_lost))
            except UnsupportedEventTypeError:
                self.get_logger().warning('this middleware reports no lost messages; only '
                                          'pma/state sequence gaps are counted')
                entry.subscription = self.create_subscription(
                    msg_type, topic, on_message, qos, raw=True)
            self.subscribed[topic] = entry
        self.get_logger().info(
            f'subscribed {topic} [{type_name}] {qos.reliability.name.lower()} '
            f'{qos.durability.name.lower()}'
            + (' (before discovery)' if offered is None else ''))

    def _add_to_bag(self, bag: RecordingSession, entry: _Subscribed) -> None:
        """Declare the topic in the bag, with its publishers' QoS (deferred until known)."""
        if not bag.declared(entry.topic) and entry.offered is None:
            publishers = [p for p in self.get_publishers_info_by_topic(entry.topic)
                          if p.topic_type == entry.type_name]
            if not publishers:
                return      # declared when its first message or publisher shows up
            entry.offered = [p.qos_profile for p in publishers]
        bag.declare(entry.topic, entry.type_name, entry.offered)

    def start_status(self, bag: RecordingSession) -> tuple[list[str], list[str]]:
        """(ready, not yet) topics of `bag` whose publishers the graph shows.

        Ready: the reader matched every publisher and, for a per-sample topic, a message
        arrived since the bag started. A publisher that discovery has not shown yet (0.2-3 s
        after it starts) cannot be waited for: /diagnostics' 'topics heard' says when the
        recorder hears a topic.
        """
        ready, waiting = [], []
        for topic in bag.topics:
            entry = self.subscribed.get(topic)
            if entry is None:
                continue
            known = len(self.get_publishers_info_by_topic(topic))
            matched = entry.subscription.get_publisher_count() >= max(known, 1)
            heard = topic in bag.heard or topic not in self.per_sample_topics
            if matched and heard:
                ready.append(topic)
            elif known:
                waiting.append(topic)
        return ready, sorted(waiting)

    # -- messages --------------------------------------------------------------------------

    def on_message(self, entry: _Subscribed, data: bytes, info: dict) -> None:
        self.last_message = entry.last_received = time.monotonic()
        entry.received += 1
        if entry.latched:
            entry.last_latched = (data, info)
        if entry.type_name == DIAGNOSTICS_TYPE:
            self.note_rig_info(data)
        with self._lock:
            bag = self.bag
            if bag is None or not bag.records(entry.topic):
                return
            if not bag.declared(entry.topic):
                try:
                    self._add_to_bag(bag, entry)
                except BagError as exc:
                    bag.fail(str(exc))
                    return
                if not bag.declared(entry.topic):
                    return
            # log_time = when DDS received it (rosbag2's recv_timestamp), not when this
            # callback ran: a backlog in the executor must not bunch the timeline up.
            bag.receive(entry.topic, data, info.get('received_timestamp'),
                        info.get('source_timestamp'))

    def on_message_lost(self, entry: _Subscribed, count: int) -> None:
        with self._lock:
            if self.bag is not None:
                self.bag.add_dds_lost(entry.topic, count)
        # Said at most once a period: a recorder falling behind gets an event every few
        # messages, and a warning each (rclpy's logger inspects the caller's frame) made it
        # fall further behind. The bag's summary counts every one.
        entry.lost_unsaid += count
        now = time.monotonic()
        if now - entry.lost_said_at >= LOST_WARNING_PERIOD_S:
            self.get_logger().warning(f'{entry.lost_unsaid} messages on {entry.topic} lost '
                                      'before reaching the recorder (DDS message-lost events)')
            entry.lost_unsaid, entry.lost_said_at = 0, now

    def note_rig_info(self, data: bytes) -> None:
        """Remember the driver's firmware/protocol from its /diagnostics for custom_data."""
        if all(key in self.rig_info for key in RIG_DIAGNOSTIC_KEYS):
            return
        try:
            array = deserialize_message(data, DiagnosticArray)
        except Exception:  # the typesupport raises several types; a bad message is not ours
            return
        new = {k: v for k, v in rig_info_from(array).items() if k not in self.rig_info}
        if not new:
            return
        with self._lock:
            self.rig_info.update(new)
            if self.bag is not None:
                self.bag.add_custom_data(new)

    def flush(self) -> None:
        """The session's flush policy, checked every FLUSH_CHECK_S."""
        with self._lock:
            if self.bag is not None:
                self.bag.flush_if_due()

    # -- services --------------------------------------------------------------------------

    async def on_start(self, request, response):
        """Open a bag; answer once its topics are heard (at most START_MATCH_TIMEOUT_S).

        A coroutine in its own callback group: while it waits, the executor's one thread
        writes the messages arriving into the new bag. Subscriptions outlive bags, so on a
        recorder that has been up a moment this answers within a sample period. (A caller
        that must not miss a sample of its own also waits until its publishers count the
        recorder's readers, as the driver's Sweep does.)
        """
        if request.request_id and request.request_id == self.bag_request_id \
                and self.bag is not None:
            bag = self.bag                  # the caller's resend: its answer was lost
        else:
            try:
                bag = self.start_bag(Path(request.bag_path) if request.bag_path else None,
                                     list(request.topics),
                                     {kv.key: kv.value for kv in request.custom_data},
                                     request_id=request.request_id)
            except BagError as exc:
                # The caller's error, answered here; the recorder is fine (not an ERROR status).
                still = f'still recording {self.bag.path}' if self.bag is not None else 'idle'
                response.success, response.message = False, str(exc)
                self.get_logger().warning(f'~/start refused ({still}): {exc}')
                return response
        deadline = time.monotonic() + START_MATCH_TIMEOUT_S
        ready, late = self.start_status(bag)
        while late and time.monotonic() < deadline and self.bag is bag:
            await self.yield_to_executor(START_POLL_S)
            ready, late = self.start_status(bag)
        if self.bag is not bag:
            response.success, response.message = False, f'{bag.path} was stopped while starting'
            return response
        response.success = True
        response.bag_path = str(bag.path)
        response.topics = ready
        response.message = (f'recording {len(ready)} topics to {bag.path}'
                            + (f'; not heard yet: {", ".join(late)}' if late else ''))
        return response

    async def yield_to_executor(self, seconds: float) -> None:
        """Yield to the executor for `seconds` (a one-shot timer in the default group)."""
        woken = Future()
        timer = self.create_timer(seconds, lambda: woken.done() or woken.set_result(None))
        try:
            await woken
        finally:
            self.destroy_timer(timer)

    async def on_stop(self, _request, response):
        """Finish the bag, once the derived topics have caught up with its last sample.

        A coroutine in its own callback group, like on_start: while it waits, the executor
        writes the late predictions into the bag.
        """
        bag = self.bag
        if bag is not None:
            await self.catch_up_derived(bag)
        if bag is None or self.bag is not bag:
            response.success = False
            response.message = ('not recording' if bag is None else f'{bag.path} was '
                                'finished meanwhile (a new ~/start or a stop signal)')
            return response
        bag, error = self.finish_bag()
        summary = bag.summary()
        response.success = not error
        response.message = error or f'wrote {summary.message_count} messages to {bag.path}'
        response.bag_path = str(bag.path)
        response.message_count = summary.message_count
        response.lost_message_count = summary.loss['lost_messages']
        return response

    async def catch_up_derived(self, bag: RecordingSession) -> None:
        """End `bag` at its last sample, then wait (<= STOP_CATCH_UP_S) for each derived
        topic to reach that sample, while its publisher is there and its messages keep coming:
        without a model running nothing is waited for."""
        with self._lock:
            bag.end_at_last_sample()
        started = time.monotonic()
        while True:
            lagging = bag.lagging_topics()
            waited = time.monotonic() - started
            if (self.bag is not bag or waited > STOP_CATCH_UP_S
                    or not any(self.still_coming(topic) for topic in lagging)):
                break
            await self.yield_to_executor(START_POLL_S)
        if lagging:
            self.get_logger().warning(
                f'~/stop: {", ".join(lagging)} had not reached the last sample of {bag.path} '
                f'after {waited:.1f} s; the bag ends without the rest')
        elif waited > 0.1:
            self.get_logger().info(f'~/stop waited {waited:.1f} s for the last predictions')

    def still_coming(self, topic: str) -> bool:
        """Is `topic`'s publisher there, and was it heard within DERIVED_QUIET_S?"""
        entry = self.subscribed.get(topic)
        return (entry is not None and entry.subscription.get_publisher_count() > 0
                and time.monotonic() - entry.last_received < DERIVED_QUIET_S)

    def on_split(self, _request, response):
        with self._lock:
            if self.bag is None:
                response.success, response.message = False, 'not recording'
            else:
                response.success, response.message = self.bag.split()
        return response

    @property
    def paused(self) -> bool:
        bag = self.bag
        return bag.paused if bag is not None else self._idle_paused

    def set_paused(self, paused: bool) -> bool:
        with self._lock:
            if self.bag is not None:
                changed = self.bag.set_paused(paused)
            else:
                changed, self._idle_paused = self._idle_paused != paused, paused
        if changed:
            self.get_logger().info('paused' if paused else 'resumed')
        return changed

    def on_pause(self, _request, response):
        response.success = True
        response.message = 'paused' if self.set_paused(True) else 'already paused'
        return response

    def on_resume(self, _request, response):
        response.success = True
        response.message = 'resumed' if self.set_paused(False) else 'already recording'
        return response

    def on_toggle(self, _request, response):
        with self._lock:
            paused = not self.paused
            self.set_paused(paused)
        response.success, response.message = True, 'paused' if paused else 'resumed'
        return response

    def on_is_paused(self, _request, response):
        response.paused = self.paused
        return response

    # -- status ----------------------------------------------------------------------------

    def publish_status(self) -> None:
        status, values = self.status()
        publish_status(self, self.diagnostics, status, values)

    def status(self) -> tuple[DiagnosticStatus, dict[str, str]]:
        """ERROR only for a bag that failed (self.error); a refused ~/start is not one."""
        with self._lock:
            bag = self.bag
            status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: bag recorder',
                                      hardware_id=str(self.target or ''))
            wanted = self.wanted_topics()
            values = {'state': 'idle' if bag is None else
                      ('paused' if self.paused else 'recording'),
                      # readers matched to at least one publisher: what a new bag would get
                      'topics heard': ' '.join(sorted(
                          topic for topic, entry in self.subscribed.items()
                          if topic in wanted
                          and entry.subscription.get_publisher_count() > 0)) or '-'}
            if bag is not None:
                loss = bag.loss()
                topics = sum(1 for t in bag.topics if t in self.subscribed)
                values.update(bag.status_values())
        if self.error:
            status.level, status.message = DiagnosticStatus.ERROR, self.error
        elif bag is None:
            status.level, status.message = DiagnosticStatus.OK, 'idle (no bag open)'
        elif loss['lost_messages']:
            status.level = DiagnosticStatus.WARN
            status.message = (f'recording {topics} topics; {loss["lost_messages"]} messages '
                              'lost before reaching the recorder')
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{values["state"]} {topics} topics'
        if self.failed_bags:
            values['incomplete bags (recover them)'] = ', '.join(self.failed_bags)
        return status, values


def drain(executor, node: Recorder, quiet_s: float = 0.2, limit_s: float = 1.0) -> None:
    """After a stop request, write what DDS already delivered (until quiet_s without any).

    A recorder stopped right after its publishers finish would otherwise drop the backlog
    still queued in its readers.
    """
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline and executor.context.ok() \
            and time.monotonic() - node.last_message < quiet_s:
        executor.spin_once(timeout_sec=0.02)


def default_bag_name() -> Path:
    return Path(datetime.now().strftime('pma_bag_%Y_%m_%d-%H_%M_%S'))


def key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition('=')
    if not sep or not key:
        raise argparse.ArgumentTypeError(f'expected KEY=VALUE, got {text!r}')
    return key, value


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='record', description=__doc__.split('\n')[0])
    parser.add_argument('-o', '--output', type=Path,
                        help='bag directory to create (default pma_bag_<date-time>); it must '
                             'not exist or be empty')
    parser.add_argument('--idle', action='store_true',
                        help='open no bag; wait for ~/start (e.g. from the driver\'s Sweep)')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC',
                        help='topics to record (default: the PMA topics; relative names are '
                             'resolved in the node namespace)')
    parser.add_argument('--compression', choices=COMPRESSION_CHOICES, default='none',
                        help='MCAP chunk compression (what rosbag2\'s mcap storage config '
                             'sets; every MCAP reader decompresses it)')
    parser.add_argument('--max-bag-size', type=int, default=0, metavar='BYTES',
                        help='split into <bag>_<n>.mcap files of about BYTES (0: no split)')
    parser.add_argument('--max-bag-duration', type=float, default=0.0, metavar='S',
                        help='split into files of at most S seconds (0: no split)')
    parser.add_argument('--note', help='free operator note, stored in metadata.yaml '
                                       'custom_data["note"]')
    experiment.add_arguments(parser)
    parser.add_argument('--custom', nargs='+', type=key_value, default=[],
                        metavar='KEY=VALUE', help='more custom_data entries (rig=..., '
                                                  'muscle=..., calibration=...)')
    parser.add_argument('--start-paused', action='store_true',
                        help='open the bag paused; ~/resume starts writing')
    parser.add_argument('--queue-depth', type=int, default=1000,
                        help='subscription queue depth per topic')
    parser.add_argument('--fsync', action='store_true',
                        help='fsync after every flush, so a power cut also loses at most ~1 s '
                             '(costs disk bandwidth on slow media)')
    parser.add_argument('--recover', type=Path, metavar='BAG',
                        help=f'same as `{run_command("pma_bag", "recover", "BAG")}`')
    args = parser.parse_args(argv)
    if args.idle and args.output:
        parser.error('--idle opens no bag: give the path in the ~/start request instead')
    try:
        experiment.from_arguments(args)
    except experiment.ExperimentError as error:
        parser.error(str(error))
    if not math.isfinite(args.max_bag_duration):
        parser.error(f'--max-bag-duration must be a finite number, got {args.max_bag_duration}')
    if args.max_bag_size < 0 or args.max_bag_duration < 0 or args.queue_depth < 1:
        parser.error('--max-bag-size and --max-bag-duration must be >= 0, --queue-depth >= 1')
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    user_args = without_ros_args(argv)[1:]
    if user_args[:1] == ['recover']:
        return recover_main(user_args[1:])
    args = parse_args(user_args)
    if args.recover is not None:
        return recover_main([str(args.recover)]
                            + (['-o', str(args.output)] if args.output else []))
    custom = {**dict(args.custom), **experiment.from_arguments(args)}
    if args.note:
        custom['note'] = args.note
    options = RecordOptions(queue_depth=args.queue_depth, fsync=args.fsync,
                            compression='' if args.compression == 'none' else args.compression,
                            max_bag_size=args.max_bag_size,
                            max_bag_duration_s=args.max_bag_duration, custom_data=custom,
                            start_paused=args.start_paused)
    with ros_context(argv, own_arguments=True) as stop:
        # -p topics:=x (a string, not a list) records nothing it was not asked for.
        node = node_or_exit(lambda: Recorder(options, args.topics), 'recorder')
        executor = SingleThreadedExecutor()
        try:
            if args.idle:
                print(f'recorder: idle; start a bag with {node.get_fully_qualified_name()}'
                      '/start', flush=True)
            else:
                path = (args.output or default_bag_name()).absolute()
                try:
                    node.start_bag(path, paused=options.start_paused)
                except BagError as exc:   # the bag this run was started for: an ERROR
                    node.target = path
                    node.fail(None, str(exc))
            spin_until_stopped(executor, node, stop)
            drain(executor, node)
        finally:
            # Its guard conditions go before the context does: left to the executor's __del__,
            # after rclpy's shutdown, they raised InvalidHandle at exit.
            executor.shutdown(timeout_sec=0.0)
            node.finish_bag()
            node.destroy_node()
        if stop.extra_signals:
            print(f'recorder: ignored {stop.extra_signals} more stop signals while finishing',
                  flush=True)
    failed = node.failed_bags or (node.error and not args.idle)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
