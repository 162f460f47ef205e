"""recorder CPU at 1 kHz against a plain rclpy subscriber, per chunk compression; SIGKILL loss.

    . tools/env.sh && python bench/bench_recorder.py [--seconds 10]

tests/helpers/bag_state_publisher.py publishes PmaState on /pma/state at 1 kHz (reliable,
depth 1000) to two subscribers at once: the recorder (`recorder -o BAG`, its default topic
list) and the baseline, a minimal rclpy node with a raw=True subscription (reliable,
KEEP_ALL, like the recorder's) whose callback only counts. CPU (utime + stime from /proc,
all threads) of both over the steady window, % of one core, and the ratio recorder /
baseline, for each chunk compression (none, zstd, lz4), and each compression's CPU as a
ratio to none's. Then the bag is read back with BagReader: /pma/state messages written vs
published (target: all). Last, a zstd recording (split every 64 kB) is killed with SIGKILL
after the window: the samples missing from its complete prefix (target: <= 1 s of samples,
the flush interval documented in docs/bags.md) and the bag size.
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from benchlib import (
    Processes,
    check,
    cpu_seconds,
    isolate_ros_graph,
    load_row,
    print_table,
    read_line,
    stop,
)
from rclpy.executors import ExternalShutdownException
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from pma_bag import BagReader
from pma_interfaces.msg import PmaState

ROOT = Path(__file__).resolve().parents[1]
RECORDER = ROOT / 'ros2_ws' / 'install' / 'pma_bag' / 'lib' / 'pma_bag' / 'record'
PUBLISHER = ROOT / 'tests' / 'helpers' / 'bag_state_publisher.py'
TOPIC = '/pma/state'
RATE_HZ = 1000.0
SETTLE_S = 1.0        # publishing before the CPU window opens
TAIL_S = 1.0          # publishing after it closes


def counter_main() -> None:
    """Baseline subscriber: raw PmaState on TOPIC, counted; prints the count (and the
    monotonic times of the first and last message) on SIGINT."""
    rclpy.init()
    node = rclpy.create_node('bench_recorder_baseline')
    count = first_ns = last_ns = 0

    def on_message(_data: bytes) -> None:
        nonlocal count, first_ns, last_ns
        last_ns = time.monotonic_ns()
        count += 1
        if count == 1:
            first_ns = last_ns
            print('first', flush=True)

    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000,
                     reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(PmaState, TOPIC, on_message, qos, raw=True)
    print('subscribed', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    print(f'received {count} {first_ns} {last_ns}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def run(seconds: float, work: Path, compression: str = 'none',
        kill: bool = False) -> tuple[list[tuple[str, str, str]], float]:
    bag = work / f'bag_{compression}{"_killed" if kill else ""}'
    count = round(RATE_HZ * (SETTLE_S + seconds + TAIL_S))
    procs = Processes(work)
    start = procs.start

    try:
        options = ['--compression', compression] + (['--max-bag-size', '65536'] if kill else [])
        recorder = start([str(RECORDER), '-o', str(bag), *options], f'recorder_{compression}')
        baseline = start([sys.executable, __file__, '--count'], 'baseline')
        read_line(baseline, 30, 'baseline subscriber start')
        publisher = start([sys.executable, str(PUBLISHER), '--topic', TOPIC,
                           '--rate', f'{RATE_HZ:g}', '--count', str(count),
                           '--wait-subscribers', '2', '--linger', '0.5'], 'publisher')
        read_line(publisher, 30, 'publisher start')
        if read_line(baseline, 60, 'first message at the baseline') != 'first':
            raise RuntimeError('baseline subscriber: unexpected output')
        time.sleep(SETTLE_S)
        pids = {'recorder': recorder.pid, 'baseline': baseline.pid, 'publisher': publisher.pid}
        cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        window_start = time.monotonic()
        time.sleep(seconds)
        cpu1 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        elapsed = time.monotonic() - window_start
        cpu = {name: (cpu1[name] - cpu0[name]) / elapsed * 100.0 for name in pids}
        if kill:
            recorder.kill()
            recorder.wait()
            published_at_kill = round((SETTLE_S + elapsed) * RATE_HZ)
        done = read_line(publisher, seconds + 60, 'publisher end')
        match = re.fullmatch(r'publisher: done (\d+) in ([\d.]+) s', done)
        if not match:
            raise RuntimeError(f'publisher: {done}')
        published, publish_s = int(match[1]), float(match[2])
        publisher.wait(10)
        time.sleep(0.5)
        stop(baseline)
        received = baseline.stdout.read().split()
        stop(recorder)
        recorder_out = recorder.stdout.read()
        if kill:
            return killed_rows(bag, published_at_kill), cpu['recorder']
    finally:
        procs.close()
    if received[:1] != ['received']:
        raise RuntimeError(f'baseline subscriber: {received}')
    first_ns, last_ns = int(received[2]), int(received[3])
    rate = (int(received[1]) - 1) / ((last_ns - first_ns) / 1e9) if last_ns > first_ns else 0.0
    wrote = re.search(r'recorder: wrote (\d+) messages', recorder_out)
    topics = re.findall(r'recording (\d+) topics', recorder_out)
    if not wrote:
        raise RuntimeError(f'recorder did not close its bag: {recorder_out[-2000:]}')
    with BagReader(bag) as reader:
        info = reader.topics.get(TOPIC)
        written = info.message_count if info is not None else 0
        bag_topics = sorted(reader.topics)

    size = sum(p.stat().st_size for p in bag.glob('*.mcap'))
    rows = [
        (f'[{compression}] recorder CPU at 1 kHz [% core]', f'{cpu["recorder"]:.1f}',
         f'(recording {topics[-1] if topics else "?"} topics: {", ".join(bag_topics)})'),
        ('  baseline raw rclpy subscriber CPU [% core]', f'{cpu["baseline"]:.1f}',
         '(same topic, same messages)'),
        ('  ratio recorder / baseline', f'{cpu["recorder"] / cpu["baseline"]:.2f}', ''),
        ('  publisher CPU [% core]', f'{cpu["publisher"]:.1f}',
         f'({published} in {publish_s:.2f} s incl. waiting for acks)'),
        ('  rate at the baseline [msg/s]', f'{rate:.0f}', f'({RATE_HZ:g} published)'),
        (f'{TOPIC} published', f'{published}', ''),
        (f'{TOPIC} written to the bag (BagReader)', f'{written}',
         check(written == published, f'{published}')),
        ('  recorder says it wrote (all topics)', f'{wrote[1]}', ''),
        ('  received by the baseline', f'{received[1]}', ''),
        ('  bag size [bytes per /pma/state message]', f'{size / max(written, 1):.1f}', ''),
    ]
    return rows, cpu['recorder'] / cpu['baseline']


def killed_rows(bag: Path, published: int) -> list[tuple[str, str, str]]:
    """What a SIGKILL'd zstd recording keeps: a gap-free prefix, at most ~1 s short."""
    import warnings

    from rclpy.serialization import deserialize_message

    from pma_bag.reader import TruncatedBagWarning

    with warnings.catch_warnings():
        warnings.simplefilter('ignore', TruncatedBagWarning)
        with BagReader(bag) as reader:
            seqs = [deserialize_message(m.data, PmaState).seq
                    for m in reader.messages([TOPIC])]
            files = len(reader.files)
    prefix = seqs == list(range(len(seqs)))
    lost = published - len(seqs)
    return [
        ('[zstd, SIGKILL] samples kept / published before the kill', f'{len(seqs)}',
         f'of ~{published}; {files} files; gap-free prefix: {prefix}'),
        ('  lost at the kill [s of samples]', f'{lost / RATE_HZ:.2f}',
         check(lost <= RATE_HZ * 1.0 and prefix, '<= 1.0 s, gap-free')),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=10.0, help='CPU window [s]')
    parser.add_argument('--count', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.count:
        counter_main()
        return
    isolate_ros_graph()
    if not RECORDER.exists():
        sys.exit(f'{RECORDER} not found: run `make setup`')
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))   # clean up on SIGTERM too
    work = Path(tempfile.mkdtemp(prefix='bench_recorder_'))
    rows, ratios = [], {}
    for compression in ('none', 'zstd', 'lz4'):
        found, ratios[compression] = run(args.seconds, work, compression)
        rows += found
    for compression in ('zstd', 'lz4'):
        rows.append((f'CPU ratio {compression} / none (each against its baseline)',
                     f'{ratios[compression] / ratios["none"]:.2f}', ''))
    rows += run(min(args.seconds, 5.0), work, 'zstd', kill=True)[0]
    rows.append(load_row())
    shutil.rmtree(work, ignore_errors=True)        # kept (logs, bag) when the run failed
    print_table(rows)


if __name__ == '__main__':
    main()
