"""(pressure, length, time) samples for the offline refit, from a bag or a CSV, split by branch.

Three inputs:
- a rosbag2 MCAP bag (directory or bare .mcap) with pma_interfaces/msg/PmaState on pma/state;
  sample time is header.stamp (the driver's estimate of acquisition time), not the log time;
- a sample log CSV with the columns time_s, gauge_pressure_pa, length_m and optionally
  gauge_setpoint_pa (SI, one row per sample, in time order);
- a branch table CSV like the paper's Table 1: pressure_kpa, length_increasing_cm,
  length_decreasing_cm (one row per pressure level, already averaged).

Samples are split into increasing and decreasing with pma_model.detector, the same deadband
detector the online model uses. Holds of a staircase sweep can be reduced to their
steady-state means, which is how the paper's table was made.
"""

from __future__ import annotations

import copy
import csv
import io
import math
import struct
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pma_common import names
from pma_model import units
from pma_model.detector import BRANCH_INCREASING, DEFAULT_DEADBAND_PA, detect_branches
from pma_model.params import utf8_error_position

STATE_TOPIC = names.STATE
STATE_TYPE = 'pma_interfaces/msg/PmaState'
# What the Sweep action did, level by level (pma_interfaces/msg/SweepRecord): next to the
# state topic, in the same namespace.
SWEEP_RECORD_TOPIC = names.SWEEP_RECORD
SWEEP_RECORD_TYPE = 'pma_interfaces/msg/SweepRecord'
SAMPLE_LOG_COLUMNS = ('time_s', 'gauge_pressure_pa', 'length_m')
BRANCH_TABLE_COLUMNS = ('pressure_kpa', 'length_increasing_cm', 'length_decreasing_cm')
# A hold is a run whose setpoint (or, without one, pressure) stays within this band [Pa].
HOLD_TOLERANCE_PA = 2_000.0
# ... lasts at least this many samples, and its steady state is the mean of this last part.
MIN_HOLD_SAMPLES = 5
STEADY_FRACTION = 0.5


class SamplesError(ValueError):
    """The input cannot give fit data; the message is one line for the user."""


@dataclass
class Samples:
    """A time series in SI (NaN lengths already removed and counted)."""

    time_s: np.ndarray
    pressure_pa: np.ndarray
    length_m: np.ndarray
    setpoint_pa: np.ndarray | None = None
    dropped_nan: int = 0
    source: str = ''
    truncated: str = ''     # a bag cut short: what is damaged ('' = complete input)
    time_origin_s: float = 0.0   # the first sample's stamp: time_s counts from it
    # The sweep's records in the bag (pma_model.offline.checks.SweepLevelRecord, SweepStartRecord);
    # None: the input has no pma/sweep_record topic (a CSV, a bag recorded before it).
    sweep_levels: list | None = None
    sweep_start: object | None = None


@dataclass
class BranchData:
    """Fit data: one (pressure, length) set per branch, SI; `levels` counts pressure levels."""

    inc_pressure_pa: np.ndarray
    inc_length_m: np.ndarray
    dec_pressure_pa: np.ndarray
    dec_length_m: np.ndarray
    source: str = ''
    samples_used: int = 0
    dropped_nan: int = 0
    steady_state: bool = False
    truncated: str = ''     # as Samples.truncated

    @property
    def rest_length_m(self) -> float:
        """Length at the lowest increasing-branch pressure: the paper's fixed L0."""
        lowest = self.inc_pressure_pa <= self.inc_pressure_pa.min() + HOLD_TOLERANCE_PA
        return float(np.mean(self.inc_length_m[lowest]))

    def loop(self):
        """(pressure, length, rising) of both branches together."""
        return (np.concatenate([self.inc_pressure_pa, self.dec_pressure_pa]),
                np.concatenate([self.inc_length_m, self.dec_length_m]),
                np.concatenate([np.ones(self.inc_pressure_pa.size, bool),
                                np.zeros(self.dec_pressure_pa.size, bool)]))


# --- readers ------------------------------------------------------------------------------

def _progress_printer(total: int, label: str) -> Callable[[int], None]:
    """A stderr progress bar that appears only once the work has taken more than 1 s."""
    started = time.monotonic()
    shown = [False]

    def report(done: int) -> None:
        if time.monotonic() - started < 1.0 and not (shown[0] and done >= total):
            return
        shown[0] = True
        fraction = done / total if total else 1.0
        bar = '#' * int(30 * fraction)
        sys.stderr.write(f'\r{label} [{bar:<30}] {100 * fraction:5.1f} % ({done}/{total})')
        if done >= total:
            sys.stderr.write('\n')
        sys.stderr.flush()

    return report


def state_topic_in(topics: dict, topic: str = STATE_TOPIC) -> str:
    """The bag topic to read: `topic` if absolute, else the one PmaState topic named like it.

    A relative name matches in any namespace (a bag recorded with `__ns:=/left` holds
    /left/pma/state); two matches (two muscles in one bag) need an explicit choice.
    """
    if topic.startswith('/'):
        candidates = [name for name in topics if name == topic]
    else:
        candidates = [name for name in topics
                      if name == f'/{topic}' or name.endswith(f'/{topic}')]
        typed = [name for name in candidates if topics[name].type_name == STATE_TYPE]
        candidates = typed or candidates
    if not candidates:
        raise SamplesError(f'the bag has no {topic} topic (topics: '
                           f'{", ".join(sorted(topics)) or "none"})')
    if len(candidates) > 1:
        raise SamplesError(f'the bag has several {topic} topics ({", ".join(sorted(candidates))})'
                           f'; choose one with --topic')
    (name,) = candidates
    if topics[name].type_name != STATE_TYPE:
        raise SamplesError(f'{name} holds {topics[name].type_name}, not {STATE_TYPE}')
    return name


def read_bag(path, topic: str = STATE_TOPIC, progress: bool = True) -> Samples:
    """PmaState samples of a bag, by header.stamp; rows with NaN length are dropped.

    A bag its recorder did not close (a crash) is read up to the damage; `truncated` on
    the result says what is missing, for the caller to tell the user in its own words.
    """
    from pma_bag import BagError, BagReader
    from pma_bag.reader import TruncatedBagWarning
    from pma_interfaces.msg import PmaState

    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', TruncatedBagWarning)
            reader = BagReader(path)
    except BagError as error:
        raise SamplesError(str(error)) from None
    truncated = '; '.join(f'{f.path.name}: {f.damage}' for f in reader.files if f.truncated)
    with reader:
        try:
            state = state_topic_in(reader.topics, topic)
        except SamplesError as error:
            raise SamplesError(f'bag {path}: {error}') from None
        wanted = {state}
        records = sweep_record_topic(reader.topics, state)
        total = reader.topics[state].message_count
        report = _progress_printer(total, 'reading bag') if progress else None
        payloads, record_payloads = [], []
        try:
            for message in reader.messages(wanted | ({records} if records else set())):
                if message.topic != state:
                    record_payloads.append(message.data)
                    continue
                payloads.append(message.data)
                if report is not None and len(payloads) % 20_000 == 0:
                    report(min(len(payloads), total))
        except BagError as error:
            raise SamplesError(str(error)) from None
        if report is not None:
            report(total)
    stamp, pressure, length, setpoint = _decode_states(payloads, PmaState)
    samples = _finish(stamp, pressure, length, setpoint, str(path))
    samples.truncated = truncated
    if records:
        samples.sweep_levels, samples.sweep_start = _decode_sweep_records(record_payloads)
    return samples


def sweep_record_topic(topics: dict, state_topic: str) -> str | None:
    """The SweepRecord topic beside this state topic (same namespace), None without one."""
    namespace = state_topic[:-len(STATE_TOPIC)] if state_topic.endswith(STATE_TOPIC) else '/'
    name = namespace + SWEEP_RECORD_TOPIC
    found = topics.get(name)
    return name if found is not None and found.type_name == SWEEP_RECORD_TYPE else None


def _decode_sweep_records(payloads: list[bytes]):
    """(LEVEL records, the START record or None) of the bag's last sweep: a bag holds one
    sweep (the Sweep action records each to its own bag); with several, the last one's."""
    from rclpy.serialization import deserialize_message

    from pma_interfaces.msg import SweepRecord
    from pma_model.offline.checks import SweepLevelRecord, SweepStartRecord

    messages = [deserialize_message(data, SweepRecord) for data in payloads]
    if not messages:
        return [], None
    last = messages[-1].sweep_id
    levels, start = [], None

    def seconds(stamp) -> float:
        return stamp.sec + 1e-9 * stamp.nanosec

    for message in messages:
        if message.sweep_id != last:
            continue
        if message.kind == SweepRecord.KIND_START:
            start = SweepStartRecord(bool(message.started_at_rest),
                                     float(message.start_gauge_pressure_pa), message.sweep_id)
        elif message.kind == SweepRecord.KIND_LEVEL:
            levels.append(SweepLevelRecord(
                int(message.level_index), int(message.level_count),
                float(message.target_gauge_pressure_pa),
                float(message.reached_gauge_pressure_pa), int(message.branch),
                bool(message.settled), seconds(message.hold_start), seconds(message.hold_end),
                message.message, message.sweep_id))
    return levels, start


# Fields read from each PmaState, with a sentinel each that cannot occur by accident.
_DECODED_FIELDS = (('gauge_pressure_pa', 1.2345678901234567e-250),
                   ('length_m', -2.3456789012345678e-250),
                   ('gauge_setpoint_pa', 3.4567890123456789e-250))
_SENTINEL_SEC, _SENTINEL_NANOSEC = 0x5EC0_1D01, 0x1234_5678


def _field_offsets(template, serialize_message) -> dict[str, tuple[int, str]]:
    """Byte offset and dtype of each decoded field in messages serialised like `template`.

    rclpy serialises a copy of the message with sentinel values and we look them up, so the
    layout comes from the installed type support, never from a copy of the .msg in our code.
    """
    probe = copy.deepcopy(template)
    probe.header.stamp.sec, probe.header.stamp.nanosec = _SENTINEL_SEC, _SENTINEL_NANOSEC
    for name, value in _DECODED_FIELDS:
        setattr(probe, name, value)
    data = serialize_message(probe)
    order = '<' if data[1] & 1 else '>'  # CDR encapsulation: odd kind = little endian
    wanted = {'sec': (struct.pack(order + 'i', _SENTINEL_SEC), 'i4'),
              'nanosec': (struct.pack(order + 'I', _SENTINEL_NANOSEC), 'u4')}
    wanted.update({name: (struct.pack(order + 'd', value), 'f8')
                   for name, value in _DECODED_FIELDS})
    offsets = {}
    for name, (packed, kind) in wanted.items():
        offset = data.find(packed)
        if offset < 0 or data.find(packed, offset + 1) >= 0:
            raise SamplesError(f'cannot locate PmaState field {name} in its CDR layout')
        offsets[name] = (offset, order + kind)
    return offsets


def _decode_states(payloads: list[bytes], state_type):
    """(stamp_s, pressure, length, setpoint) arrays from PmaState CDR payloads.

    Messages of one size share one layout (header.frame_id is the only variable-length
    field), so each size group is decoded at numpy speed from offsets found by
    `_field_offsets`; the first and last message of every group are cross-checked against
    rclpy's own deserialisation. About 40x faster than deserialising each message.
    """
    from rclpy.serialization import deserialize_message, serialize_message

    sizes = np.fromiter((len(p) for p in payloads), dtype=np.int64, count=len(payloads))
    columns = {name: np.empty(len(payloads)) for name in
               ('sec', 'nanosec', 'gauge_pressure_pa', 'length_m', 'gauge_setpoint_pa')}
    for size in np.unique(sizes):
        members = np.flatnonzero(sizes == size)
        first = deserialize_message(payloads[members[0]], state_type)
        offsets = _field_offsets(first, serialize_message)
        rows = np.frombuffer(b''.join(payloads[i] for i in members),
                             dtype=np.uint8).reshape(members.size, int(size))
        for name, (offset, kind) in offsets.items():
            width = np.dtype(kind).itemsize
            columns[name][members] = rows[:, offset:offset + width].copy().view(kind).ravel()
        for index in (members[0], members[-1]):
            state = deserialize_message(payloads[index], state_type)
            expected = (state.header.stamp.sec, state.header.stamp.nanosec,
                        state.gauge_pressure_pa, state.length_m, state.gauge_setpoint_pa)
            got = tuple(columns[name][index] for name in columns)
            if not np.array_equal(np.array(expected, float), np.array(got), equal_nan=True):
                raise SamplesError('PmaState payloads do not match the installed message layout')
    stamp = columns['sec'] + 1e-9 * columns['nanosec']
    return stamp, columns['gauge_pressure_pa'], columns['length_m'], columns['gauge_setpoint_pa']


def _finish(stamp, pressure, length, setpoint, source) -> Samples:
    order = np.argsort(stamp, kind='stable')
    stamp, pressure, length = stamp[order], pressure[order], length[order]
    setpoint = None if setpoint is None else setpoint[order]
    usable = np.isfinite(length) & np.isfinite(pressure)
    dropped = int(np.count_nonzero(~usable))
    if setpoint is not None:
        setpoint = setpoint[usable]
        if not np.any(np.isfinite(setpoint)):
            setpoint = None
    origin = float(stamp[0]) if stamp.size else 0.0
    return Samples(stamp[usable] - origin, pressure[usable], length[usable], setpoint, dropped,
                   source, time_origin_s=origin)


def _csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise SamplesError(f'cannot read {path}: {error.strerror}') from None
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise SamplesError(f'{path} is neither an MCAP bag nor a UTF-8 CSV file: '
                           f'{utf8_error_position(data, error)}') from None
    rows = [row for row in csv.reader(io.StringIO(text, newline=''))
            if row and not row[0].startswith('#')]
    if not rows:
        raise SamplesError(f'{path} is empty')
    return [name.strip() for name in rows[0]], rows[1:]


def _column(path, header, rows, name) -> np.ndarray:
    index = header.index(name)
    try:
        return np.array([float(row[index]) if row[index].strip() else math.nan for row in rows])
    except (ValueError, IndexError):
        raise SamplesError(f'{path}: column {name} has a value that is not a number') from None


def read_sample_log(path) -> Samples:
    """A CSV sample log: time_s, gauge_pressure_pa, length_m [, gauge_setpoint_pa]."""
    header, rows = _csv_rows(Path(path))
    missing = [name for name in SAMPLE_LOG_COLUMNS if name not in header]
    if missing:
        raise SamplesError(f'{path}: missing column(s) {", ".join(missing)}; a sample log needs '
                           f'{", ".join(SAMPLE_LOG_COLUMNS)} (and optionally gauge_setpoint_pa)')
    columns = [_column(path, header, rows, name) for name in SAMPLE_LOG_COLUMNS]
    setpoint = _column(path, header, rows, 'gauge_setpoint_pa') \
        if 'gauge_setpoint_pa' in header else None
    return _finish(*columns, setpoint, str(path))


def read_branch_table(path) -> BranchData:
    """A table like the paper's Table 1 (kPa, cm) as branch data in SI."""
    header, rows = _csv_rows(Path(path))
    pressure_kpa, inc_cm, dec_cm = (_column(path, header, rows, name)
                                    for name in BRANCH_TABLE_COLUMNS)
    inc_ok = np.isfinite(pressure_kpa) & np.isfinite(inc_cm)
    dec_ok = np.isfinite(pressure_kpa) & np.isfinite(dec_cm)
    return BranchData(units.kpa_to_pa(pressure_kpa[inc_ok]), units.cm_to_m(inc_cm[inc_ok]),
                      units.kpa_to_pa(pressure_kpa[dec_ok]), units.cm_to_m(dec_cm[dec_ok]),
                      source=str(path), samples_used=int(inc_ok.sum() + dec_ok.sum()),
                      dropped_nan=int((~inc_ok).sum() + (~dec_ok).sum()), steady_state=True)


def is_branch_table(path) -> bool:
    header, _ = _csv_rows(Path(path))
    return all(name in header for name in BRANCH_TABLE_COLUMNS)


# --- splitting and steady state -----------------------------------------------------------

def hold_runs(values: np.ndarray, tolerance: float = HOLD_TOLERANCE_PA,
              min_samples: int = MIN_HOLD_SAMPLES) -> list[tuple[int, int]]:
    """[start, end) ranges where `values` stays within `tolerance` of the run's first value."""
    runs = []
    start = 0
    size = values.size
    while start < size:
        end, window = size, 64
        while True:  # growing windows keep a ramp's many short runs linear in time
            segment = values[start:start + window]
            away = np.flatnonzero(np.abs(segment - values[start]) > tolerance)
            if away.size:
                end = start + int(away[0])
                break
            if start + window >= size:
                break
            window *= 4
        if end - start >= min_samples:
            runs.append((start, end))
        start = end
    return runs


def settled_holds(samples: Samples) -> tuple[list[tuple[int, int]], bool]:
    """The settled part of each hold, and whether holds make up most of the path.

    Holds are found on the setpoint when it was recorded (the pressure otherwise); the
    settled part is the last STEADY_FRACTION of each. "Mostly holds" means a staircase,
    whose holds are best reduced to their means.
    """
    drive = samples.setpoint_pa if samples.setpoint_pa is not None else samples.pressure_pa
    runs = hold_runs(drive)
    mostly_holds = sum(end - start for start, end in runs) >= 0.5 * drive.size
    settled = [(start + int((end - start) * (1 - STEADY_FRACTION)), end) for start, end in runs]
    return settled, mostly_holds


def split_branches(samples: Samples, deadband_pa: float,
                   steady_state: bool | None = None) -> BranchData:
    """Label samples with the detector; reduce holds to their means (None: if mostly holds)."""
    if samples.pressure_pa.size == 0:
        raise SamplesError(f'{samples.source}: no usable samples (every length was NaN or the '
                           'topic is empty)')
    labels = detect_branches(samples.pressure_pa, deadband_pa)
    pressure, length = samples.pressure_pa, samples.length_m
    steady, mostly_holds = settled_holds(samples) if steady_state is not False else ([], False)
    if steady_state is None:  # auto: reduce only data that are mostly holds (a staircase)
        steady_state = mostly_holds
    if steady_state:
        if not steady:
            raise SamplesError(f'{samples.source}: no holds found for --steady-state (no run of '
                               f'{MIN_HOLD_SAMPLES}+ samples within {HOLD_TOLERANCE_PA:.0f} Pa); '
                               'use --no-steady-state')
        pressure = np.array([pressure[a:b].mean() for a, b in steady])
        length = np.array([length[a:b].mean() for a, b in steady])
        labels = np.array([labels[b - 1] for _, b in steady])
    rising = labels == BRANCH_INCREASING
    return BranchData(pressure[rising], length[rising], pressure[~rising], length[~rising],
                      source=samples.source, samples_used=int(samples.pressure_pa.size),
                      dropped_nan=samples.dropped_nan, steady_state=steady_state)


def load_branch_data(path, deadband_pa: float = DEFAULT_DEADBAND_PA,
                     steady_state: bool | None = None, topic: str = STATE_TOPIC,
                     progress: bool = True) -> BranchData:
    """Whatever the input is (bag, sample log, branch table), its fit data per branch."""
    return load_fit_input(path, deadband_pa, steady_state, topic, progress)[0]


def load_fit_input(path, deadband_pa: float = DEFAULT_DEADBAND_PA,
                   steady_state: bool | None = None, topic: str = STATE_TOPIC,
                   progress: bool = True) -> tuple[BranchData, Samples | None]:
    """(fit data per branch, the sample path it came from): the path is None for a branch
    table, which has no time. One read of the input for the fit and the time-series plot."""
    path = Path(path)
    if not is_bag(path) and is_branch_table(path):
        return read_branch_table(path), None
    samples = load_samples(path, topic, progress)
    data = split_branches(samples, deadband_pa, steady_state)
    data.truncated = samples.truncated
    return data, samples


def load_samples(path, topic: str = STATE_TOPIC, progress: bool = True) -> Samples:
    """The sample path of a bag or a sample-log CSV, in time order (no branch split)."""
    path = Path(path)
    if is_bag(path):
        return read_bag(path, topic, progress=progress)
    if is_branch_table(path):
        raise SamplesError(f'{path} is a branch table: it has no pressure path to follow')
    return read_sample_log(path)


def is_bag(path: Path) -> bool:
    """A bag directory, or a file that starts with the MCAP magic or is named .mcap.

    Decided by content, so a bare .mcap is never read as text first; a file named .mcap
    without the magic goes to the bag reader too, which says it is not an MCAP file.
    """
    from pma_bag.reader import MAGIC

    if not path.exists():
        raise SamplesError(f'{path}: no such file or directory')
    if path.is_dir():
        return True
    if not path.is_file():
        raise SamplesError(f'{path} is not a regular file (refit reads bags and CSV files)')
    try:
        with open(path, 'rb') as stream:
            head = stream.read(len(MAGIC))
    except OSError as error:
        raise SamplesError(f'cannot read {path}: {error.strerror}') from None
    return head == MAGIC or path.suffix.lower() == '.mcap'
