"""Throughput of the bag code: BagWriter vs a raw mcap.Writer, BagReader vs rosbags.

    . tools/env.sh && python bench/bench_bag.py [--count 100000] [--repeat 3]

Writes N pre-serialised PmaState messages (write figures exclude serialisation), then reads
the same file raw with BagReader and with rosbags AnyReader (raw, and + deserialize).
Prints median wall times and the read ratio BagReader / rosbags (target >= 1).
"""

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from mcap.writer import CompressionType, Writer
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagReader, BagWriter
from pma_interfaces.msg import PmaState

STATE = 'pma_interfaces/msg/PmaState'


def timed(action, repeat: int) -> float:
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


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

    def write_bag() -> Path:
        bag = work / f'bag{next(runs)}'
        with BagWriter(bag) as writer:
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

    write_ours = timed(write_bag, args.repeat)
    write_base = timed(write_raw_mcap, args.repeat)
    bag = write_bag()

    def read_ours() -> None:
        with BagReader(bag) as reader:
            assert sum(len(m.data) > 0 for m in reader.messages()) == args.count

    def read_rosbags_raw() -> None:
        with AnyReader([bag]) as reader:
            assert sum(len(raw) > 0 for _, _, raw in reader.messages()) == args.count

    def read_rosbags_decode() -> None:
        with AnyReader([bag]) as reader:
            assert sum(reader.deserialize(raw, c.msgtype).seq >= 0
                       for c, _, raw in reader.messages()) == args.count

    read_ours_s = timed(read_ours, args.repeat)
    raw_s = timed(read_rosbags_raw, args.repeat)
    decode_s = timed(read_rosbags_decode, args.repeat)
    rate = args.count / 1000
    print(f'{args.count} PmaState ({len(data[0])} B CDR), median of {args.repeat}:')
    print(f'  write BagWriter          {write_ours:6.3f} s  {rate / write_ours:7.0f} k msg/s')
    print(f'  write raw mcap.Writer    {write_base:6.3f} s  {rate / write_base:7.0f} k msg/s')
    print(f'  read  BagReader (raw)    {read_ours_s:6.3f} s  {rate / read_ours_s:7.0f} k msg/s')
    print(f'  read  rosbags raw        {raw_s:6.3f} s  {rate / raw_s:7.0f} k msg/s')
    print(f'  read  rosbags+deserialize{decode_s:6.3f} s  {rate / decode_s:7.0f} k msg/s')
    print(f'  read ratio BagReader/rosbags raw: {raw_s / read_ours_s:.2f}, '
          f'/rosbags+deserialize: {decode_s / read_ours_s:.2f} (target >= 1)')
    shutil.rmtree(work)


if __name__ == '__main__':
    main()
