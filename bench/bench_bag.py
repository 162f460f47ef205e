"""Bag throughput: BagReader against mcap's own readers and rosbags, on the same files.

    . tools/env.sh && python bench/bench_bag.py [--count 100000] [--repeat 3]

Writes N pre-serialised PmaState (write figures exclude serialisation) with chunk compression
none, zstd and lz4, then reads each file raw (no decoding) with
  - BagReader (our struct parser),
  - mcap `make_reader(f).iter_messages()` (seeking, log-time order: what BagReader yields),
  - mcap `NonSeekingReader(f).iter_messages(log_time_order=False)` (the stream reader),
  - rosbags AnyReader `messages()` (raw bytes),
and, for a file cut short like a SIGKILL leaves it, BagReader against mcap's stream reader
(the only mcap reader that opens it). Every reader must yield every message. Ratios are
other reader time / BagReader time, measured in this run (> 1: BagReader is faster); the
hand-written parser is kept only while it is >= 1.5x faster than mcap's (docs/bags.md).
"""

import argparse
import shutil
import statistics
import tempfile
import time
import warnings
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagReader, BagWriter
from pma_bag.reader import TruncatedBagWarning
from pma_interfaces.msg import PmaState

STATE = 'pma_interfaces/msg/PmaState'
KEEP_RATIO = 1.5


def timed(action, repeat: int) -> float:
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


def count_bag_reader(path: Path) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', TruncatedBagWarning)
        with BagReader(path) as reader:
            return sum(1 for m in reader.messages() if m.data)


def count_mcap_seeking(path: Path) -> int:
    with open(path, 'rb') as stream:
        return sum(1 for _, _, m in make_reader(stream).iter_messages() if m.data)


def count_mcap_stream(path: Path) -> int:
    count = 0
    with open(path, 'rb') as stream:
        try:
            for _, _, message in NonSeekingReader(stream).iter_messages(log_time_order=False):
                count += bool(message.data)
        except McapError:
            pass            # a cut file ends in an error after its last complete record
    return count


def count_rosbags(path: Path) -> int:
    with AnyReader([path]) as reader:
        return sum(1 for _, _, raw in reader.messages() if raw)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument('--count', type=int, default=100_000)
    parser.add_argument('--repeat', type=int, default=3)
    args = parser.parse_args()
    data = [serialize_message(PmaState(seq=i, gauge_pressure_pa=float(i)))
            for i in range(args.count)]
    t0 = time.time_ns()
    work = Path(tempfile.mkdtemp(prefix='bench_bag_'))
    runs = iter(range(10**6))

    def write_bag(compression: str = '') -> Path:
        bag = work / f'bag{next(runs)}'
        with BagWriter(bag, compression=compression) as writer:
            writer.add_topic('/pma/state', STATE)
            for i, cdr in enumerate(data):
                writer.write('/pma/state', cdr, t0 + i * 1_000_000)
        return bag

    def write_raw_mcap() -> None:
        with open(work / f'raw{next(runs)}.mcap', 'wb') as stream:
            writer = Writer(stream, chunk_size=768 * 1024, compression=CompressionType.NONE)
            writer.start('ros2', 'bench')
            schema = writer.register_schema(STATE, 'ros2msg', b'')
            channel = writer.register_channel('/pma/state', 'cdr', schema)
            for i, cdr in enumerate(data):
                writer.add_message(channel, t0 + i * 1_000_000, cdr, t0 + i * 1_000_000)
            writer.finish()

    rows = []
    write_ours = timed(write_bag, args.repeat)
    write_base = timed(write_raw_mcap, args.repeat)
    rate = args.count / 1000
    rows.append(('write BagWriter (none)', f'{write_ours:.3f} s',
                 f'{rate / write_ours:.0f} k msg/s; ratio to raw mcap.Writer '
                 f'{write_ours / write_base:.2f}'))
    worst = float('inf')
    for compression in ('', 'zstd', 'lz4'):
        name = compression or 'none'
        bag = write_bag(compression)
        path = next(bag.glob('*.mcap'))
        readers = {'BagReader': lambda p=path: count_bag_reader(p),
                   'mcap make_reader().iter_messages()': lambda p=path: count_mcap_seeking(p),
                   'mcap NonSeekingReader': lambda p=path: count_mcap_stream(p),
                   'rosbags AnyReader (raw)': lambda b=bag: count_rosbags(b)}
        for label, read in readers.items():
            got = read()
            if got != args.count:
                raise SystemExit(f'{label} read {got} of {args.count} messages ({name})')
        times = {label: timed(read, args.repeat) for label, read in readers.items()}
        ours = times['BagReader']
        size = path.stat().st_size
        rows.append((f'{name}: file size', f'{size / 1e6:.2f} MB',
                     f'{size / args.count:.1f} B/msg'))
        rows.append((f'{name}: read BagReader', f'{ours:.3f} s',
                     f'{rate / ours:.0f} k msg/s'))
        for label, seconds in times.items():
            if label != 'BagReader':
                rows.append((f'{name}: ratio {label} / BagReader', f'{seconds / ours:.2f}',
                             ''))
        worst = min(worst, times['mcap make_reader().iter_messages()'] / ours,
                    times['mcap NonSeekingReader'] / ours)
    # A file cut in the middle of its last chunk, without summary (what SIGKILL leaves).
    bag = write_bag()
    whole = next(bag.glob('*.mcap')).read_bytes()
    cut = work / 'cut.mcap'
    cut.write_bytes(whole[:int(len(whole) * 0.7)])
    ours_cut, mcap_cut = count_bag_reader(cut), count_mcap_stream(cut)
    ours_s = timed(lambda: count_bag_reader(cut), args.repeat)
    mcap_s = timed(lambda: count_mcap_stream(cut), args.repeat)
    rows.append(('cut file: messages BagReader / mcap stream', f'{ours_cut}/{mcap_cut}',
                 '(mcap drops the cut chunk whole)'))
    rows.append(('cut file: ratio mcap NonSeekingReader / BagReader', f'{mcap_s / ours_s:.2f}',
                 ''))
    worst = min(worst, mcap_s / ours_s)
    verdict = 'keep the parser' if worst >= KEEP_RATIO else 'use the mcap reader'
    rows.append(('slowest mcap reader / BagReader (all files)', f'{worst:.2f}',
                 f'>= {KEEP_RATIO}: {verdict}'))
    print(f'{args.count} PmaState ({len(data[0])} B CDR), median of {args.repeat}:')
    width = max(len(r[0]) for r in rows)
    for label, value, note in rows:
        print(f'  {label:<{width}}  {value:>12}  {note}')
    shutil.rmtree(work)


if __name__ == '__main__':
    main()
