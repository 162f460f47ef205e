"""BagWriter: a rosbag2 (jazzy, metadata v9) bag directory holding one MCAP file.

Layout `<bag>/<bag>_0.mcap` + `<bag>/metadata.yaml`, profile `ros2`, one `ros2msg` schema per
type, `cdr` channels carrying `offered_qos_profiles` and `topic_type_hash`, chunks with message
indexes and a Statistics record: what `ros2 bag record -s mcap` writes (docs/bags.md).

Crash safety: an MCAP chunk reaches the disk only when it is finished, so the writer finishes
and flushes the chunk at least every `flush_interval_s`; a SIGKILL then loses at most that
interval, and recover_bag() rebuilds the index from what is on disk.
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import CompressionType, IndexType, Writer

from pma_bag.errors import BagWriteError
from pma_bag.schemas import MessageSchema, message_schema

METADATA_VERSION = 9
DEFAULT_CHUNK_SIZE = 768 * 1024  # rosbag2's mcap default
LIBRARY = 'pma_bag (python mcap)'
# rmw's RMW_DURATION_INFINITE as rosbag2 writes it.
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}
_NS_PER_S = 1_000_000_000


def _duration_dict(value: Any) -> dict[str, int]:
    """{sec, nsec} from a dict, an int of ns, or an object with .nanoseconds (rclpy Duration)."""
    if isinstance(value, Mapping):
        return {'sec': int(value['sec']), 'nsec': int(value['nsec'])}
    nanoseconds = int(getattr(value, 'nanoseconds', value))
    return {'sec': nanoseconds // _NS_PER_S, 'nsec': nanoseconds % _NS_PER_S}


def _policy_name(value: Any) -> str:
    """v9 enum spelling: 'keep_last', 'reliable', 'transient_local', ... from enum or str."""
    name = getattr(value, 'name', value)
    return str(name).lower()


def qos_profile_dict(profile: Any) -> dict[str, Any]:
    """A full v9 QoS dict (rosbag2 metadata layout) from an rclpy QoSProfile or a dict.

    Duck-typed so that this package stays free of rclpy: the recorder passes the publishers'
    offered profiles from get_publishers_info_by_topic, recover passes parsed YAML.
    """
    get = profile.get if isinstance(profile, Mapping) else lambda key: getattr(profile, key)
    return {
        'history': _policy_name(get('history')),
        'depth': int(get('depth')),
        'reliability': _policy_name(get('reliability')),
        'durability': _policy_name(get('durability')),
        'deadline': _duration_dict(get('deadline')),
        'lifespan': _duration_dict(get('lifespan')),
        'liveliness': _policy_name(get('liveliness')),
        'liveliness_lease_duration': _duration_dict(get('liveliness_lease_duration')),
        'avoid_ros_namespace_conventions': bool(get('avoid_ros_namespace_conventions')),
    }


def dump_qos_profiles(profiles: list[dict[str, Any]]) -> str:
    """The channel-metadata form: a YAML string of the list (empty string for no profiles)."""
    if not profiles:
        return ''
    return yaml.safe_dump(profiles, default_flow_style=False, sort_keys=False).strip()


@dataclass
class _Topic:
    name: str
    schema: MessageSchema
    qos_profiles: list[dict[str, Any]]
    channel_id: int
    message_count: int = 0
    extra: dict[str, str] = field(default_factory=dict)


class BagWriter:
    """Write raw CDR messages into a new rosbag2-compatible MCAP bag directory.

    Not thread-safe: call it from one thread (the recorder's executor).
    """

    def __init__(self, bag_dir: str | os.PathLike, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 flush_interval_s: float = 1.0, fsync: bool = False, ros_distro: str | None = None,
                 compression: str = ''):
        self.bag_dir = Path(bag_dir)
        self.mcap_path = self.bag_dir / f'{self.bag_dir.name}_0.mcap'
        self.metadata_path = self.bag_dir / 'metadata.yaml'
        self.flush_interval_s = flush_interval_s
        self.fsync = fsync
        self.ros_distro = ros_distro or os.environ.get('ROS_DISTRO', 'jazzy')
        self.message_count = 0
        self.messages_flushed = 0  # message_count at the last flush: what a crash keeps
        self.start_time_ns: int | None = None
        self.end_time_ns: int | None = None
        self._topics: dict[str, _Topic] = {}
        self._schema_ids: dict[str, int] = {}
        self._failed: BagWriteError | None = None
        self._closed = False
        if self.metadata_path.exists() or self.mcap_path.is_file():
            raise BagWriteError(f'{self.bag_dir} already holds a bag; choose a new output path')
        compressions = {'': CompressionType.NONE, 'zstd': CompressionType.ZSTD,
                        'lz4': CompressionType.LZ4}
        if compression not in compressions:
            raise BagWriteError(f'unknown chunk compression {compression!r} (use zstd or lz4)')
        try:
            self.bag_dir.mkdir(parents=True, exist_ok=True)
            self._stream = open(self.mcap_path, 'wb')  # closed in close()
        except OSError as exc:
            reason = exc.strerror or exc
            raise BagWriteError(f'cannot create bag {self.bag_dir}: {reason}') from exc
        self._mcap = Writer(self._stream, chunk_size=chunk_size,
                            compression=compressions[compression], index_types=IndexType.ALL)
        self._guard(lambda: self._mcap.start(profile='ros2', library=LIBRARY))
        self._last_flush = time.monotonic()

    # -- topics and messages -------------------------------------------------------------

    @property
    def topics(self) -> dict[str, int]:
        """Message count per topic written so far."""
        return {name: topic.message_count for name, topic in self._topics.items()}

    def add_topic(self, topic: str, type_name: str, offered_qos_profiles: Iterable[Any] = (),
                  *, schema: MessageSchema | None = None) -> None:
        """Declare a topic before writing to it.

        schema defaults to the installed definition of type_name (SchemaError if missing);
        recover passes the schema found in the damaged bag instead.
        """
        if topic in self._topics:
            raise BagWriteError(f'topic {topic} was already added')
        schema = schema or message_schema(type_name)
        profiles = [qos_profile_dict(p) for p in offered_qos_profiles]
        schema_id = self._schema_ids.get(schema.type_name)
        if schema_id is None:
            schema_id = self._guard(lambda: self._mcap.register_schema(
                name=schema.type_name, encoding=schema.encoding,
                data=schema.text.encode('utf-8')))
            self._schema_ids[schema.type_name] = schema_id
        metadata = {'offered_qos_profiles': dump_qos_profiles(profiles)}
        if schema.type_hash:
            metadata['topic_type_hash'] = schema.type_hash
        channel_id = self._guard(lambda: self._mcap.register_channel(
            topic=topic, message_encoding='cdr', schema_id=schema_id, metadata=metadata))
        self._topics[topic] = _Topic(topic, schema, profiles, channel_id)

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Store one serialized (CDR) message exactly as given; log_time is the receive time."""
        entry = self._topics.get(topic)
        if entry is None:
            raise BagWriteError(f'topic {topic} was not added before writing')
        self._guard(lambda: self._mcap.add_message(
            channel_id=entry.channel_id, log_time=log_time_ns, data=data,
            publish_time=log_time_ns if publish_time_ns is None else publish_time_ns))
        entry.message_count += 1
        self.message_count += 1
        if self.start_time_ns is None or log_time_ns < self.start_time_ns:
            self.start_time_ns = log_time_ns
        if self.end_time_ns is None or log_time_ns > self.end_time_ns:
            self.end_time_ns = log_time_ns
        self.flush_if_due()

    def flush_if_due(self) -> None:
        """Flush when the last flush is older than flush_interval_s (call it from a timer too)."""
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Finish the current chunk and push it to the OS, so a hard kill cannot lose it."""
        self._guard(self._mcap.flush)
        if self.fsync:
            self._guard(lambda: os.fsync(self._stream.fileno()))
        self._last_flush = time.monotonic()
        self.messages_flushed = self.message_count

    # -- closing ---------------------------------------------------------------------------

    def metadata(self) -> dict[str, Any]:
        """The `rosbag2_bagfile_information` mapping (v9, every key jazzy requires)."""
        start = self.start_time_ns or 0
        duration = (self.end_time_ns - start) if self.end_time_ns is not None else 0
        return {
            'version': METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': self.message_count,
            'topics_with_message_count': [
                {
                    'topic_metadata': {
                        'name': t.name,
                        'type': t.schema.type_name,
                        'serialization_format': 'cdr',
                        'offered_qos_profiles': t.qos_profiles,
                        'type_description_hash': t.schema.type_hash,
                    },
                    'message_count': t.message_count,
                }
                for t in self._topics.values()
            ],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [self.mcap_path.name],
            'files': [{
                'path': self.mcap_path.name,
                'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': duration},
                'message_count': self.message_count,
            }],
            'custom_data': None,
            'ros_distro': self.ros_distro,
        }

    def close(self) -> None:
        """Write the summary (statistics, indexes) and metadata.yaml; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        info = self.metadata()
        info_text = yaml.safe_dump(info, default_flow_style=False, sort_keys=False)
        try:
            self._guard(lambda: self._mcap.add_metadata(
                'rosbag2', {'serialized_metadata': info_text}))
            self._guard(self._mcap.finish)
            self._guard(self._stream.flush)
            if self.fsync:
                self._guard(lambda: os.fsync(self._stream.fileno()))
        finally:
            try:
                self._stream.close()
            except OSError:
                pass  # already reported by _guard; the data section stays recoverable
        text = metadata_yaml_text(info)
        temporary = self.metadata_path.with_suffix('.yaml.tmp')
        try:
            temporary.write_text(text, encoding='utf-8')
            temporary.replace(self.metadata_path)
        except OSError as exc:
            raise BagWriteError(
                f'cannot write {self.metadata_path}: {exc.strerror or exc}') from exc

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _guard(self, action):
        """Run a write action; turn OS errors (ENOSPC, EIO, ...) into one BagWriteError."""
        if self._failed is not None:
            raise self._failed
        try:
            return action()
        except OSError as exc:
            self._failed = BagWriteError(
                f'writing bag {self.mcap_path} failed: {exc.strerror or exc}')
            self._failed.__cause__ = exc
            raise self._failed from exc


def metadata_yaml_text(info: Mapping[str, Any]) -> str:
    """metadata.yaml text for a `rosbag2_bagfile_information` mapping."""
    stream = io.StringIO()
    yaml.safe_dump({'rosbag2_bagfile_information': dict(info)}, stream,
                   default_flow_style=False, sort_keys=False)
    return stream.getvalue()
