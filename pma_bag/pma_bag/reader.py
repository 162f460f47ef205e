"""BagReader: raw CDR messages of a rosbag2 MCAP bag, in log-time order, without decoding.

The MCAP records are parsed here with `struct` rather than through mcap's reader, for two
reasons measured in bench/bench_bag.py: raw iteration is several times faster than mcap's own
non-decoding readers (and about twice rosbags'), and a file cut short by a crash is read up
to its last complete record, including the complete messages of an uncompressed chunk that
was cut in the middle, where mcap's stream reader drops the whole chunk. A split bag (a
directory of `<bag>_<n>.mcap`) reads as one. `check()` validates the CRCs the writer stored.
Layout reference: https://mcap.dev/spec (opcodes below).
"""

from __future__ import annotations

import heapq
import itertools
import mmap
import os
import re
import struct
import warnings
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Any, NamedTuple

import yaml

from pma_bag.errors import BagError
from pma_bag.schemas import MessageSchema
from pma_common.commands import run_command

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL = 0x01, 0x02, 0x03, 0x04
OP_MESSAGE, OP_CHUNK = 0x05, 0x06
OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA = 0x08, 0x0B, 0x0C
OP_METADATA_INDEX, OP_DATA_END = 0x0D, 0x0F
_U16 = struct.Struct('<H')
_U32 = struct.Struct('<I')
_U64 = struct.Struct('<Q')
_RECORD_HEAD = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel_id, sequence, log_time, publish_time
_CHUNK_HEAD = struct.Struct('<QQQI')  # start, end, uncompressed_size, uncompressed_crc
_FOOTER_SIZE = 1 + 8 + 20
_STATISTICS_HEAD = struct.Struct('<QHIIIIQQ')
_SPLIT_FILE = re.compile(r'_(\d+)\.mcap$')


class TruncatedBagWarning(UserWarning):
    """The file has no summary (the writer did not close it); read up to the damage."""


class BagMessage(NamedTuple):
    """One stored message: the CDR bytes exactly as recorded."""

    topic: str
    type_name: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


@dataclass
class TopicInfo:
    """What a bag holds for one topic."""

    name: str
    type_name: str
    message_count: int
    offered_qos_profiles: list[dict[str, Any]]
    schema: MessageSchema
    serialization_format: str = 'cdr'


@dataclass
class _Channel:
    id: int
    topic: str
    encoding: str
    schema_id: int
    metadata: dict[str, str]


@dataclass
class CrcReport:
    """What `BagReader.check()` found in one file: counts, and a line per problem."""

    path: Path
    chunks_checked: int = 0
    chunks_without_crc: int = 0
    data_section: str = 'absent'    # 'ok', 'absent' (writer stored 0) or 'missing' (cut short)
    summary: str = 'absent'         # the same for the summary section
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class _Segment:
    """A run of messages in file order: one chunk (maybe cut short) or one bare message."""

    start_ns: int
    end_ns: int
    offset: int
    end: int
    kind: int


def _string(buf, pos: int) -> tuple[str, int]:
    (size,) = _U32.unpack_from(buf, pos)
    pos += 4
    return bytes(buf[pos:pos + size]).decode('utf-8', errors='replace'), pos + size


def _string_map(buf, pos: int) -> tuple[dict[str, str], int]:
    (size,) = _U32.unpack_from(buf, pos)
    pos += 4
    end = pos + size
    result = {}
    while pos < end:
        key, pos = _string(buf, pos)
        value, pos = _string(buf, pos)
        result[key] = value
    return result, end


def parse_qos_profiles(text: str) -> list[dict[str, Any]]:
    """The channel's offered_qos_profiles YAML string as a list of dicts ([] if empty/bad)."""
    if not text:
        return []
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError:
        return []
    return loaded if isinstance(loaded, list) else []


class _McapFile:
    """One .mcap file mapped in memory, with its schemas, channels and damage report."""

    def __init__(self, path: Path):
        self.path = path
        try:
            size = path.stat().st_size
        except OSError as exc:
            raise BagError(f'cannot open {path}: {exc.strerror or exc}') from exc
        if size == 0:
            raise BagError(f'{path} is empty (0 bytes): the recorder wrote nothing')
        try:
            with open(path, 'rb') as stream:
                self.buf = mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ)
        except OSError as exc:
            raise BagError(f'cannot open {path}: {exc.strerror or exc}') from exc
        if self.buf[:8] != MAGIC:
            raise BagError(f'{path} is not an MCAP file (bad magic bytes)')
        self.schemas: dict[int, MessageSchema] = {}
        self.channels: dict[int, _Channel] = {}
        self.counts: dict[int, int] | None = None
        self.time_range_ns: tuple[int, int] | None = None
        self.truncated = False
        self.damage = ''
        self.metadata_records: dict[str, dict[str, str]] = {}   # name -> last record's map
        self.compressions: set[str] = set()                      # chunk compressions seen
        try:
            self._parse()
        except (struct.error, IndexError) as exc:
            # A record cut short where its own length fields promised more: a damaged file
            # gets the same one-line answer as any other unreadable bag, not a traceback.
            raise BagError(f'{path} is damaged ({exc}); if it was cut short by a crash, '
                           f'try: {run_command("pma_bag", "recover", path)}') from None

    def _parse(self) -> None:
        path = self.path
        pos = 8
        if len(self.buf) < pos + 9 or self.buf[pos] != OP_HEADER:
            raise BagError(f'{path} is not a complete MCAP file (no header record)')
        (length,) = _U64.unpack_from(self.buf, pos + 1)
        self.profile, _ = _string(self.buf, pos + 9)
        if self.profile != 'ros2':
            raise BagError(f'{path} is not a rosbag2 bag: MCAP profile {self.profile!r}, '
                           'expected "ros2"')
        self.data_start = pos + 9 + length
        if not self._read_summary():
            self.truncated = True
            self._scan_everything()

    # -- summary ----------------------------------------------------------------------------

    def _read_summary(self) -> bool:
        """Load schemas, channels and counts from the summary; False if the file has none."""
        buf = self.buf
        size = len(buf)
        if size < 8 + _FOOTER_SIZE + 8 or buf[size - 8:] != MAGIC:
            return False
        footer = size - 8 - _FOOTER_SIZE
        if buf[footer] != OP_FOOTER:
            return False
        (summary_start,) = _U64.unpack_from(buf, footer + 9)
        if summary_start == 0 or summary_start >= footer:
            return False
        statistics = None
        for opcode, start, _ in _records(buf, summary_start, footer):
            if opcode == OP_SCHEMA:
                self._add_schema(start)
            elif opcode == OP_CHANNEL:
                self._add_channel(start)
            elif opcode == OP_STATISTICS:
                statistics = start
            elif opcode == OP_CHUNK_INDEX:
                (map_size,) = _U32.unpack_from(buf, start + 32)
                compression, _ = _string(buf, start + 32 + 4 + map_size + 8)
                self.compressions.add(compression)
            elif opcode == OP_METADATA_INDEX:
                offset, _ = struct.unpack_from('<QQ', buf, start)
                if buf[offset] == OP_METADATA:
                    self._add_metadata(offset + 9)
        if statistics is None:
            return False
        fixed = _STATISTICS_HEAD.unpack_from(buf, statistics)
        pos = statistics + _STATISTICS_HEAD.size
        (map_size,) = _U32.unpack_from(buf, pos)
        counts = {}
        for entry in range(pos + 4, pos + 4 + map_size, 10):
            (channel_id,) = _U16.unpack_from(buf, entry)
            (count,) = _U64.unpack_from(buf, entry + 2)
            counts[channel_id] = count
        self.counts = counts
        self.time_range_ns = (fixed[6], fixed[7]) if fixed[0] else None
        return True

    def _add_metadata(self, pos: int) -> None:
        name, pos = _string(self.buf, pos)
        self.metadata_records[name], _ = _string_map(self.buf, pos)

    def _add_schema(self, pos: int) -> None:
        (schema_id,) = _U16.unpack_from(self.buf, pos)
        name, pos = _string(self.buf, pos + 2)
        encoding, pos = _string(self.buf, pos)
        (size,) = _U32.unpack_from(self.buf, pos)
        text = bytes(self.buf[pos + 4:pos + 4 + size]).decode('utf-8', errors='replace')
        self.schemas[schema_id] = MessageSchema(name, encoding, text, '')

    def _add_channel(self, pos: int) -> None:
        channel_id, schema_id = struct.unpack_from('<HH', self.buf, pos)
        topic, pos = _string(self.buf, pos + 4)
        encoding, pos = _string(self.buf, pos)
        metadata, _ = _string_map(self.buf, pos)
        if encoding != 'cdr':
            raise BagError(f'{self.path}: topic {topic} has message encoding {encoding!r}, '
                           'not "cdr": not a ROS 2 recording')
        self.channels[channel_id] = _Channel(channel_id, topic, encoding, schema_id, metadata)

    # -- data section -----------------------------------------------------------------------

    def segments(self) -> list[_Segment]:
        """Chunks and bare messages of the data section in file order, up to any damage."""
        buf = self.buf
        found = []
        for opcode, start, end in _records(buf, self.data_start, len(buf), self._note_damage):
            if opcode == OP_CHUNK:
                first, last = struct.unpack_from('<QQ', buf, start)
                found.append(_Segment(first, last, start, end, OP_CHUNK))
            elif opcode == OP_MESSAGE:
                (log_time,) = _U64.unpack_from(buf, start + 6)
                found.append(_Segment(log_time, log_time, start, end, OP_MESSAGE))
            elif opcode in (OP_SCHEMA, OP_CHANNEL):
                (self._add_schema if opcode == OP_SCHEMA else self._add_channel)(start)
            elif opcode == OP_METADATA:
                self._add_metadata(start)
            elif opcode == OP_DATA_END:
                break
        if self._partial_chunk is not None:
            found.append(self._partial_chunk)
        return found

    _partial_chunk: _Segment | None = None

    def _note_damage(self, pos: int, opcode: int, end: int) -> None:
        """A record runs past the end of the file: keep an uncompressed chunk's complete part."""
        self.truncated = True
        self.damage = f'record at byte {pos} is cut off ({end - len(self.buf)} bytes missing)'
        start = pos + 9
        if opcode != OP_CHUNK or len(self.buf) < start + _CHUNK_HEAD.size + 4:
            return
        first, last, _, _ = _CHUNK_HEAD.unpack_from(self.buf, start)
        compression, _ = _string(self.buf, start + _CHUNK_HEAD.size)
        if compression == '':
            self._partial_chunk = _Segment(first, last, start, len(self.buf), OP_CHUNK)

    def segment_messages(self, segment: _Segment) -> list[tuple[int, int, int, bytes]]:
        """(log_time, channel_id, publish_time, data) of a segment, sorted by log_time."""
        buf = self.buf
        if segment.kind == OP_MESSAGE:
            channel_id, _, log_time, publish_time = _MESSAGE_HEAD.unpack_from(buf, segment.offset)
            return [(log_time, channel_id, publish_time,
                     buf[segment.offset + _MESSAGE_HEAD.size:segment.end])]
        records = self._chunk_records(segment)
        out = []
        append = out.append
        unpack_record = _RECORD_HEAD.unpack_from
        unpack_message = _MESSAGE_HEAD.unpack_from
        pos, end = 0, len(records)
        while pos + 9 <= end:
            opcode, length = unpack_record(records, pos)
            start = pos + 9
            pos = start + length
            if pos > end:
                break
            if opcode == OP_MESSAGE:
                channel_id, _, log_time, publish_time = unpack_message(records, start)
                append((log_time, channel_id, publish_time, records[start + 22:pos]))
            elif opcode == OP_SCHEMA:
                self._add_schema_from(records, start)
            elif opcode == OP_CHANNEL:
                self._add_channel_from(records, start)
        out.sort(key=itemgetter(0))
        return out

    def _chunk_records(self, segment: _Segment) -> bytes:
        """The records inside a chunk, decompressed (a cut chunk: as much as there is)."""
        buf = self.buf
        compression, pos = _string(buf, segment.offset + _CHUNK_HEAD.size)
        self.compressions.add(compression)
        (size,) = _U64.unpack_from(buf, pos)
        records = buf[pos + 8:min(pos + 8 + size, segment.end)]
        if compression:
            records = _decompress(compression, records, self.path)
        return records

    def check(self) -> CrcReport:
        """Validate every CRC the writer stored: chunks, data section and summary."""
        report = CrcReport(self.path)
        buf = self.buf
        data_end = None
        for segment in self.segments():
            if segment.kind != OP_CHUNK:
                continue
            (crc,) = _U32.unpack_from(buf, segment.offset + 24)
            if segment is self._partial_chunk:
                report.problems.append(f'chunk at byte {segment.offset - 9} is cut short')
            elif crc == 0:
                report.chunks_without_crc += 1
            else:
                report.chunks_checked += 1
                try:
                    actual = zlib.crc32(self._chunk_records(segment))
                except BagError as exc:
                    report.problems.append(str(exc))
                    continue
                if actual != crc:
                    report.problems.append(
                        f'chunk at byte {segment.offset - 9}: CRC {actual:08x}, stored {crc:08x}')
        for opcode, start, _ in _records(buf, self.data_start, len(buf)):
            if opcode == OP_DATA_END:
                data_end = start - 9
                break
        if data_end is None:
            report.data_section = report.summary = 'missing'
            report.problems.append('no end of data section: the file was not closed '
                                   f'({self.damage or "no summary"})')
            return report
        (stored,) = _U32.unpack_from(buf, data_end + 9)
        if stored:
            actual = zlib.crc32(buf[:data_end])
            report.data_section = 'ok' if actual == stored else 'mismatch'
            if actual != stored:
                report.problems.append(
                    f'data section CRC {actual:08x}, stored {stored:08x}')
        footer = len(buf) - 8 - _FOOTER_SIZE
        if self.truncated or buf[footer] != OP_FOOTER:
            report.summary = 'missing'
            return report
        summary_start, _, stored = struct.unpack_from('<QQI', buf, footer + 9)
        if stored:
            actual = zlib.crc32(buf[summary_start:footer + 9 + 16])
            report.summary = 'ok' if actual == stored else 'mismatch'
            if actual != stored:
                report.problems.append(f'summary CRC {actual:08x}, stored {stored:08x}')
        return report

    def _add_schema_from(self, records: bytes, pos: int) -> None:
        (schema_id,) = _U16.unpack_from(records, pos)
        if schema_id not in self.schemas:
            saved, self.buf = self.buf, records
            try:
                self._add_schema(pos)
            finally:
                self.buf = saved

    def _add_channel_from(self, records: bytes, pos: int) -> None:
        (channel_id,) = _U16.unpack_from(records, pos)
        if channel_id not in self.channels:
            saved, self.buf = self.buf, records
            try:
                self._add_channel(pos)
            finally:
                self.buf = saved

    def _scan_everything(self) -> None:
        """No summary: count messages per channel by reading every complete record."""
        counts: dict[int, int] = {}
        first = last = None
        for segment in self.segments():
            for log_time, channel_id, _, _ in self.segment_messages(segment):
                counts[channel_id] = counts.get(channel_id, 0) + 1
                first = log_time if first is None else min(first, log_time)
                last = log_time if last is None else max(last, log_time)
        self.counts = counts
        self.time_range_ns = None if first is None else (first, last)
        if not self.damage:
            self.damage = 'the file has no summary (the writer was not closed)'

    def messages(self, channel_ids: set[int] | None,
                 start_time_ns: int | None) -> Iterator[tuple[int, int, int, bytes]]:
        """(log_time, channel_id, publish_time, data) in log-time order."""
        segments = self.segments()
        in_order = all(b.start_ns >= a.end_ns for a, b in itertools.pairwise(segments))
        if in_order:
            batches: Iterable[list] = (self.segment_messages(s) for s in segments
                                       if start_time_ns is None or s.end_ns >= start_time_ns)
        else:
            merged = [m for s in segments for m in self.segment_messages(s)]
            merged.sort(key=itemgetter(0))
            batches = [merged]
        for batch in batches:
            for item in batch:
                if channel_ids is not None and item[1] not in channel_ids:
                    continue
                if start_time_ns is not None and item[0] < start_time_ns:
                    continue
                yield item


def _records(buf, pos: int, end: int, on_damage=None) -> Iterator[tuple[int, int, int]]:
    """(opcode, content start, content end) of each complete record in buf[pos:end]."""
    unpack = _RECORD_HEAD.unpack_from
    while pos + 9 <= end:
        opcode, length = unpack(buf, pos)
        record_end = pos + 9 + length
        if record_end > end:
            if on_damage is not None:
                on_damage(pos, opcode, record_end)
            return
        yield opcode, pos + 9, record_end
        pos = record_end
    if pos < end and on_damage is not None:
        on_damage(pos, -1, pos + 9)


def _decompress(compression: str, data: bytes, path: Path) -> bytes:
    try:
        if compression == 'zstd':
            import zstandard
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        if compression == 'lz4':
            import lz4.frame
            return lz4.frame.decompress(data)
    except Exception as exc:  # any codec failure means a damaged chunk
        raise BagError(f'{path}: cannot decompress a {compression} chunk: {exc}') from exc
    raise BagError(f'{path}: unsupported chunk compression {compression!r}')


class BagReader:
    """Open a bag directory (metadata.yaml + *.mcap) or a bare .mcap file for reading.

    Raises BagError with a one-line reason for a missing, empty or foreign bag. A file
    without summary is read up to its last complete record, with a TruncatedBagWarning.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.warnings = []
        self.bag_info: dict[str, Any] | None = None   # metadata.yaml, when the bag has one
        self.files = self._open_files(self._mcap_paths())
        for mcap_file in self.files:
            if mcap_file.truncated:
                message = (f'{mcap_file.path} is truncated ({mcap_file.damage}); reading the '
                           'complete records before the damage')
                self.warnings.append(message)
                warnings.warn(message, TruncatedBagWarning, stacklevel=2)
        self._topics = self._collect_topics()

    @classmethod
    def quietly(cls, path: str | os.PathLike) -> BagReader:
        """A reader for a tool that reports the damage itself (`damage`), so without the
        TruncatedBagWarning."""
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', TruncatedBagWarning)
            return cls(path)

    @property
    def damage(self) -> str:
        """'' for a whole bag; else each truncated file's name and what is damaged."""
        return '; '.join(f'{f.path.name}: {f.damage}' for f in self.files if f.truncated)

    def _open_files(self, paths: list[Path]) -> list[_McapFile]:
        files = []
        for index, path in enumerate(paths):
            try:
                files.append(_McapFile(path))
            except BagError as exc:
                # A recorder killed just after a split leaves an empty or header-less last
                # file: the files before it are whole, so that one is skipped, with a note.
                if index == 0 or index < len(paths) - 1 or self.bag_info is not None:
                    raise
                message = f'{path} skipped: {exc}'
                self.warnings.append(message)
                warnings.warn(message, TruncatedBagWarning, stacklevel=3)
        return files

    def _mcap_paths(self) -> list[Path]:
        if not self.path.exists():
            raise BagError(f'bag {self.path} does not exist')
        if self.path.is_file():
            return [self.path]
        metadata = self.path / 'metadata.yaml'
        if metadata.is_file():
            try:
                info = yaml.safe_load(metadata.read_text(encoding='utf-8'))
                info = info['rosbag2_bagfile_information']
                storage = info.get('storage_identifier', 'mcap')
                names = list(info['relative_file_paths'])
            except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
                raise BagError(f'{metadata} is not a rosbag2 metadata file: {exc}') from exc
            self.bag_info = info
            if storage != 'mcap':
                raise BagError(f'bag {self.path} uses storage {storage!r}; only mcap is read')
            paths = [self.path / Path(name).name for name in names]
            missing = [str(p) for p in paths if not p.is_file()]
            if missing:
                raise BagError(f'bag {self.path}: files listed in metadata.yaml are missing: '
                               + ', '.join(missing))
            return paths
        # No metadata.yaml (the recorder was killed): the files in split order, as
        # `ros2 bag reindex` takes them (<bag>_2.mcap before <bag>_10.mcap).
        def split_index(path: Path) -> tuple[int, str]:
            match = _SPLIT_FILE.search(path.name)
            return (int(match.group(1)) if match else -1, path.name)

        paths = sorted(self.path.glob('*.mcap'), key=split_index)
        if not paths:
            raise BagError(f'bag directory {self.path} holds no .mcap file')
        return paths

    def _collect_topics(self) -> dict[str, TopicInfo]:
        topics: dict[str, TopicInfo] = {}
        for mcap_file in self.files:
            for channel in mcap_file.channels.values():
                count = (mcap_file.counts or {}).get(channel.id, 0)
                known = topics.get(channel.topic)
                if known is not None:
                    known.message_count += count
                    continue
                schema = mcap_file.schemas.get(channel.schema_id)
                if schema is None:
                    raise BagError(f'{mcap_file.path}: topic {channel.topic} has no schema')
                schema = MessageSchema(schema.type_name, schema.encoding, schema.text,
                                       channel.metadata.get('topic_type_hash', ''))
                topics[channel.topic] = TopicInfo(
                    channel.topic, schema.type_name, count,
                    parse_qos_profiles(channel.metadata.get('offered_qos_profiles', '')), schema)
        return topics

    @property
    def truncated(self) -> bool:
        return any(f.truncated for f in self.files)

    @property
    def custom_data(self) -> dict[str, str]:
        """metadata.yaml `custom_data`, else the newest rosbag2 Metadata record's (crashed bag)."""
        if self.bag_info is not None:
            stored = self.bag_info.get('custom_data') or {}
            return {str(k): str(v) for k, v in stored.items()} if isinstance(stored, dict) else {}
        for mcap_file in reversed(self.files):
            text = mcap_file.metadata_records.get('rosbag2', {}).get('serialized_metadata')
            if not text:
                continue
            try:
                stored = (yaml.safe_load(text) or {}).get('custom_data') or {}
            except (yaml.YAMLError, AttributeError):
                continue
            if isinstance(stored, dict):
                return {str(k): str(v) for k, v in stored.items()}
        return {}

    @property
    def compressions(self) -> set[str]:
        """Chunk compressions used ('' = none); known after opening for closed files."""
        return set().union(*(f.compressions for f in self.files))

    def check(self) -> list[CrcReport]:
        """Validate the stored CRCs of every file (what mcap's readers do with validate_crcs)."""
        return [f.check() for f in self.files]

    @property
    def topics(self) -> dict[str, TopicInfo]:
        """Topic name -> TopicInfo, in the order the channels were first written."""
        return dict(self._topics)

    @property
    def message_count(self) -> int:
        return sum(t.message_count for t in self._topics.values())

    def time_range_ns(self) -> tuple[int, int] | None:
        """(first, last) log_time, None for a bag without messages."""
        ranges = [f.time_range_ns for f in self.files if f.time_range_ns is not None]
        if not ranges:
            return None
        return min(r[0] for r in ranges), max(r[1] for r in ranges)

    def messages(self, topics: Iterable[str] | None = None,
                 start_time_ns: int | None = None) -> Iterator[BagMessage]:
        """Messages (of the given topics) in log-time order, from start_time_ns on."""
        wanted = None if topics is None else set(topics)
        streams = []
        for mcap_file in self.files:
            channels = {cid: (c.topic, mcap_file.schemas[c.schema_id].type_name)
                        for cid, c in mcap_file.channels.items()}
            ids = None if wanted is None else {
                cid for cid, (topic, _) in channels.items() if topic in wanted}
            streams.append(self._file_messages(mcap_file, channels, ids, start_time_ns))
        if len(streams) == 1:
            return streams[0]
        return heapq.merge(*streams, key=lambda m: m.log_time_ns)

    @staticmethod
    def _file_messages(mcap_file: _McapFile, channels, ids, start_time_ns):
        for log_time, channel_id, publish_time, data in mcap_file.messages(ids, start_time_ns):
            topic_type = channels.get(channel_id)
            if topic_type is None:
                channel = mcap_file.channels.get(channel_id)  # defined inside a later chunk
                if channel is None:
                    continue
                topic_type = (channel.topic, mcap_file.schemas[channel.schema_id].type_name)
                channels[channel_id] = topic_type
            yield BagMessage(topic_type[0], topic_type[1], data, log_time, publish_time)

    def __iter__(self) -> Iterator[BagMessage]:
        return self.messages()

    def close(self) -> None:
        for mcap_file in self.files:
            mcap_file.buf.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
