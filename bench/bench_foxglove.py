"""foxglove_live's cost: CPU and latency against a bare rclpy subscriber; its handshake layer's.

    . tools/env.sh && python bench/bench_foxglove.py [--seconds 20] [--burst-hz 1000]

tests/helpers/live_publisher.py publishes PmaState on /pma/state and PmaPrediction on
/pma/prediction at 100 Hz each (what driver_node and model_node send at the rig's rate),
reliable, each header stamped with time.time_ns() at publish. Two readers take them:
- the bridge, `foxglove_live` (port 0), with two viewers: Foxglove WebSocket protocol clients
  (pma_bringup.foxglove_client) in this process, subscribed to both channels, one through
  the handshake layer on the public port offering `foxglove.websocket.v1` (the new path), one
  straight to foxglove-sdk's own server behind it (its loopback port, which the bridge prints:
  today's path before the layer), so both paths carry the same messages in the same run;
- the baseline, a bare rclpy node (--baseline) with raw subscriptions to both topics,
  reliable, KEEP_ALL (the bridge's QoS), whose callback only notes the latency.
CPU (utime + stime from /proc, all threads) of the bridge and of the baseline over the same
window, % of one core, and the ratio bridge / baseline. Latency = arrival time (time.time_ns,
at the viewer's socket for the bridge, in the callback for the baseline) - header stamp;
p50 and p99 of each and their ratios (the bridge's path is DDS -> rclpy -> WebSocket ->
viewer, so it includes the viewer's own receive). The layer: p50/p99 latency of the viewer
through it against the direct one, their ratios, and per message the difference of the two
arrival times (what the layer adds); its thread's CPU (`fg-handshake`). Then a burst at
--burst-hz for 2 s: messages each path lost (target: none) and the rate each viewer received
them at (throughput ratio layer / direct). Last, the layer alone, without ROS: --mbytes MB
sent by a server on 127.0.0.1 to a reader, straight and through a HandshakeProxy, MB/s of each
(its capacity against what the rig needs, about 0.03 MB/s). The viewers' CPU is not counted
(it is the Foxglove app's).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
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

from pma_bringup.foxglove_client import FoxgloveClient
from pma_bringup.ws_handshake import THREAD_NAME, HandshakeProxy
from pma_interfaces.msg import PmaPrediction, PmaState

ROOT = Path(__file__).resolve().parents[1]

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


def added_by_layer(direct: FoxgloveClient, layer: FoxgloveClient) -> list[int]:
    """Per message both viewers got: arrival through the layer - arrival direct [ns]."""
    added = []
    for topic in TOPICS:
        first = {(stamp_ns(m.payload), m.payload): m.received_ns for m in direct.received(topic)}
        added += [m.received_ns - first[key] for m in layer.received(topic)
                  if (key := (stamp_ns(m.payload), m.payload)) in first]
    return added


def receive_rate(messages: list, n_first: int) -> float:
    """Messages per second a viewer received them at, after its first n_first."""
    burst = messages[n_first:]
    if len(burst) < 2:
        return float('nan')
    return (len(burst) - 1) / ((burst[-1].received_ns - burst[0].received_ns) / 1e9)


def thread_cpu_seconds(pid: int, name: str) -> float:
    """CPU time of a process's threads named `name` (their /proc comm)."""
    total = 0.0
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            if (task / 'comm').read_text().strip() == name:
                fields = (task / 'stat').read_text().rsplit(')', 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
        except OSError:
            pass
    return total


def layer_capacity(mbytes: int) -> tuple[float, float]:
    """(MB/s straight from a sending server, MB/s through a HandshakeProxy), 127.0.0.1 only."""
    total = mbytes * 1_000_000
    chunk = b'\x00' * 65536
    server = socket.create_server(('127.0.0.1', 0))
    port = server.getsockname()[1]

    def serve() -> None:
        for _ in range(2):
            conn, _ = server.accept()
            with conn:
                data = b''
                while b'\r\n\r\n' not in data:
                    data += conn.recv(4096)
                conn.sendall(b'HTTP/1.1 101 Switching Protocols\r\n\r\n')
                sent = 0
                while sent < total:
                    conn.sendall(chunk)
                    sent += len(chunk)

    def read_all(to_port: int) -> float:
        with socket.create_connection(('127.0.0.1', to_port)) as sock:
            sock.sendall(b'GET / HTTP/1.1\r\nSec-WebSocket-Protocol: foxglove.websocket.v1'
                         b'\r\n\r\n')
            buffer = bytearray(1 << 20)
            got, start = 0, time.perf_counter()
            head = b''
            while b'\r\n\r\n' not in head:
                head += sock.recv(4096)
            got = len(head.split(b'\r\n\r\n', 1)[1])
            total_wanted = -(-total // len(chunk)) * len(chunk)
            while got < total_wanted:
                n = sock.recv_into(buffer)
                if not n:
                    break
                got += n
            return got / 1e6 / (time.perf_counter() - start)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    proxy = HandshakeProxy('127.0.0.1', 0, port)
    try:
        direct = read_all(port)
        through = read_all(proxy.port)
    finally:
        proxy.close()
        server.close()
    return direct, through


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=20.0, help='CPU window [s]')
    parser.add_argument('--burst-hz', type=float, default=1000.0)
    parser.add_argument('--mbytes', type=int, default=500,
                        help='MB through the layer alone, and straight')
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
    viewers: dict[str, FoxgloveClient] = {}

    def publish(first: int, rate: float, count: int) -> subprocess.Popen:
        """A publisher that starts once the viewer is subscribed to both channels."""
        go = work / f'go{first}'
        proc = start([sys.executable, str(PUBLISHER), '--first-seq', str(first), '--rate',
                      f'{rate:g}', '--count', str(count), '--wait-subscribers', '2',
                      '--go-file', str(go)], f'publisher{first}')
        read_line(proc, 60, 'publisher matched')
        for client in viewers.values():
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
        # The next line, printed right after the URL (it may already be in stdout's buffer,
        # where read_line's select() does not see it; EOF if the bridge died: no match).
        sdk_port = re.search(r'on 127\.0\.0\.1:(\d+)', bridge.stdout.readline())
        if sdk_port is None:
            sys.exit('the bridge did not say where foxglove-sdk\'s server listens')
        sdk_port = sdk_port.group(1)
        viewers['layer'] = FoxgloveClient(url.group(0), subprotocols=['foxglove.websocket.v1'])
        viewers['direct'] = FoxgloveClient(f'ws://127.0.0.1:{sdk_port}',
                                           subprotocols=['foxglove.sdk.v1'])
        for client in viewers.values():
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
        layer_cpu0 = thread_cpu_seconds(bridge.pid, THREAD_NAME)
        window_start = time.monotonic()
        time.sleep(args.seconds)
        cpu1 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        layer_cpu1 = thread_cpu_seconds(bridge.pid, THREAD_NAME)
        elapsed = time.monotonic() - window_start
        cpu = {name: (cpu1[name] - cpu0[name]) / elapsed * 100.0 for name in pids}
        cpu['layer'] = (layer_cpu1 - layer_cpu0) / elapsed * 100.0
        read_line(publisher, 60, 'publisher end')
        publisher.wait(10)
        time.sleep(1.0)
        steady = {name: {t: len(c.received(t)) for t in TOPICS} for name, c in viewers.items()}
        latency = {name: viewer_latencies(c) for name, c in viewers.items()}
        added = added_by_layer(viewers['direct'], viewers['layer'])

        burst_count = round(args.burst_hz * BURST_S)
        burst = publish(1_000_000, args.burst_hz, burst_count)
        done = read_line(burst, 60, 'burst end')
        burst_sent = int(done.rsplit(' ', 1)[1])
        time.sleep(1.5)
        burst_viewer = {name: {t: len(c.received(t)) - steady[name][t] for t in TOPICS}
                        for name, c in viewers.items()}
        rate = {name: sum(receive_rate(c.received(t), steady[name][t]) for t in TOPICS)
                for name, c in viewers.items()}
        stop(baseline)
        base = json.loads(baseline_out.read_text())
    finally:
        for client in viewers.values():
            client.close()
        procs.close()
    capacity = layer_capacity(args.mbytes)

    base_steady = {t: base[t][:steady_count] for t in TOPICS}
    base_burst = {t: len(base[t]) - len(base_steady[t]) for t in TOPICS}
    all_base = base_steady['/pma/state'] + base_steady['/pma/prediction']
    v50, v99 = percentiles(latency['layer']['/pma/state'] + latency['layer']['/pma/prediction'])
    d50, d99 = percentiles(latency['direct']['/pma/state']
                           + latency['direct']['/pma/prediction'])
    a50, a99 = percentiles(added)
    a90 = float(np.percentile(np.asarray(added, dtype=float) / 1e6, 90))
    over_1ms = sum(1 for a in added if a > 1_000_000) / len(added) * 100.0
    b50, b99 = percentiles(all_base)
    lost_steady = {name: sum(steady_count - steady[name][t] for t in TOPICS)
                   for name in viewers}
    lost_burst = {name: sum(burst_sent - burst_viewer[name][t] for t in TOPICS)
                  for name in viewers}
    lost_base = {t: burst_sent - base_burst[t] for t in TOPICS}
    rows = [
        ('bridge CPU, 2 x 100 Hz, two viewers [% core]', f'{cpu["bridge"]:.1f}',
         '(/pma/state + /pma/prediction, raw CDR passed through)'),
        ('  of it the handshake layer\'s thread [% core]', f'{cpu["layer"]:.1f}',
         '(one viewer through it)'),
        ('baseline bare rclpy subscriber CPU [% core]', f'{cpu["baseline"]:.1f}',
         '(same topics, raw, callback notes the latency)'),
        ('CPU ratio bridge / baseline', f'{cpu["bridge"] / cpu["baseline"]:.2f}',
         f'(over {elapsed:.1f} s)'),
        ('latency p50 to the viewer through the layer [ms]', f'{v50:.2f}',
         '(publish stamp -> viewer socket)'),
        ('latency p50 to the viewer direct to the SDK [ms]', f'{d50:.2f}',
         '(today\'s path before the layer)'),
        ('latency p50 to the baseline [ms]', f'{b50:.2f}', '(publish stamp -> callback)'),
        ('latency p50 ratio bridge (layer) / baseline', f'{v50 / b50:.2f}', ''),
        ('latency p50 ratio layer / direct', f'{v50 / d50:.2f}', ''),
        ('latency p99 through the layer [ms]', f'{v99:.2f}', ''),
        ('latency p99 direct [ms]', f'{d99:.2f}', ''),
        ('latency p99 to the baseline [ms]', f'{b99:.2f}', ''),
        ('latency p99 ratio bridge (layer) / baseline', f'{v99 / b99:.2f}', ''),
        ('latency p99 ratio layer / direct', f'{v99 / d99:.2f}', ''),
        ('added by the layer, per message, p50 [ms]', f'{a50:.3f}',
         f'(arrival through it - arrival direct, {len(added)} messages)'),
        ('added by the layer, per message, p90 [ms]', f'{a90:.3f}', ''),
        ('added by the layer, per message, p99 [ms]', f'{a99:.3f}',
         f'({over_1ms:.0f} % of the messages over 1 ms)'),
        ('steady: messages published per topic', f'{steady_count}', ''),
        ('steady: lost on the way, layer / direct', f'{lost_steady["layer"]} / '
         f'{lost_steady["direct"]}', check(not any(lost_steady.values()), '0')),
        (f'burst {args.burst_hz:g} Hz x {BURST_S:g} s: published per topic', f'{burst_sent}',
         ''),
        ('burst: lost on the way, layer / direct', f'{lost_burst["layer"]} / '
         f'{lost_burst["direct"]}', check(not any(lost_burst.values()), '0')),
        ('burst: lost on the way to the baseline', f'{sum(lost_base.values())}', ''),
        ('burst: received rate through the layer [msg/s]', f'{rate["layer"]:.0f}',
         '(both topics)'),
        ('burst: received rate direct [msg/s]', f'{rate["direct"]:.0f}', ''),
        ('burst: throughput ratio layer / direct', f'{rate["layer"] / rate["direct"]:.2f}',
         ''),
        (f'layer alone: {args.mbytes} MB straight [MB/s]', f'{capacity[0]:.0f}',
         '(127.0.0.1, no ROS)'),
        (f'layer alone: {args.mbytes} MB through it [MB/s]', f'{capacity[1]:.0f}',
         f'(ratio {capacity[1] / capacity[0]:.2f}; the rig needs about 0.03)'),
        load_row(),
    ]
    print_table(rows)


if __name__ == '__main__':
    main()
