"""foxglove_live's cost: CPU and end-to-end latency against a bare rclpy subscriber, same run.

    . tools/env.sh && python bench/bench_foxglove.py [--seconds 20] [--burst-hz 1000]

tests/helpers/live_publisher.py publishes PmaState on /pma/state and PmaPrediction on
/pma/prediction at 100 Hz each (what driver_node and model_node send at the rig's rate),
reliable, each header stamped with time.time_ns() at publish. Two readers take them:
- the bridge, `foxglove_live` (port 0), with one viewer: a Foxglove WebSocket protocol client
  (tests/support/foxglove_ws.py) in this process, subscribed to both channels;
- the baseline, a bare rclpy node (--baseline) with raw subscriptions to both topics,
  reliable, KEEP_ALL (the bridge's QoS), whose callback only notes the latency.
CPU (utime + stime from /proc, all threads) of the bridge and of the baseline over the same
window, % of one core, and the ratio bridge / baseline. Latency = arrival time (time.time_ns,
at the viewer's socket for the bridge, in the callback for the baseline) - header stamp;
p50 and p99 of each and their ratios (the bridge's path is DDS -> rclpy -> WebSocket ->
viewer, so it includes the viewer's own receive). Then a burst at --burst-hz for 2 s: messages
each path lost (target: none). The viewer's CPU is not counted (it is the Foxglove app's).
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
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

from pma_interfaces.msg import PmaPrediction, PmaState

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'tests'))
from support.foxglove_ws import FoxgloveClient  # noqa: E402

BRIDGE = ROOT / 'ros2_ws' / 'install' / 'pma_bringup' / 'lib' / 'pma_bringup' / 'foxglove_live'
PUBLISHER = ROOT / 'tests' / 'helpers' / 'live_publisher.py'
TOPICS = {'/pma/state': PmaState, '/pma/prediction': PmaPrediction}
RATE_HZ = 100.0
SETTLE_S = 2.0        # publishing before the CPU window opens
BURST_S = 2.0
_STAMP = struct.Struct('<iI')        # header.stamp (sec, nanosec) after the 4-byte CDR header


def stamp_ns(cdr: bytes) -> int:
    sec, nanosec = _STAMP.unpack_from(cdr, 4)
    return sec * 1_000_000_000 + nanosec


def baseline_main(out: Path) -> None:
    """Raw subscriptions to both topics; on SIGINT, their latencies [ns] to `out` as JSON."""
    rclpy.init()
    node = rclpy.create_node('bench_foxglove_baseline')
    latencies: dict[str, list[int]] = {topic: [] for topic in TOPICS}
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=100,
                     reliability=ReliabilityPolicy.RELIABLE)
    for topic, msg_type in TOPICS.items():
        def on_message(data: bytes, found=latencies[topic]) -> None:
            found.append(time.time_ns() - stamp_ns(data))
        node.create_subscription(msg_type, topic, on_message, qos, raw=True)
    print('subscribed', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    out.write_text(json.dumps(latencies))
    node.destroy_node()
    rclpy.try_shutdown()


def viewer_latencies(client: FoxgloveClient) -> dict[str, list[int]]:
    """Latencies [ns] of what the viewer got so far, per topic."""
    return {topic: [m.received_ns - stamp_ns(m.payload) for m in client.received(topic)]
            for topic in TOPICS}


def percentiles(values_ns: list[int]) -> tuple[float, float]:
    array = np.asarray(values_ns, dtype=float) / 1e6
    return float(np.percentile(array, 50)), float(np.percentile(array, 99))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=20.0, help='CPU window [s]')
    parser.add_argument('--burst-hz', type=float, default=1000.0)
    parser.add_argument('--baseline', type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.baseline:
        baseline_main(args.baseline)
        return
    isolate_ros_graph()
    if not BRIDGE.exists():
        sys.exit(f'{BRIDGE} not found: run `make setup`')
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    work = Path(tempfile.mkdtemp(prefix='bench_foxglove_'))
    procs = Processes(work)
    start = procs.start
    client = None

    def publish(first: int, rate: float, count: int) -> subprocess.Popen:
        """A publisher that starts once the viewer is subscribed to both channels."""
        go = work / f'go{first}'
        proc = start([sys.executable, str(PUBLISHER), '--first-seq', str(first), '--rate',
                      f'{rate:g}', '--count', str(count), '--wait-subscribers', '2',
                      '--go-file', str(go)], f'publisher{first}')
        read_line(proc, 60, 'publisher matched')
        for topic in TOPICS:
            client.channel_for(topic, 10)
        time.sleep(0.5)            # our subscribe requests reach the server
        go.touch()
        read_line(proc, 30, 'publisher start')
        return proc

    try:
        bridge = start([str(BRIDGE), '--ros-args', '-p', 'port:=0'], 'bridge')
        url = None
        while url is None:
            url = re.search(r'ws://\S+', read_line(bridge, 30, 'the bridge\'s URL'))
        client = FoxgloveClient(url.group(0))
        client.follow(list(TOPICS))
        baseline_out = work / 'baseline.json'
        baseline = start([sys.executable, __file__, '--baseline', str(baseline_out)],
                         'baseline')
        read_line(baseline, 30, 'baseline subscriber start')

        steady_count = round(RATE_HZ * (SETTLE_S + args.seconds + 1.0))
        publisher = publish(0, RATE_HZ, steady_count)
        time.sleep(SETTLE_S)
        pids = {'bridge': bridge.pid, 'baseline': baseline.pid}
        cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        window_start = time.monotonic()
        time.sleep(args.seconds)
        cpu1 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        elapsed = time.monotonic() - window_start
        cpu = {name: (cpu1[name] - cpu0[name]) / elapsed * 100.0 for name in pids}
        read_line(publisher, 60, 'publisher end')
        publisher.wait(10)
        time.sleep(1.0)
        steady = {t: len(client.received(t)) for t in TOPICS}
        viewer = viewer_latencies(client)

        burst_count = round(args.burst_hz * BURST_S)
        burst = publish(1_000_000, args.burst_hz, burst_count)
        done = read_line(burst, 60, 'burst end')
        burst_sent = int(done.rsplit(' ', 1)[1])
        time.sleep(1.5)
        burst_viewer = {t: len(client.received(t)) - steady[t] for t in TOPICS}
        stop(baseline)
        base = json.loads(baseline_out.read_text())
    finally:
        if client is not None:
            client.close()
        procs.close()

    base_steady = {t: base[t][:steady_count] for t in TOPICS}
    base_burst = {t: len(base[t]) - len(base_steady[t]) for t in TOPICS}
    all_viewer = viewer['/pma/state'] + viewer['/pma/prediction']
    all_base = base_steady['/pma/state'] + base_steady['/pma/prediction']
    v50, v99 = percentiles(all_viewer)
    b50, b99 = percentiles(all_base)
    lost_steady = {t: steady_count - steady[t] for t in TOPICS}
    lost_burst = {t: burst_sent - burst_viewer[t] for t in TOPICS}
    lost_base = {t: burst_sent - base_burst[t] for t in TOPICS}
    rows = [
        ('bridge CPU, 2 x 100 Hz, one viewer [% core]', f'{cpu["bridge"]:.1f}',
         '(/pma/state + /pma/prediction, raw CDR passed through)'),
        ('baseline bare rclpy subscriber CPU [% core]', f'{cpu["baseline"]:.1f}',
         '(same topics, raw, callback notes the latency)'),
        ('CPU ratio bridge / baseline', f'{cpu["bridge"] / cpu["baseline"]:.2f}',
         f'(over {elapsed:.1f} s)'),
        ('latency p50 to the viewer [ms]', f'{v50:.2f}', '(publish stamp -> viewer socket)'),
        ('latency p50 to the baseline [ms]', f'{b50:.2f}', '(publish stamp -> callback)'),
        ('latency p50 ratio bridge / baseline', f'{v50 / b50:.2f}', ''),
        ('latency p99 to the viewer [ms]', f'{v99:.2f}', ''),
        ('latency p99 to the baseline [ms]', f'{b99:.2f}', ''),
        ('latency p99 ratio bridge / baseline', f'{v99 / b99:.2f}', ''),
        ('steady: messages published per topic', f'{steady_count}', ''),
        ('steady: lost on the way to the viewer', f'{sum(lost_steady.values())}',
         check(not any(lost_steady.values()), '0')),
        (f'burst {args.burst_hz:g} Hz x {BURST_S:g} s: published per topic', f'{burst_sent}',
         ''),
        ('burst: lost on the way to the viewer', f'{sum(lost_burst.values())}',
         check(not any(lost_burst.values()), '0')),
        ('burst: lost on the way to the baseline', f'{sum(lost_base.values())}', ''),
        load_row(),
    ]
    print_table(rows)


if __name__ == '__main__':
    main()
