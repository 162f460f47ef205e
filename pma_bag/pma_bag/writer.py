"""BagWriter: a rosbag2 (jazzy, metadata v9) bag directory of one or more MCAP files.

Layout `<bag>/<bag>_0.mcap` [`<bag>_1.mcap` ...] + `<bag>/metadata.yaml`, profile `ros2`,
one `ros2msg` schema per type, `cdr` channels carrying `offered_qos_profiles` and
`topic_type_hash`, chunks with message indexes and CRCs, a Statistics record and a `rosbag2`
Metadata record: what `ros2 bag record -s mcap` writes (docs/bags.md).

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


COMPRESSIONS = {'': CompressionType.NONE, 'none': CompressionType.NONE,
                'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4}


@dataclass
class _Topic:
    name: str
    schema: MessageSchema
    qos_profiles: list[dict[str, Any]]
    channel_metadata: dict[str, str]
    message_count: int = 0


@dataclass
class _File:
    """One `<bag>_<n>.mcap` of the bag, open or finished."""

    path: Path
    stream: Any = None
    mcap: Writer | None = None
    channel_ids: dict[str, int] = field(default_factory=dict)
    schema_ids: dict[str, int] = field(default_factory=dict)
    message_count: int = 0
    start_time_ns: int | None = None
    end_time_ns: int | None = None
    _texts: tuple[dict[str, Any], str, str] | None = None   # entry(), its YAML, the path's

    def entry_texts(self) -> tuple[str, str]:
        """YAML of this file's item in `files` and in `relative_file_paths`, dumped again only
        when the entry changed (a finished file's, never)."""
        entry = self.entry()
        if self._texts is None or self._texts[0] != entry:
            self._texts = (entry, _yaml_text([entry]), _yaml_text([entry['path']]))
        return self._texts[1], self._texts[2]

    def entry(self) -> dict[str, Any]:
        start = self.start_time_ns or 0
        end = self.end_time_ns if self.end_time_ns is not None else start
        return {'path': self.path.name,
                'starting_time': {'nanoseconds_since_epoch': start},
                'duration': {'nanoseconds': end - start},
                'message_count': self.message_count}


def check_output_directory(bag_dir: Path) -> None:
    """Refuse a path that is a file or a directory holding anything (rosbag2 refuses it too).

    Writing into a directory with other files would mix a bag with unrelated data, and
    `reindex`/`recover` pick up every `*_N.mcap` there.
    """
    if bag_dir.is_dir():
        contents = sorted(p.name for p in bag_dir.iterdir())
        if contents:
            what = ('a bag' if 'metadata.yaml' in contents
                    or any(n.endswith('.mcap') for n in contents) else 'other files')
            shown = ', '.join(contents[:3]) + (', ...' if len(contents) > 3 else '')
            raise BagWriteError(f'{bag_dir} already exists and holds {what} ({shown}); '
                                'choose a new output path')
    elif bag_dir.exists():
        raise BagWriteError(f'cannot create bag {bag_dir}: it exists and is not a directory')


class BagWriter:
    """Write raw CDR messages into a new rosbag2-compatible MCAP bag directory.

    Split like `ros2 bag record --max-bag-size/--max-bag-duration`: a new `<bag>_<n>.mcap`
    starts before a message when the current file holds max_bag_size bytes or more on disk
    (the chunk still in memory is not counted, as in rosbag2, so a file can end up to one
    chunk larger; the recorder flushes a chunk every 0.75 s) or when the message is more than
    max_bag_duration_s after the file's first one; every
    file is finished (summary, indexes) when the next one starts, so only the last one can
    be cut short by a crash. compression is the MCAP chunk compression ('zstd', 'lz4' or ''):
    what rosbag2's mcap storage config sets, which every MCAP reader decompresses itself
    (metadata.yaml compression_format stays '', as rosbag2 writes it for chunk compression).

    Not thread-safe: call it from one thread at a time.
    """

    def __init__(self, bag_dir: str | os.PathLike, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 flush_interval_s: float = 1.0, fsync: bool = False, ros_distro: str | None = None,
                 compression: str = '', max_bag_size: int = 0, max_bag_duration_s: float = 0.0,
                 custom_data: Mapping[str, str] | None = None):
        self.bag_dir = Path(bag_dir)
        self.metadata_path = self.bag_dir / 'metadata.yaml'
        self.flush_interval_s = flush_interval_s
        self.fsync = fsync
        self.ros_distro = ros_distro or os.environ.get('ROS_DISTRO', 'jazzy')
        if compression not in COMPRESSIONS:
            raise BagWriteError(f'unknown chunk compression {compression!r} '
                                '(use zstd, lz4 or none)')
        if max_bag_size < 0 or max_bag_duration_s < 0:
            raise BagWriteError('max_bag_size and max_bag_duration_s must be >= 0 (0 = no split)')
        self.compression = '' if compression == 'none' else compression
        self.chunk_size = chunk_size
        self.max_bag_size = int(max_bag_size)
        self.max_bag_duration_ns = int(max_bag_duration_s * _NS_PER_S)
        self.custom_data: dict[str, str] = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.message_count = 0
        self.messages_flushed = 0  # message_count at the last flush: what a crash keeps
        self.start_time_ns: int | None = None
        self.end_time_ns: int | None = None
        self._topics: dict[str, _Topic] = {}
        self._files: list[_File] = []
        self._failed: BagWriteError | None = None
        self._closed = False
        self._metadata_written = ''   # custom_data as last stored in the file
        check_output_directory(self.bag_dir)
        try:
            self.bag_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BagWriteError(
                f'cannot create bag {self.bag_dir}: {exc.strerror or exc}') from exc
        self._open_file()
        self._last_flush = time.monotonic()

    # -- files -----------------------------------------------------------------------------

    @property
    def mcap_path(self) -> Path:
        """The file being written now."""
        return self._files[-1].path

    @property
    def file_paths(self) -> list[Path]:
        return [f.path for f in self._files]

    def _open_file(self) -> None:
        path = self.bag_dir / f'{self.bag_dir.name}_{len(self._files)}.mcap'
        try:
            stream = open(path, 'xb')  # closed in _finish_file
        except OSError as exc:
            raise BagWriteError(
                f'cannot create bag {self.bag_dir}: {exc.strerror or exc}') from exc
        current = _File(path, stream)
        self._files.append(current)
        current.mcap = Writer(stream, chunk_size=self.chunk_size,
                              compression=COMPRESSIONS[self.compression],
                              index_types=IndexType.ALL, enable_data_crcs=True)
        self._guard(lambda: current.mcap.start(profile='ros2', library=LIBRARY))
        for topic in self._topics.values():
            self._register(current, topic)
        # Written at open too (as rosbag2 does), so a bag cut short by a crash still says
        # what the experiment was; rewritten whenever custom_data changes and at close.
        self._write_metadata_record(force=True)
        self._guard(stream.flush)  # a header on disk at once: a crash leaves a readable file

    def _register(self, target: _File, topic: _Topic) -> None:
        schema = topic.schema
        schema_id = target.schema_ids.get(schema.type_name)
        if schema_id is None:
            schema_id = self._guard(lambda: target.mcap.register_schema(
                name=schema.type_name, encoding=schema.encoding,
                data=schema.text.encode('utf-8')))
            target.schema_ids[schema.type_name] = schema_id
        target.channel_ids[topic.name] = self._guard(lambda: target.mcap.register_channel(
            topic=topic.name, message_encoding='cdr', schema_id=schema_id,
            metadata=topic.channel_metadata))

    def _finish_file(self, current: _File) -> None:
        """Summary and indexes of one file, then close it (kept closed on any error)."""
        try:
            self._write_metadata_record(force=True)
            self._guard(current.mcap.finish)
            self._guard(current.stream.flush)
            if self.fsync:
                self._guard(lambda: os.fsync(current.stream.fileno()))
        finally:
            try:
                current.stream.close()
            except OSError:
                pass  # already reported by _guard; the data section stays recoverable

    def split(self) -> bool:
        """Finish the current file and continue in `<bag>_<n+1>.mcap` (False: it is empty)."""
        self._check_open()
        current = self._files[-1]
        if current.message_count == 0:
            return False
        self._finish_file(current)
        self._open_file()
        self._last_flush = time.monotonic()
        self.messages_flushed = self.message_count
        return True

    def _split_due(self, log_time_ns: int) -> bool:
        current = self._files[-1]
        if current.message_count == 0:
            return False
        if self.max_bag_duration_ns and current.start_time_ns is not None \
                and log_time_ns - current.start_time_ns > self.max_bag_duration_ns:
            return True
        return bool(self.max_bag_size) and current.stream.tell() >= self.max_bag_size

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
        self._check_open()
        if topic in self._topics:
            raise BagWriteError(f'topic {topic} was already added')
        schema = schema or message_schema(type_name)
        profiles = [qos_profile_dict(p) for p in offered_qos_profiles]
        metadata = {'offered_qos_profiles': dump_qos_profiles(profiles)}
        if schema.type_hash:
            metadata['topic_type_hash'] = schema.type_hash
        entry = _Topic(topic, schema, profiles, metadata)
        self._register(self._files[-1], entry)
        self._topics[topic] = entry

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Store one serialized (CDR) message exactly as given; log_time is the receive time."""
        entry = self._topics.get(topic)
        if entry is None:
            raise BagWriteError(f'topic {topic} was not added before writing')
        self._check_open()
        if (self.max_bag_size or self.max_bag_duration_ns) and self._split_due(log_time_ns):
            self.split()
        current = self._files[-1]
        self._guard(lambda: current.mcap.add_message(
            channel_id=current.channel_ids[topic], log_time=log_time_ns, data=data,
            publish_time=log_time_ns if publish_time_ns is None else publish_time_ns))
        entry.message_count += 1
        self.message_count += 1
        current.message_count += 1
        if current.start_time_ns is None or log_time_ns < current.start_time_ns:
            current.start_time_ns = log_time_ns
        if current.end_time_ns is None or log_time_ns > current.end_time_ns:
            current.end_time_ns = log_time_ns
        if self.start_time_ns is None or log_time_ns < self.start_time_ns:
            self.start_time_ns = log_time_ns
        if self.end_time_ns is None or log_time_ns > self.end_time_ns:
            self.end_time_ns = log_time_ns
        self.flush_if_due()

    def update_custom_data(self, values: Mapping[str, str]) -> None:
        """Add or change `custom_data` entries; stored in the file at the next flush/close."""
        self.custom_data.update({str(k): str(v) for k, v in values.items()})

    def flush_if_due(self) -> None:
        """Flush when the last flush is older than flush_interval_s (call it from a timer too)."""
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Finish the current chunk and push it to the OS, so a hard kill cannot lose it."""
        self._check_open()
        current = self._files[-1]
        self._write_metadata_record()
        self._guard(current.mcap.flush)
        if self.fsync:
            self._guard(lambda: os.fsync(current.stream.fileno()))
        self._last_flush = time.monotonic()
        self.messages_flushed = self.message_count

    def _write_metadata_record(self, force: bool = False) -> None:
        """The rosbag2 Metadata record, when custom_data changed since it was last stored."""
        key = repr(sorted(self.custom_data.items()))
        if not force and key == self._metadata_written:
            return
        text = self._metadata_text(self.metadata())
        current = self._files[-1]
        self._guard(lambda: current.mcap.add_metadata('rosbag2', {'serialized_metadata': text}))
        self._metadata_written = key

    def _metadata_text(self, info: Mapping[str, Any]) -> str:
        """yaml.safe_dump(info) as it reads, with each file's items kept from the last time.

        The record lists every file and is written twice per split (into the finished file
        and into the new one): dumped whole, a split of a 300-file bag took 110 ms, and a burst
        of 300 ~/split_bagfile requests stalled a recorder of 200 Hz for tens of seconds.
        """
        files, paths = zip(*(f.entry_texts() for f in self._files), strict=True)
        kept = {'files': files, 'relative_file_paths': paths}
        return ''.join(f'{key}:\n' + ''.join(kept[key]) if key in kept
                       else _yaml_text({key: value}) for key, value in info.items())

    def _check_open(self) -> None:
        if self._failed is not None:
            raise self._failed
        if self._closed:
            raise BagWriteError(f'bag {self.bag_dir} is already closed')

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
            'relative_file_paths': [f.path.name for f in self._files],
            'files': [f.entry() for f in self._files],
            'custom_data': dict(self.custom_data) or None,
            'ros_distro': self.ros_distro,
        }

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def failed(self) -> BagWriteError | None:
        """The write error that stopped this bag, if any."""
        return self._failed

    def close(self) -> None:
        """Finish the last file and write metadata.yaml; safe to call twice.

        After a write error (disk full) no metadata.yaml is written: it would describe data
        that is not in the files. The files stay as they are for `recover`.
        """
        if self._closed:
            return
        self._closed = True
        if self._failed is not None:
            self._close_quietly()
            raise self._failed
        self._finish_file(self._files[-1])
        text = metadata_yaml_text(self.metadata())
        temporary = self.metadata_path.with_suffix('.yaml.tmp')
        try:
            temporary.write_text(text, encoding='utf-8')
            temporary.replace(self.metadata_path)
        except OSError as exc:
            temporary.unlink(missing_ok=True)
            raise BagWriteError(
                f'cannot write {self.metadata_path}: {exc.strerror or exc}') from exc

    def _close_quietly(self) -> None:
        try:
            self._files[-1].stream.close()
        except OSError:
            pass  # the buffered rest cannot reach a full disk; the error is reported already

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


def _yaml_text(value: Any) -> str:
    return yaml.safe_dump(value, default_flow_style=False, sort_keys=False)


def metadata_yaml_text(info: Mapping[str, Any]) -> str:
    """metadata.yaml text for a `rosbag2_bagfile_information` mapping."""
    stream = io.StringIO()
    yaml.safe_dump({'rosbag2_bagfile_information': dict(info)}, stream,
                   default_flow_style=False, sort_keys=False)
    return stream.getvalue()
