"""info: what `ros2 bag info` prints about a bag, plus a PMA summary of its pma/state.

    ros2 run pma_bag info BAG [--check] [--topic pma/state]

BAG is a bag directory (split or not, with or without metadata.yaml) or a bare .mcap file.
Files, size, storage, duration, start/end, message count, chunk compression, per-topic type,
count and offered QoS, then the experiment's custom_data (metadata.yaml) and the recorder's
loss counts. When the bag holds pma_interfaces/msg/PmaState: pressure range, sample rate and
sequence gaps; and the sweeps its pma/sweep_record holds (the driver's START, LEVEL and END
records: how many, how they ended, their levels and how many did not settle), or that it
holds none. Decoded from the bag's own schemas (no sourced ROS needed).
`--check` validates every CRC the writer stored (chunks, data section, summary); exit code 1
if one does not match or a file was not closed. A missing or unreadable bag: exit code 2.
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from pma_bag.errors import BagError
from pma_bag.reader import BagReader, TopicInfo, TruncatedBagWarning
from pma_common.commands import run_command
from pma_common.console import closed_pipe_ends_quietly

STATE_TYPE = 'pma_interfaces/msg/PmaState'
RECORD_TYPE = 'pma_interfaces/msg/SweepRecord'
# SweepRecord's constants (pma_interfaces/msg/SweepRecord.msg)
KIND_START, KIND_LEVEL, KIND_END = 0, 1, 2
BRANCH_REST, BRANCH_RISING, BRANCH_FALLING = 0, 1, -1
OUTCOMES = ('succeeded', 'aborted', 'canceled')
# The recorder's loss counts in custom_data (docs/bags.md), shown under their own heading.
LOSS_KEYS = ('lost_messages', 'lost_state_samples', 'state_sequence_gaps',
             'dds_messages_lost')
LABEL_WIDTH = 19


def human_size(size: int) -> str:
    value = float(size)
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if value < 1024 or unit == 'GiB':
            return f'{value:.1f} {unit}' if unit != 'B' else f'{size} B'
        value /= 1024
    return f'{size} B'


def format_time(ns: int) -> str:
    """`Jun 10 2024 14:33:11.123456789 (1718029991.123456789)`, local time, as rosbag2 does."""
    seconds, rest = divmod(ns, 1_000_000_000)
    stamp = datetime.fromtimestamp(seconds).strftime('%b %d %Y %H:%M:%S')
    return f'{stamp}.{rest:09d} ({seconds}.{rest:09d})'


def format_qos(profiles: list[dict]) -> str:
    if not profiles:
        return 'none recorded'
    kinds = sorted({(p.get('reliability', '?'), p.get('durability', '?')) for p in profiles})
    text = '; '.join(f'{r}, {d}' for r, d in kinds)
    return f'{text} ({len(profiles)} publisher{"s" if len(profiles) > 1 else ""})'


@dataclass
class StateSummary:
    topic: str
    samples: int
    rate_hz: float
    pressure_min_pa: float
    pressure_max_pa: float
    setpoint_max_pa: float
    lost: int
    gaps: int
    duplicates: int
    restarts: int


def state_summary(reader: BagReader, topic: TopicInfo) -> StateSummary:
    """Decode every PmaState with a decoder generated from the bag's own schema text."""
    from mcap_ros2._dynamic import generate_dynamic

    from pma_common.sequence import SequenceTracker

    decode = generate_dynamic(topic.type_name, topic.schema.text)[topic.type_name]
    tracker = SequenceTracker()
    count = 0
    first_stamp = last_stamp = None
    p_min, p_max, sp_max = math.inf, -math.inf, 0.0
    for message in reader.messages([topic.name]):
        state = decode(message.data)
        count += 1
        tracker.add(state.seq)
        stamp = state.header.stamp.sec + 1e-9 * state.header.stamp.nanosec
        first_stamp = stamp if first_stamp is None else min(first_stamp, stamp)
        last_stamp = stamp if last_stamp is None else max(last_stamp, stamp)
        if math.isfinite(state.gauge_pressure_pa):
            p_min = min(p_min, state.gauge_pressure_pa)
            p_max = max(p_max, state.gauge_pressure_pa)
        sp_max = max(sp_max, state.gauge_setpoint_pa)
    span = (last_stamp - first_stamp) if count > 1 else 0.0
    stats = tracker.stats()
    return StateSummary(topic.name, count, (count - 1) / span if span > 0 else 0.0,
                        p_min, p_max, sp_max, stats.lost, stats.gaps, stats.duplicates,
                        stats.restarts)


@dataclass
class SweepSummary:
    """The sweeps a bag's SweepRecords tell of (none: `topics` is empty or they hold none)."""

    topics: list[str]
    sweeps: int = 0
    ended: dict[str, int] = field(default_factory=dict)    # outcome: sweeps
    unended: int = 0              # a START without an END in the bag (cut short?)
    before_first_level: int = 0   # an END without a START: aborted before the first level
    pressurised: int = 0          # started from the pressure it had (start_pressurised)
    levels: int = 0
    branches: dict[int, int] = field(default_factory=dict)
    not_settled: int = 0


def sweep_summary(reader: BagReader, topics: list[TopicInfo]) -> SweepSummary:
    """Count sweeps by sweep_id from their START and END records, and their LEVELs."""
    from mcap_ros2._dynamic import generate_dynamic

    summary = SweepSummary([t.name for t in topics])
    started: set[str] = set()
    ended: dict[str, str] = {}
    for topic in topics:
        decode = generate_dynamic(topic.type_name, topic.schema.text)[topic.type_name]
        for message in reader.messages([topic.name]):
            record = decode(message.data)
            key = f'{topic.name} {record.sweep_id}'
            if record.kind == KIND_START:
                started.add(key)
                summary.pressurised += not record.started_at_rest
            elif record.kind == KIND_END:
                outcome = record.message.split(':', 1)[0]
                ended[key] = outcome if outcome in OUTCOMES else 'ended otherwise'
            elif record.kind == KIND_LEVEL:
                summary.levels += 1
                summary.branches[record.branch] = summary.branches.get(record.branch, 0) + 1
                summary.not_settled += not record.settled
    summary.sweeps = len(started | set(ended))
    for outcome in ended.values():
        summary.ended[outcome] = summary.ended.get(outcome, 0) + 1
    summary.unended = len(started - set(ended))
    summary.before_first_level = len(set(ended) - started)
    return summary


def describe(reader: BagReader, *, pma: bool = True) -> list[str]:
    lines: list[str] = []

    def row(label: str, value: object = '') -> None:
        lines.append(f'{label + ":":<{LABEL_WIDTH}}{value}')

    def more(value: object) -> None:
        lines.append(' ' * LABEL_WIDTH + str(value))

    names = [f.path.name for f in reader.files]
    row('Files', names[0])
    for name in names[1:]:
        more(name)
    row('Bag size', human_size(sum(f.path.stat().st_size for f in reader.files)))
    row('Storage id', 'mcap')
    if reader.bag_info is not None:
        row('ROS Distro', reader.bag_info.get('ros_distro', 'unknown'))
    time_range = reader.time_range_ns()
    start, end = time_range if time_range else (0, 0)
    row('Duration', f'{(end - start) / 1e9:.9f}s')
    row('Start', format_time(start) if time_range else '-')
    row('End', format_time(end) if time_range else '-')
    row('Messages', reader.message_count)
    chunks = sorted(reader.compressions - {''}) or ['none']
    row('Compression', f'{", ".join(chunks)} (MCAP chunks)')
    if reader.truncated:
        row('Truncated', f'yes: not closed by its recorder; recover it with '
                         f'`{run_command("pma_bag", "recover", reader.path)}`')
    topics = list(reader.topics.values())
    for index, topic in enumerate(topics):
        text = (f'Topic: {topic.name} | Type: {topic.type_name} | Count: '
                f'{topic.message_count} | Serialization Format: {topic.serialization_format}'
                f' | QoS: {format_qos(topic.offered_qos_profiles)}')
        (row('Topic information', text) if index == 0 else more(text))
    if not topics:
        row('Topic information', 'none')
    custom = reader.custom_data
    experiment = {k: v for k, v in custom.items() if k not in LOSS_KEYS}
    losses = {k: custom[k] for k in LOSS_KEYS if k in custom}
    for index, (key, value) in enumerate(sorted(experiment.items())):
        (row('Custom data', f'{key}: {value}') if index == 0 else more(f'{key}: {value}'))
    if losses:
        row('Recorder losses', ', '.join(f'{k.replace("_", " ")} {v}'
                                         for k, v in losses.items()))
    if pma:
        states = [t for t in topics if t.type_name == STATE_TYPE and t.message_count]
        records = [t for t in topics if t.type_name == RECORD_TYPE]
        for topic in states:
            lines += pma_lines(state_summary(reader, topic))
        if states or records:
            lines += sweep_lines(sweep_summary(reader, records))
    return lines


def pma_lines(summary: StateSummary) -> list[str]:
    """Human-facing: kPa, labelled."""
    return [
        f'PMA summary ({summary.topic}):',
        f'  samples:        {summary.samples} at {summary.rate_hz:.1f} Hz (header stamps)',
        f'  pressure range: {summary.pressure_min_pa / 1e3:.1f} .. '
        f'{summary.pressure_max_pa / 1e3:.1f} kPa gauge',
        f'  sequence:       {summary.lost} lost in {summary.gaps} gaps, '
        f'{summary.duplicates} duplicates, {summary.restarts} restarts',
        f'  setpoints:      up to {summary.setpoint_max_pa / 1e3:.1f} kPa',
    ]


def sweep_lines(summary: SweepSummary) -> list[str]:
    """`sweeps: N (how they ended)` and their levels, from the driver's records only."""
    if not summary.sweeps:
        where = ', '.join(summary.topics) or 'no pma/sweep_record topic in the bag'
        return [f'  sweeps:         none recorded ({where})']
    how = [f'{n} {outcome}' for outcome, n in sorted(summary.ended.items())]
    if summary.unended:
        how.append(f'{summary.unended} without an END in the bag (cut short?)')
    if summary.before_first_level:
        how.append(f'{summary.before_first_level} ended before its first level')
    if summary.pressurised:
        how.append(f'{summary.pressurised} started pressurised (start_pressurised)')
    branches = summary.branches
    settled = (f'{summary.not_settled} not settled' if summary.not_settled
               else 'all settled')
    lines = [f'  sweeps:         {summary.sweeps} ({", ".join(how)}; from '
             f'{", ".join(summary.topics)})']
    if summary.levels:
        lines.append(f'  levels:         {summary.levels} ({branches.get(BRANCH_REST, 0)} at '
                     f'rest, {branches.get(BRANCH_RISING, 0)} rising, '
                     f'{branches.get(BRANCH_FALLING, 0)} falling), {settled}')
    return lines


def check_lines(reader: BagReader) -> tuple[list[str], bool]:
    lines, ok = [], True
    for report in reader.check():
        ok = ok and report.ok
        state = 'OK' if report.ok else 'FAILED'
        without = (f', {report.chunks_without_crc} without CRC'
                   if report.chunks_without_crc else '')
        lines.append(f'CRC check {report.path.name}: {state} ({report.chunks_checked} chunks'
                     f'{without}, data section {report.data_section}, summary {report.summary})')
        lines += [f'  {problem}' for problem in report.problems]
    return lines, ok


@closed_pipe_ends_quietly
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='info', description=__doc__.split('\n')[0])
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('--check', action='store_true',
                        help='validate the CRCs of chunks, data section and summary')
    parser.add_argument('--no-pma-summary', action='store_true',
                        help='skip decoding pma/state (faster on very long bags)')
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', TruncatedBagWarning)
            reader = BagReader(args.bag)
        with reader:
            lines = describe(reader, pma=not args.no_pma_summary)
            ok = True
            if args.check:
                checked, ok = check_lines(reader)
                lines += checked
    except BagError as exc:
        print(f'info: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print('\n'.join(lines))
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
