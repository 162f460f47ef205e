"""play: play a recorded bag back onto the ROS graph with its original timing.

    ros2 run pma_bag play BAG [--rate R] [--loop] [--start-offset S] [--topics T ...]
                               [--remap /old:=/new ...] [--clock [HZ]] [--start-paused] [--delay S]

The recorded CDR bytes are published as they are (no decode/re-encode), spaced by their
log_time (receive time) divided by R, with each topic's recorded QoS when all its recorded
publisher profiles agree (else reliable/volatile, depth 1000). `--clock` publishes bag time
on /clock (rosgraph_msgs/Clock, best effort like rosbag2) for `use_sim_time` consumers.
Put BAG before a bare `--clock`, otherwise the bag name is taken as the rate in Hz.

Services (std_srvs/srv/Trigger): ~/pause, ~/resume, ~/toggle_paused, and ~/play_next
(while paused: publish the next message now, as rosbag2's play_next).
A missing, empty, truncated or foreign bag ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import threading
import time
import warnings
from pathlib import Path

from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from pma_bag import BagError, BagReader, TopicInfo
from pma_bag.reader import TruncatedBagWarning
from pma_common.commands import run_command
from pma_common.node import ros_context, spin_until_stopped, split_ros_args
from pma_common.service import SERVICE_QOS

NS_PER_S = 1_000_000_000
DEFAULT_QOS_DEPTH = 1000
MAX_RATE = 1e6                          # a day of bag in 0.1 s
MIN_CLOCK_HZ, MAX_CLOCK_HZ = 0.001, 1000.0
_POLICIES = {
    'reliability': ReliabilityPolicy,
    'durability': DurabilityPolicy,
    'liveliness': LivelinessPolicy,
}


def _duration(value: dict) -> Duration:
    return Duration(seconds=int(value['sec']), nanoseconds=int(value['nsec']))


def playback_qos(profiles: list[dict]) -> QoSProfile:
    """The recorded QoS if all recorded profiles agree, else the default (as rosbag2 does).

    History and depth are not carried by DDS discovery (recorded as unknown/0), so the player
    keeps the last DEFAULT_QOS_DEPTH messages, enough for a burst after a pause.
    """
    default = QoSProfile(depth=DEFAULT_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    if not profiles or any(p != profiles[0] for p in profiles):
        return default
    recorded = profiles[0]
    try:
        policies = {key: enum[str(recorded[key]).upper()] for key, enum in _POLICIES.items()}
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                         depth=max(int(recorded.get('depth', 0)), DEFAULT_QOS_DEPTH), **policies)
        for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
            setattr(qos, key, _duration(recorded[key]))
    except (KeyError, TypeError, ValueError):
        return default
    if 'UNKNOWN' in (policies['reliability'].name, policies['durability'].name):
        return default
    return qos


def message_class(type_name: str):
    package, _, name = type_name.split('/')
    try:
        return getattr(importlib.import_module(f'{package}.msg'), name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f'message type {type_name} is not installed here (build and source '
                       f'the package that defines it): {exc}') from exc


def check_types(reader: BagReader, topics: dict[str, TopicInfo]) -> dict[str, type]:
    """Import each topic's class and decode its first message, so a mismatch fails early."""
    classes = {}
    for name, info in topics.items():
        msg_type = message_class(info.type_name)
        first = next(iter(reader.messages([name])), None)
        if first is not None:
            try:
                deserialize_message(first.data, msg_type)
            except Exception as exc:  # the typesupport raises several types
                raise BagError(f'messages on {name} do not decode as {info.type_name}: '
                               f'{exc}') from exc
        classes[name] = msg_type
    return classes


def normalise(topic: str) -> str:
    return topic if topic.startswith('/') else f'/{topic}'


def parse_remaps(pairs: list[str]) -> dict[str, str]:
    remaps = {}
    for pair in pairs:
        old, sep, new = pair.partition(':=')
        if not sep or not old or not new:
            raise BagError(f'bad --remap {pair!r}: expected /old:=/new')
        remaps[normalise(old)] = normalise(new)
    return remaps


def playback_start(reader: BagReader, topics: list[str],
                   start_offset_s: float) -> tuple[int, int]:
    """(bag time to start at, messages of `topics` from there); BagError if none is left.

    The offset counts from the bag's first message (as in ros2 bag play). An offset past the
    end would otherwise announce the whole bag and then play nothing.
    """
    first_ns, last_ns = reader.time_range_ns()
    start_ns = first_ns + round(start_offset_s * NS_PER_S)
    if start_ns == first_ns:
        return start_ns, sum(reader.topics[t].message_count for t in topics)
    length = f'the bag lasts {(last_ns - first_ns) / NS_PER_S:.3f} s'
    if start_ns > last_ns:
        raise BagError(f'--start-offset {start_offset_s:g} s is past the end: {length}')
    count = sum(1 for _ in reader.messages(topics, start_time_ns=start_ns))
    if not count:
        raise BagError(f'no message of {", ".join(topics)} from --start-offset '
                       f'{start_offset_s:g} s on ({length})')
    return start_ns, count


class Player(Node):
    """Publishes a bag's messages from a playback thread; the executor serves the services."""

    def __init__(self, reader: BagReader, args: argparse.Namespace):
        super().__init__('player')
        self.reader = reader
        self.rate = args.rate
        self.loop = args.loop
        self.delay_s = args.delay
        topics = reader.topics
        if args.topics:
            wanted = [normalise(t) for t in args.topics]
            unknown = [t for t in wanted if t not in topics]
            if unknown:
                raise BagError(f'topics not in the bag: {", ".join(unknown)} (bag has: '
                               f'{", ".join(topics)})')
            topics = {t: topics[t] for t in wanted}
        if args.clock is not None:
            topics.pop('/clock', None)
        if not any(t.message_count for t in topics.values()):
            raise BagError(f'bag {reader.path} has no messages to play')
        classes = check_types(reader, topics)
        remaps = parse_remaps(args.remap or [])
        self.publishers_by_topic = {
            name: self.create_publisher(classes[name], remaps.get(name, name),
                                        playback_qos(info.offered_qos_profiles))
            for name, info in topics.items()}
        self.start_ns, self.message_total = playback_start(reader, list(topics),
                                                           args.start_offset)
        self._lock = threading.Lock()
        self._anchor = (self.start_ns, time.monotonic_ns())  # (bag ns, wall ns) while playing
        self._paused_at: int | None = self.start_ns if args.start_paused else None
        self.finished = threading.Event()
        self.stopping = threading.Event()
        # Each queues a burst (SERVICE_QOS), as every service of the project does.
        self.create_service(Trigger, '~/pause', self.on_pause, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/resume', self.on_resume, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/toggle_paused', self.on_toggle, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/play_next', self.on_play_next, qos_profile=SERVICE_QOS)
        self._step_wanted = threading.Event()   # play_next asked for one message
        self._stepped = threading.Event()       # ... and the playback thread published it
        if args.clock is not None:
            self.clock_publisher = self.create_publisher(
                Clock, '/clock', QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
            self.create_timer(1.0 / args.clock, self.publish_clock)
        self.thread = threading.Thread(target=self.play, daemon=True)

    # -- timeline ---------------------------------------------------------------------------

    def bag_now(self) -> int:
        """Current bag time [ns since epoch] of the playback timeline."""
        with self._lock:
            return self._paused_at if self._paused_at is not None else self._running_ns()

    def _running_ns(self) -> int:
        """Where the running timeline is now (hold the lock)."""
        bag, wall = self._anchor
        return bag + int((time.monotonic_ns() - wall) * self.rate)

    def restart_timeline(self, bag_ns: int) -> None:
        with self._lock:
            if self._paused_at is not None:
                self._paused_at = bag_ns
            self._anchor = (bag_ns, time.monotonic_ns())

    def set_paused(self, paused: bool) -> bool:
        """Pause or resume; return whether the state changed."""
        with self._lock:
            if paused == (self._paused_at is not None):
                return False
            if paused:
                self._paused_at = self._running_ns()
            else:
                self._anchor = (self._paused_at, time.monotonic_ns())
                self._paused_at = None
            return True

    @property
    def paused(self) -> bool:
        with self._lock:
            return self._paused_at is not None

    def on_pause(self, _request, response):
        response.success = True
        response.message = 'paused' if self.set_paused(True) else 'already paused'
        return response

    def on_resume(self, _request, response):
        response.success = True
        response.message = 'resumed' if self.set_paused(False) else 'already playing'
        return response

    def on_play_next(self, _request, response):
        """While paused, publish the next message at once; the timeline moves to it."""
        if not self.paused:
            response.success, response.message = False, 'not paused (pause first)'
            return response
        self._stepped.clear()
        self._step_wanted.set()
        if self._stepped.wait(2.0):
            response.success, response.message = True, 'published the next message'
        else:
            self._step_wanted.clear()
            response.success, response.message = False, 'no message left to play'
        return response

    def on_toggle(self, _request, response):
        self.set_paused(not self.paused)
        response.success = True
        response.message = 'paused' if self.paused else 'resumed'
        return response

    def publish_clock(self) -> None:
        now = self.bag_now()
        self.clock_publisher.publish(Clock(clock=Time(sec=now // NS_PER_S,
                                                      nanosec=now % NS_PER_S)))

    # -- playback thread --------------------------------------------------------------------

    def wait_until(self, log_time_ns: int) -> bool:
        """Sleep until the timeline reaches log_time_ns; False if playback is stopping."""
        while not self.stopping.is_set():
            if self.paused:  # even a message due right now waits for the resume ...
                if self._step_wanted.is_set():  # ... unless play_next asks for it
                    self._step_wanted.clear()
                    with self._lock:
                        self._paused_at = max(self._paused_at, log_time_ns)
                    return True
                time.sleep(0.01)
                continue
            ahead_ns = log_time_ns - self.bag_now()
            if ahead_ns <= 0:
                return True
            time.sleep(min(ahead_ns / self.rate / NS_PER_S, 0.05))
        return False

    def play(self) -> None:
        topics = list(self.publishers_by_topic)
        message = None
        try:
            while not self.stopping.wait(self.delay_s):
                self.restart_timeline(self.start_ns)
                for message in self.reader.messages(topics, start_time_ns=self.start_ns):
                    if not self.wait_until(message.log_time_ns):
                        return
                    self.publishers_by_topic[message.topic].publish(message.data)
                    self._stepped.set()
                if not self.loop:
                    break
            if message is not None:
                # /clock stops at the end of the bag while acks drain. The timeline is already
                # a little past the last message (it was published once due), and /clock must
                # never step back: stop where it is.
                with self._lock:
                    if self._paused_at is None:
                        self._paused_at = max(message.log_time_ns, self._running_ns())
            for publisher in self.publishers_by_topic.values():
                publisher.wait_for_all_acked(Duration(seconds=1))
        finally:
            self.finished.set()


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='play', description=__doc__.split('\n')[0])
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('-r', '--rate', type=float, default=1.0, help='speed factor (> 0)')
    parser.add_argument('-l', '--loop', action='store_true', help='play again from the start')
    parser.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                        help='start S seconds after the first message')
    parser.add_argument('--topics', nargs='+', metavar='TOPIC', help='play only these topics')
    parser.add_argument('-m', '--remap', nargs='+', metavar='/OLD:=/NEW',
                        help='publish a recorded topic under another name')
    parser.add_argument('-d', '--delay', type=float, default=0.0, metavar='S',
                        help='wait S seconds before playing (each loop), e.g. for discovery')
    parser.add_argument('--clock', type=float, nargs='?', const=40.0, metavar='HZ',
                        help='publish bag time on /clock (default 40 Hz)')
    parser.add_argument('-p', '--start-paused', action='store_true',
                        help='wait for ~/resume or ~/toggle_paused before playing')
    args = parser.parse_args(argv)
    # float() takes 'nan' and 'inf', which no comparison below refuses.
    numbers = {'--rate': args.rate, '--start-offset': args.start_offset,
               '--delay': args.delay, '--clock': args.clock}
    for name, value in numbers.items():
        if value is not None and not math.isfinite(value):
            parser.error(f'{name} must be a finite number, got {value}')
    # The upper bounds keep the arithmetic in range (bag ns * rate, rclpy's timer period,
    # threading's longest wait); nobody needs more.
    if not 0 < args.rate <= MAX_RATE:
        parser.error(f'--rate must be > 0 and <= {MAX_RATE:g}')
    if args.clock is not None and not MIN_CLOCK_HZ <= args.clock <= MAX_CLOCK_HZ:
        parser.error(f'--clock must be {MIN_CLOCK_HZ:g} to {MAX_CLOCK_HZ:g} Hz')
    if args.start_offset < 0:
        parser.error('--start-offset must be >= 0')
    if not 0 <= args.delay <= threading.TIMEOUT_MAX:
        parser.error(f'--delay must be >= 0 and <= {threading.TIMEOUT_MAX:g} s')
    return args


def open_bag(path: Path) -> BagReader:
    """Open for playback: a truncated bag is refused (recover it first)."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', TruncatedBagWarning)
        reader = BagReader(path)
    if reader.truncated:
        reader.close()
        raise BagError(f'bag {path} is truncated (not closed by its recorder); recover it '
                       f'first: {run_command("pma_bag", "recover", path)}')
    return reader


def main(argv: list[str] | None = None) -> int:
    user_args, argv = split_ros_args(sys.argv if argv is None else argv)
    args = parse_args(user_args)
    try:
        reader = open_bag(args.bag)
    except BagError as exc:
        print(f'play: {exc}', file=sys.stderr)
        return 2
    with ros_context(argv) as stop:
        try:
            player = Player(reader, args)
        except BagError as exc:
            print(f'play: {exc}', file=sys.stderr)
            reader.close()
            return 2
        print(f'play: playing {player.message_total} messages on '
              f'{len(player.publishers_by_topic)} topics from {args.bag} at rate {args.rate}'
              + (f' from {args.start_offset:g} s on' if args.start_offset else '')
              + (' (paused)' if args.start_paused else ''), flush=True)
        player.thread.start()
        try:
            spin_until_stopped(SingleThreadedExecutor(), player, stop,
                               until=player.finished.is_set)
            if player.finished.is_set():
                print('play: done', flush=True)
        finally:
            player.stopping.set()
            player.thread.join(2)
            player.destroy_node()
            reader.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
