"""model_node service round trip, stream latency, drops at 1 kHz and CPU.

    . tools/env.sh && python bench/bench_model_node.py [--seconds 10] [--calls 500]

* service: sequential calls from this process to model_node's `pressure_for_length`
  (length_m=0.27, branch=1), interleaved with calls to a trivial std_srvs/Trigger server
  (a minimal rclpy node process started here: the baseline); p50/p99 of both and the ratios
  model / trigger (target <= 1.5).
* stream latency: a publisher process sends PmaState on pma/state at 100 Hz (header stamped
  with its ROS clock, monotonic send time kept per stamp); the PmaPrediction with the same
  header stamp is received here; p50/p99 of publish -> prediction received (target p99 < 5 ms).
* drops at 1 kHz: PmaState published vs PmaPrediction received (target 0), split with
  model_node's own /diagnostics 'samples' count into the best-effort state subscription and
  the reliable prediction topic.
* model_node CPU (utime + stime from /proc) at 100 Hz and 1 kHz, % of one core.
"""

from __future__ import annotations

import argparse
import math
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from benchlib import check, cpu_seconds, isolate_ros_graph, load_row, print_table, read_line, stop
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

from pma_interfaces.msg import PmaPrediction, PmaState
from pma_interfaces.srv import PressureForLength

ROOT = Path(__file__).resolve().parents[1]
MODEL_NODE = ROOT / 'ros2_ws' / 'install' / 'pma_model' / 'lib' / 'pma_model' / 'model_node'
TRIGGER_SERVICE = 'bench_trigger'
WARMUP_CALLS = 50
SETTLE_S = 1.0        # publishing before the CPU / latency window opens
TAIL_S = 1.0          # publishing after it closes


# --- helper processes (run as `bench_model_node.py --trigger-server` / `--publish ...`) -----

def trigger_server_main() -> None:
    """Baseline server: std_srvs/Trigger answered with a constant, nothing else in the node."""
    rclpy.init()
    node = rclpy.create_node('bench_trigger_server')

    def on_trigger(_request, response):
        response.success = True
        return response

    node.create_service(Trigger, TRIGGER_SERVICE, on_trigger)
    print('ready', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    node.destroy_node()
    rclpy.try_shutdown()


def publisher_main(rate_hz: float, seconds: float, out: str) -> None:
    """PmaState on pma/state at rate_hz; saves (stamp ns, monotonic send ns, seq) to out."""
    rclpy.init()
    node = rclpy.create_node('bench_state_publisher')
    # driver_node's default data QoS (reliable, depth 10); model_node's best-effort
    # subscription makes the delivery best effort.
    publisher = node.create_publisher(PmaState, 'pma/state', QoSProfile(depth=10))
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            print('no subscriber', flush=True)
            sys.exit(1)
        time.sleep(0.02)
    time.sleep(0.5)                       # let the match settle on both sides
    count = round(rate_hz * seconds)
    stamps = np.zeros(count, dtype=np.int64)
    sent = np.zeros(count, dtype=np.int64)
    period = 1.0 / rate_hz
    clock = node.get_clock()
    print('publishing', flush=True)
    start = time.monotonic()
    for seq in range(count):
        delay = start + seq * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        t = seq * period
        msg = PmaState(seq=seq, device_time_s=t,
                       gauge_pressure_pa=250_000.0 + 5_000.0 * math.sin(2 * math.pi * 0.5 * t),
                       length_m=0.26, gauge_setpoint_pa=250_000.0,
                       valve_state=PmaState.VALVE_HOLD, status=0, pressure_adc=512,
                       echo_us=1500)
        now = clock.now()
        msg.header.stamp = now.to_msg()
        msg.header.frame_id = 'muscle'
        sent[seq] = time.monotonic_ns()
        publisher.publish(msg)
        stamps[seq] = now.nanoseconds
    elapsed = time.monotonic() - start
    np.save(out, np.array([stamps, sent, np.arange(count)], dtype=np.int64))
    print(f'done {count} {elapsed:.3f}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def percentiles(values_ms: np.ndarray) -> tuple[float, float]:
    if len(values_ms) == 0:
        return math.nan, math.nan
    return float(np.percentile(values_ms, 50)), float(np.percentile(values_ms, 99))


# --- the bench ------------------------------------------------------------------------------

class Bench:
    def __init__(self, work: Path):
        self.work = work
        self.procs: list[subprocess.Popen] = []
        self.logs = []
        self.executor: SingleThreadedExecutor | None = None
        self.spinner: threading.Thread | None = None
        self.predictions: list[tuple[int, int]] = []     # (header stamp ns, receive mono ns)
        self.diagnostics: list[tuple[int, int]] = []     # (receive mono ns, samples)
        self.pressure_answer = math.nan

    def start(self, argv: list[str], name: str, pipe: bool = False) -> subprocess.Popen:
        log = open(self.work / f'{name}.log', 'w')  # closed in close()
        self.logs.append(log)
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE if pipe else log, stderr=log,
                                text=True, start_new_session=True)
        self.procs.append(proc)
        return proc

    def log_tail(self, name: str) -> str:
        path = self.work / f'{name}.log'
        return path.read_text()[-2000:] if path.exists() else ''

    def close(self) -> None:
        for proc in reversed(self.procs):
            stop(proc)
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=2)
        if self.spinner is not None:
            self.spinner.join(5)
        for log in self.logs:
            log.close()

    # service round trip ---------------------------------------------------------------

    def services(self, calls: int) -> dict[str, np.ndarray]:
        trigger = self.start([sys.executable, __file__, '--trigger-server'], 'trigger_server',
                             pipe=True)
        read_line(trigger, 30, 'trigger server start')
        node = rclpy.create_node('bench_model_node_client')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        model_request = PressureForLength.Request(length_m=0.27, branch=1)
        clients = {
            'model': (node.create_client(PressureForLength, 'pressure_for_length'),
                      model_request),
            'trigger': (node.create_client(Trigger, TRIGGER_SERVICE), Trigger.Request()),
        }
        for name, (client, _) in clients.items():
            if not client.wait_for_service(timeout_sec=30):
                raise TimeoutError(f'{name} service not available within 30 s')
        times: dict[str, list[int]] = {name: [] for name in clients}
        order = list(clients)
        retries = 0
        for i in range(WARMUP_CALLS + calls):
            order.reverse()                  # alternate who goes first
            for name in order:
                client, request = clients[name]
                while True:
                    start = time.perf_counter_ns()
                    future = client.call_async(request)
                    deadline = time.monotonic() + 5.0
                    # Not executor.spin_until_future_complete: in this rclpy (7.1.x) every
                    # call leaves never-run wake-up tasks in the executor, so a long-lived
                    # executor gets slower with each call (ms after a few hundred calls;
                    # ros2/rclpy#1374). A spin_once loop is the lean client.
                    while not future.done() and time.monotonic() < deadline:
                        executor.spin_once(timeout_sec=0.5)
                    end = time.perf_counter_ns()
                    if future.done():
                        break
                    client.remove_pending_request(future)
                    retries += 1
                    # A request sent right after discovery can be lost (the server's reply
                    # writer not matched yet): tolerated in the warm-up only.
                    if i >= WARMUP_CALLS or retries > 5:
                        raise TimeoutError(f'{name}: no response within 5 s (call {i})')
                response = future.result()
                if not response.success:
                    raise RuntimeError(f'{name} call failed: {getattr(response, "message", "")}')
                if name == 'model':
                    self.pressure_answer = response.gauge_pressure_pa
                if i >= WARMUP_CALLS:
                    times[name].append(end - start)
        executor.remove_node(node)
        executor.shutdown()
        node.destroy_node()
        stop(trigger)
        return {name: np.array(t) / 1e6 for name, t in times.items()}

    # stream --------------------------------------------------------------------------

    def start_listener(self) -> None:
        node = rclpy.create_node('bench_model_node_listener')

        def on_prediction(msg: PmaPrediction) -> None:
            now = time.monotonic_ns()
            stamp = msg.header.stamp
            self.predictions.append((stamp.sec * 1_000_000_000 + stamp.nanosec, now))

        def on_diagnostics(msg: DiagnosticArray) -> None:
            now = time.monotonic_ns()
            for status in msg.status:
                if 'model_node' not in status.name:
                    continue
                for kv in status.values:
                    if kv.key == 'samples':
                        self.diagnostics.append((now, int(kv.value)))

        node.create_subscription(PmaPrediction, 'pma/prediction', on_prediction,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(node)
        self.spinner = threading.Thread(target=self._spin, daemon=True)
        self.spinner.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def samples_settled(self, after_ns: int, timeout: float) -> int:
        """model_node's 'samples' once two reports received after after_ns agree."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            fresh = [s for t, s in self.diagnostics if t > after_ns]
            if len(fresh) >= 2 and fresh[-1] == fresh[-2]:
                return fresh[-1]
            time.sleep(0.1)
        raise TimeoutError(f'model_node /diagnostics did not settle within {timeout:.0f} s')

    def stream(self, model: subprocess.Popen, rate_hz: float, seconds: float) -> StreamRun:
        samples_before = self.samples_settled(time.monotonic_ns(), 10)
        self.predictions = []
        out = self.work / f'published_{rate_hz:g}.npy'
        name = f'publisher_{rate_hz:g}'
        publisher = self.start([sys.executable, __file__, '--publish', str(rate_hz),
                                str(SETTLE_S + seconds + TAIL_S), str(out)], name, pipe=True)
        line = read_line(publisher, 30, 'state publisher start')
        if line != 'publishing':
            raise RuntimeError(f'state publisher: {line} {self.log_tail(name)}')
        time.sleep(SETTLE_S)
        cpu0, start = cpu_seconds(model.pid), time.monotonic_ns()
        time.sleep(seconds)
        end = time.monotonic_ns()
        cpu = (cpu_seconds(model.pid) - cpu0) / ((end - start) / 1e9) * 100.0
        done = read_line(publisher, seconds + 60, 'state publisher end').split()
        publisher.wait(10)
        samples_after = self.samples_settled(time.monotonic_ns(), 15)
        if done[0] != 'done' or not out.exists():
            raise RuntimeError(f'state publisher: {done}')
        stamps, sent, _ = np.load(out)
        received = dict(self.predictions)
        latency = []
        for stamp, sent_ns in zip(stamps.tolist(), sent.tolist(), strict=True):
            got = received.get(stamp)
            if got is not None and start <= sent_ns < end:
                latency.append((got - sent_ns) / 1e6)
        missing = np.array([s not in received for s in stamps.tolist()], dtype=bool)
        in_window = (sent >= start) & (sent < end)
        return StreamRun(rate_hz=rate_hz, published=len(stamps),
                         missing_by_part=(int(np.sum(missing & (sent < start))),
                                          int(np.sum(missing & in_window)),
                                          int(np.sum(missing & (sent >= end)))),
                         longest_gap=longest_run(missing),
                         publish_seconds=float(done[2]),
                         model_samples=samples_after - samples_before,
                         received=sum(1 for s in stamps.tolist() if s in received),
                         latency_ms=np.array(latency), cpu_percent=cpu,
                         window_published=int(np.sum(in_window)))


def longest_run(mask: np.ndarray) -> int:
    """Longest stretch of consecutive True values."""
    best = current = 0
    for value in mask.tolist():
        current = current + 1 if value else 0
        best = max(best, current)
    return best


@dataclass
class StreamRun:
    rate_hz: float
    published: int
    publish_seconds: float
    model_samples: int          # states model_node counted (its /diagnostics 'samples')
    received: int               # predictions received here, matched to a published stamp
    latency_ms: np.ndarray      # publish -> prediction received, send time in the window
    cpu_percent: float
    window_published: int
    missing_by_part: tuple[int, int, int]  # missing predictions: settle, window, tail
    longest_gap: int            # most consecutive states without a prediction


def run(args: argparse.Namespace, work: Path) -> list[tuple[str, str, str]]:
    rows: list[tuple[str, str, str]] = []
    bench = Bench(work)
    # Python's own SIGINT handling (KeyboardInterrupt), so Ctrl-C ends the run at once and
    # the finally below stops every process; rclpy's handler would only stop the executor.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        model = bench.start([str(MODEL_NODE), '--ros-args', '--log-level', 'warn'], 'model_node')
        times = bench.services(args.calls)
        p50 = {name: float(np.percentile(t, 50)) for name, t in times.items()}
        p99 = {name: float(np.percentile(t, 99)) for name, t in times.items()}
        rows.append(('service pressure_for_length p50 [ms]', f'{p50["model"]:.3f}',
                     f'({len(times["model"])} calls, answer '
                     f'{bench.pressure_answer / 1000:.1f} kPa)'))
        rows.append(('service pressure_for_length p99 [ms]', f'{p99["model"]:.3f}', ''))
        rows.append(('  baseline std_srvs/Trigger p50 [ms]', f'{p50["trigger"]:.3f}',
                     f'({len(times["trigger"])} calls, interleaved)'))
        rows.append(('  baseline std_srvs/Trigger p99 [ms]', f'{p99["trigger"]:.3f}', ''))
        for q, values in (('p50', p50), ('p99', p99)):
            ratio = values['model'] / values['trigger']
            rows.append((f'  ratio model / trigger {q}', f'{ratio:.2f}',
                         check(ratio <= 1.5, '<= 1.5')))

        bench.start_listener()
        slow = bench.stream(model, 100.0, args.seconds)
        fast = bench.stream(model, 1000.0, args.seconds)
        if len(slow.latency_ms) == 0:
            raise RuntimeError('no prediction received at 100 Hz: '
                               f'{slow.published} published, {slow.model_samples} seen by '
                               f'model_node\n{bench.log_tail("model_node")}')
        s50, s99 = percentiles(slow.latency_ms)
        rows.append(('latency PmaState -> PmaPrediction p50 [ms]', f'{s50:.2f}',
                     f'({len(slow.latency_ms)} of {slow.window_published} at 100 Hz)'))
        rows.append(('latency PmaState -> PmaPrediction p99 [ms]', f'{s99:.2f}',
                     check(s99 < 5.0, '< 5')))
        dropped = fast.published - fast.received
        rows.append(('1 kHz: PmaState published', f'{fast.published}',
                     f'(in {fast.publish_seconds:.2f} s)'))
        rows.append(('1 kHz: PmaPrediction received', f'{fast.received}', ''))
        rows.append(('1 kHz: dropped', f'{dropped}', check(dropped == 0, '0')))
        rows.append(('  of which state -> model_node (best effort)',
                     f'{fast.published - fast.model_samples}', "(model_node 'samples')"))
        rows.append(('  of which prediction -> here (reliable, depth 10)',
                     f'{fast.model_samples - fast.received}', ''))
        before, inside, after = fast.missing_by_part
        rows.append(('  dropped in the steady window', f'{inside}',
                     f'({fast.window_published} sent; {before} in the {SETTLE_S:g} s before, '
                     f'{after} in the {TAIL_S:g} s after; longest run {fast.longest_gap})'))
        rows.append(('  100 Hz: dropped (state / prediction)',
                     f'{slow.published - slow.received}',
                     f'({slow.published - slow.model_samples} / '
                     f'{slow.model_samples - slow.received})'))
        f50, f99 = percentiles(fast.latency_ms)
        rows.append(('  latency at 1 kHz p50 / p99 [ms]', f'{f50:.2f}', f'/ {f99:.2f}'))
        rows.append(('model_node CPU at 100 Hz [% core]', f'{slow.cpu_percent:.1f}', ''))
        rows.append(('model_node CPU at 1 kHz [% core]', f'{fast.cpu_percent:.1f}', ''))
    finally:
        bench.close()
        rclpy.try_shutdown()
    rows.append(load_row())
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=10.0,
                        help='measuring window of each stream rate [s]')
    parser.add_argument('--calls', type=int, default=500, help='service calls per server')
    parser.add_argument('--trigger-server', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--publish', nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.trigger_server:
        trigger_server_main()
        return
    if args.publish:
        publisher_main(float(args.publish[0]), float(args.publish[1]), args.publish[2])
        return
    isolate_ros_graph()
    if not MODEL_NODE.exists():
        sys.exit(f'{MODEL_NODE} not found: run `make setup`')
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))   # clean up on SIGTERM too
    work = Path(tempfile.mkdtemp(prefix='bench_model_node_'))
    rows = run(args, work)
    shutil.rmtree(work, ignore_errors=True)        # kept (logs) when the run failed
    print_table(rows)


if __name__ == '__main__':
    main()
