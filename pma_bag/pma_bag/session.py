"""One bag's recording session, without ROS: what happens to a message once it has arrived.

The recorder node (`pma_bag.record.Recorder`) owns the ROS side: parameters, subscriptions
and their QoS, services and /diagnostics. It hands every message it receives to the open
`RecordingSession`, which decides whether and how it is written: the bag's topics, pause
windows by receive time, event history from before the bag, loss accounting (pma/state
sequence numbers, DDS message-lost events), splits, the flush policy, custom_data and the
summary that `~/stop` and the exit line report (docs/bags.md, Record). Free of rclpy, so it
is tested by writing and reading real bags without a ROS graph.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pma_bag.errors import BagError, BagWriteError
from pma_bag.writer import BagWriter
from pma_common.commands import run_command
from pma_common.sequence import SequenceTracker

STATE_TYPE = 'pma_interfaces/msg/PmaState'
# The current chunk is pushed to disk once it is this old, so a SIGKILL loses about 1 s.
FLUSH_AGE_S = 0.75
# Records on an event topic with a source stamp older than the bag's opening by more than
# this (two hosts' clocks) are the publisher's history from before the bag: not written.
EVENT_HISTORY_SLACK_NS = 1_000_000_000
PAUSED_FOREVER = 2 ** 63
# Keys of the driver's /diagnostics copied into custom_data when the bag has none of its own.
RIG_DIAGNOSTIC_KEYS = ('firmware', 'protocol')
_STAMP = {1: struct.Struct('<iI'), 0: struct.Struct('>iI')}   # by the CDR's byte-order flag


def header_stamp_ns(cdr: bytes) -> int:
    """header.stamp in ns of a raw message whose first field is a std_msgs/Header.

    The stamp (int32 sec, uint32 nanosec) follows the 4-byte encapsulation header at once,
    so, unlike PmaState.seq (state_seq.py), it needs no layout check.
    """
    sec, nanosec = _STAMP[cdr[1] & 1].unpack_from(cdr, 4)
    return sec * 1_000_000_000 + nanosec


@dataclass
class RecordOptions:
    """How bags are written (command line of `record`, the same for every bag of the run)."""

    queue_depth: int = 1000
    fsync: bool = False
    compression: str = ''
    max_bag_size: int = 0
    max_bag_duration_s: float = 0.0
    custom_data: dict[str, str] = field(default_factory=dict)
    start_paused: bool = False


@dataclass(frozen=True)
class SessionSummary:
    """What a finished bag holds and lost: `~/stop`'s answer and the recorder's exit lines."""

    path: Path
    message_count: int          # written (all topics)
    messages_flushed: int       # known to have reached the disk
    loss: dict[str, int]        # RecordingSession.loss()
    error: str                  # '' when the bag was finished whole

    def lines(self) -> list[str]:
        """The recorder's lines about this bag (after `recorder: `)."""
        if self.error:
            lines = [f'ERROR bag {self.path} is incomplete ({self.error}); '
                     f'{self.messages_flushed} messages reached the disk. Recover them with: '
                     f'{run_command("pma_bag", "recover", self.path)}']
        else:
            lines = [f'wrote {self.message_count} messages to {self.path}']
        if self.loss['lost_messages']:
            lines.append(f'{self.loss["lost_messages"]} messages were lost before reaching the '
                         f'recorder (pma/state sequence: {self.loss["lost_state_samples"]} in '
                         f'{self.loss["state_sequence_gaps"]} gaps; DDS message-lost events: '
                         f'{self.loss["dds_messages_lost"]})')
        return lines


def rig_info_from(array) -> dict[str, str]:
    """The RIG_DIAGNOSTIC_KEYS a DiagnosticArray carries (the first of each, set values only)."""
    found: dict[str, str] = {}
    for status in array.status:
        for item in status.values:
            if item.key in RIG_DIAGNOSTIC_KEYS and item.value not in ('', '-'):
                found.setdefault(item.key, item.value)
    return found


class RecordingSession:
    """One bag being written, and what was lost before its messages reached the recorder.

    Not thread-safe: the node calls it under its own lock. A write failure (disk full) does
    not raise: the session stops writing, keeps `error` and calls `on_fail` once.
    """

    def __init__(self, path: Path, topics: Iterable[str], options: RecordOptions, *,
                 read_seq: Callable[[bytes], int],
                 custom_data: Mapping[str, str] | None = None,
                 rig_info: Mapping[str, str] | None = None,
                 event_topics: Iterable[str] = (),
                 derived_topics: Iterable[str] = (),
                 on_fail: Callable[[str], None] | None = None,
                 clock: Callable[[], int] = time.time_ns):
        """Create the bag (BagError if it cannot be made: a path holding a bag, ...).

        custom_data: this bag's entries over the options' ones; rig_info fills keys neither
        sets. read_seq: PmaState.seq from its CDR (pma_bag.state_seq). derived_topics: topics
        published for each PmaState with its header (a model's predictions), which a stop
        lets catch up (end_at_last_sample). clock: the receive time of a message that came
        without one, and of pauses.
        """
        data = {**options.custom_data, **(custom_data or {})}
        for key, value in (rig_info or {}).items():
            data.setdefault(key, value)
        self.writer = BagWriter(path, flush_interval_s=FLUSH_AGE_S, fsync=options.fsync,
                                compression=options.compression,
                                max_bag_size=options.max_bag_size,
                                max_bag_duration_s=options.max_bag_duration_s,
                                custom_data=data)
        self.path = path
        self.topics = list(topics)
        self.event_topics = frozenset(event_topics)
        self.derived_topics = frozenset(derived_topics)
        self._read_seq = read_seq
        self._on_fail = on_fail
        self._clock = clock
        self.opened_ns = clock()
        self.state_trackers: dict[str, SequenceTracker] = {}
        self.dds_lost = 0
        self.error = ''
        self.heard: set[str] = set()       # topics with a message since the bag started
        self.paused = False
        self._pause_ns = (0, 0)            # receive-time window of the latest pause
        # The last PmaState written, per topic (its stamp is read once, when the bag closes),
        # and the header stamp of the latest derived message heard.
        self._last_state_written: dict[str, bytes] = {}
        self.last_stamp_ns: dict[str, int] = {}
        self.closing = False               # end_at_last_sample was called
        self.end_stamp_ns: int | None = None

    # -- topics ----------------------------------------------------------------------------

    def records(self, topic: str) -> bool:
        """Is `topic` one of this bag's, and is the bag still being written?"""
        return not self.error and topic in self.topics

    def declared(self, topic: str) -> bool:
        return topic in self.writer.topics

    def declare(self, topic: str, type_name: str, offered_qos_profiles=()) -> None:
        """Add `topic` to the bag (BagError if it cannot be); a PmaState topic is counted."""
        if topic not in self.writer.topics:
            self.writer.add_topic(topic, type_name, offered_qos_profiles)
        if type_name == STATE_TYPE:
            self.state_trackers.setdefault(topic, SequenceTracker())

    # -- messages --------------------------------------------------------------------------

    def receive(self, topic: str, data: bytes, received_ns: int | None = None,
                source_ns: int | None = None) -> None:
        """A message of a declared topic as it arrived; written unless paused at receipt.

        pma/state is counted while paused too: not recorded is not lost.
        """
        derived = topic in self.derived_topics
        stamp_ns = header_stamp_ns(data) if derived else None
        if self.closing and not (derived and self.end_stamp_ns is not None
                                 and stamp_ns <= self.end_stamp_ns):
            return
        self.heard.add(topic)
        if derived and stamp_ns > self.last_stamp_ns.get(topic, -1):
            self.last_stamp_ns[topic] = stamp_ns
        tracker = self.state_trackers.get(topic)
        if tracker is not None:
            tracker.add(self._read_seq(data))
        if topic in self.event_topics and (source_ns or 0) \
                < self.opened_ns - EVENT_HISTORY_SLACK_NS:
            return
        received_ns = received_ns or self._clock()
        if not self.was_paused_at(received_ns) and self.write(topic, data, received_ns,
                                                                 source_ns):
            if tracker is not None:
                self._last_state_written[topic] = data

    def end_at_last_sample(self) -> None:
        """Take nothing that arrives from now on, except derived messages of samples already
        in the bag: a model running behind (1-2 s on a loaded machine) has not yet published
        the predictions of the last samples when a sweep stops its bag."""
        self.closing = True
        self.end_stamp_ns = max(map(header_stamp_ns, self._last_state_written.values()),
                                default=None)

    def lagging_topics(self) -> list[str]:
        """Derived topics heard in this bag whose latest message is for a sample before the
        bag's last one (none until end_at_last_sample, or when the bag holds no sample)."""
        if self.end_stamp_ns is None:
            return []
        return sorted(t for t in self.derived_topics
                      if t in self.heard and self.last_stamp_ns.get(t, -1) < self.end_stamp_ns)

    def write(self, topic: str, data: bytes, received_ns: int,
              source_ns: int | None = None) -> bool:
        """Write one message; log_time is the receive time, so an executor backlog does not
        bunch the timeline up. False when the write failed (the session has failed)."""
        try:
            self.writer.write(topic, data, received_ns, source_ns)
        except BagWriteError as exc:
            self.fail(str(exc))
            return False
        return True

    def add_dds_lost(self, topic: str, count: int) -> None:
        """Messages of `topic` DDS says never reached the recorder (message-lost event)."""
        if topic in self.topics:
            self.dds_lost += count

    # -- pause -----------------------------------------------------------------------------

    def set_paused(self, paused: bool) -> bool:
        """Pause or resume from now (by receive time); True if that changed anything."""
        changed, self.paused = self.paused != paused, paused
        if changed and paused:
            self._pause_ns = (self._clock(), PAUSED_FOREVER)
        elif changed:
            self._pause_ns = (self._pause_ns[0], self._clock())
        return changed

    def was_paused_at(self, received_ns: int) -> bool:
        """Paused when the message arrived? By receive time, not by when it is handled."""
        start, end = self._pause_ns
        return start <= received_ns < end

    # -- files -----------------------------------------------------------------------------

    def flush_if_due(self) -> None:
        """Push the current chunk to disk once it is FLUSH_AGE_S old (from the node's timer)."""
        if self.error:
            return
        try:
            self.writer.flush_if_due()
        except BagWriteError as exc:
            self.fail(str(exc))

    def split(self) -> tuple[bool, str]:
        """Continue in the next file: (split?, what happened)."""
        if self.error:
            return False, 'not recording'
        try:
            split = self.writer.split()
        except BagWriteError as exc:
            self.fail(str(exc))
            return False, str(exc)
        name = self.writer.mcap_path.name
        return split, (f'now writing {name}' if split else
                       f'{name} holds no message yet; not split')

    def add_custom_data(self, values: Mapping[str, str]) -> None:
        """Add the entries the bag has none of yet (rig info seen after it opened)."""
        writer = self.writer
        if writer.failed is None and not writer.closed:
            writer.update_custom_data({k: v for k, v in values.items()
                                       if k not in writer.custom_data})

    def fail(self, reason: str) -> bool:
        """Stop writing for `reason`; True (and on_fail called) the first time only."""
        if self.error:
            return False
        self.error = reason
        if self._on_fail is not None:
            self._on_fail(reason)
        return True

    def finish(self) -> SessionSummary:
        """Close the bag with its loss counts in custom_data; a close that fails is kept in
        `error` (the bag then needs `recover`), without on_fail: nothing is written after."""
        loss = self.loss()
        try:
            if self.writer.failed is None:
                self.writer.update_custom_data({k: str(v) for k, v in loss.items()})
            self.writer.close()
        except BagError as exc:
            self.error = self.error or str(exc)
        return self.summary()

    # -- numbers ---------------------------------------------------------------------------

    @property
    def message_count(self) -> int:
        return self.writer.message_count

    def loss(self) -> dict[str, int]:
        stats = [t.stats() for t in self.state_trackers.values()]
        lost_states = sum(s.lost for s in stats)
        return {'lost_messages': lost_states + self.dds_lost,
                'lost_state_samples': lost_states,
                'state_sequence_gaps': sum(s.gaps for s in stats),
                'dds_messages_lost': self.dds_lost}

    def summary(self) -> SessionSummary:
        return SessionSummary(self.path, self.writer.message_count,
                              self.writer.messages_flushed, self.loss(), self.error)

    def status_values(self) -> dict[str, str]:
        """The bag's entries in the recorder's /diagnostics status."""
        return {'bag': str(self.path), 'file': self.writer.mcap_path.name,
                'messages_written': str(self.writer.message_count),
                **{k: str(v) for k, v in self.loss().items()}}
