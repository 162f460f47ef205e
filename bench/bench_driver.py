"""driver_node throughput, latency and CPU, fed by a device on a real pty.

    . tools/env.sh && python bench/bench_driver.py [--seconds 5]

* throughput: the device writes samples as fast as the pty takes them; samples published
  per second by driver_node (seen by a subscriber in this process, sequence gaps counted),
  and the ratio to a bare pyserial readline loop on the same kind of pty (target >= 2000/s).
* latency: a line written at 100 Hz -> its PmaState received here (same clock); p50/p99
  (target p99 < 5 ms).
* CPU of driver_node (utime + stime from /proc) at 20 Hz and 1 kHz, % of one core.
* under the length controller's traffic (50 Hz samples, 50 Hz pma/pressure_setpoint), in
  several fresh starts: CPU and latency p99 / worst per start. rclpy's MultiThreadedExecutor
  fell into spinning at 100 % CPU in about one start in three here, samples then up to 3 s
  late (docs/driver.md, Threads); the latency is reported as a ratio to the 100 Hz run.
"""

from __future__ import annotations

import argparse
import os
import select
import subprocess
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
import serial
from benchlib import cpu_seconds, isolate_ros_graph, load_row, print_table, stop
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile
from std_msgs.msg import Float64

from pma_common import names, protocol
from pma_interfaces.msg import PmaState

ROOT = Path(__file__).resolve().parents[1]
DRIVER = ROOT / 'ros2_ws' / 'install' / 'pma_driver' / 'lib' / 'pma_driver' / 'driver_node'
FLAT_OUT_LINES = 200_000


class BenchDevice:
    """Protocol-v1 device on a pty: answers commands; streams paced or flat out."""

    def __init__(self, rate_hz: float | None):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.rate_hz = rate_hz          # None: as fast as the pty drains
        self.written_ns: dict[int, int] = {}
        self.started = threading.Event()   # set once the host's HELLO arrived
        self.stop = threading.Event()
        self.seq = 0
        self._lock = threading.Lock()
        if rate_hz is None:
            # Built before streaming, so writing costs only os.write (no GIL-bound encoding).
            lines = [self._line(i) for i in range(FLAT_OUT_LINES)]
            self._chunks = [b''.join(lines[i:i + 64]) for i in range(0, len(lines), 64)]
        threading.Thread(target=self._commands, daemon=True).start()
        threading.Thread(target=self._stream, daemon=True).start()

    def close(self) -> None:
        self.stop.set()
        time.sleep(0.1)
        os.close(self.master)
        os.close(self.slave)

    def _write(self, data: bytes) -> None:
        with self._lock:
            view = memoryview(data)
            while view:
                view = view[os.write(self.master, view):]

    def _commands(self) -> None:
        decoder = protocol.FrameDecoder(parse=protocol.parse_host_line)
        while not self.stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            if self.stop.is_set():
                return
            for cmd in decoder.feed(data):
                if cmd.command == 'HELLO':
                    self._write(protocol.encode_ack('HELLO') + protocol.encode_hello(
                        protocol.Hello(1, 'bench', '0', 20, 100_000, 500_000, 500_000, 1000)))
                    self.started.set()
                elif cmd.command != 'HB':
                    try:
                        self._write(protocol.encode_ack(cmd.command, *cmd.args[:1]))
                    except OSError:
                        return        # closed at the end of a run

    def _line(self, t_ms: int) -> bytes:
        line = protocol.encode_sample(protocol.Sample(self.seq, t_ms % protocol.U32, 200, 583,
                                                      0, 0, 0))
        self.seq += 1
        return line

    def _stream(self) -> None:
        chunks = getattr(self, '_chunks', [])
        self.started.wait()
        t0 = time.monotonic()
        sent = 0
        while not self.stop.is_set():
            try:
                if self.rate_hz is None:
                    if sent >= len(chunks):
                        return
                    self._write(chunks[sent])
                    sent += 1
                    continue
                due = int((time.monotonic() - t0) * self.rate_hz) + 1
                for _ in range(due - sent):
                    seq = self.seq
                    line = self._line(int((time.monotonic() - t0) * 1000))
                    self.written_ns[seq] = time.monotonic_ns()
                    self._write(line)
                sent = max(sent, due)
            except OSError:
                return
            time.sleep(min(0.001, 0.5 / self.rate_hz))


def subscriber_main(out: str, setpoint_hz: float) -> None:
    """Child process: record (seq, receive time) of every PmaState until SIGINT; optionally
    stream pressure setpoints as the length controller does."""
    rclpy.init()
    node = rclpy.create_node('bench_driver_probe')
    if setpoint_hz > 0:
        setpoints = node.create_publisher(Float64, names.PRESSURE_SETPOINT, 10)
        node.create_timer(1.0 / setpoint_hz, lambda: setpoints.publish(
            Float64(data=100_000.0 + 50_000.0 * np.sin(time.monotonic()))))
    seqs: list[int] = []
    times: list[int] = []

    def on_state(msg: PmaState) -> None:
        times.append(time.monotonic_ns())
        seqs.append(msg.seq)
        if len(seqs) == 1:
            print('first', flush=True)

    diagnostics: list[tuple[int, int, int]] = []   # (receive ns, published, lost)

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            if 'samples published' in values:
                diagnostics.append((time.monotonic_ns(), int(values['samples published']),
                                    int(values['lost samples'])))

    node.create_subscription(PmaState, names.STATE, on_state, QoSProfile(depth=1000))
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    np.save(out, np.array([seqs, times], dtype=np.int64))
    np.save(out.replace('.npy', '_diag.npy'), np.array(diagnostics, dtype=np.int64))
    node.destroy_node()
    rclpy.try_shutdown()


def start_driver(port: str, rate_hz: float) -> subprocess.Popen:
    return subprocess.Popen(
        [str(DRIVER), '--ros-args', '-p', f'port:={port}', '-p', f'sample_rate_hz:={rate_hz}',
         '-p', 'qos_depth:=1000', '--log-level', 'warn'],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.05)


def run_driver(rate_hz: float | None, seconds: float, work: Path, setpoint_hz: float = 0.0,
               run_name: str = ''):
    """Driver fed by a BenchDevice; returns (device, [(seq, receive ns)], CPU % of one core)."""
    name = run_name or f'{rate_hz}'
    out = work / f'received_{name}.npy'
    errors = open(work / f'subscriber_{name}.log', 'w')  # closed after the run
    subscriber = subprocess.Popen([sys.executable, __file__, '--subscribe', str(out),
                                   '--setpoint-hz', str(setpoint_hz)],
                                  stdout=subprocess.PIPE, stderr=errors, text=True,
                                  start_new_session=True)
    device = BenchDevice(rate_hz)
    driver = start_driver(device.port, rate_hz or 1000.0)
    try:
        ready, _, _ = select.select([subscriber.stdout], [], [], 30)
        if not ready or subscriber.stdout.readline().strip() != 'first':
            raise TimeoutError('no PmaState reached the subscriber within 30 s')
        time.sleep(1.0)                     # settle (discovery, clock sync)
        cpu0, start = cpu_seconds(driver.pid), time.monotonic_ns()
        time.sleep(seconds)
        end = time.monotonic_ns()
        cpu = (cpu_seconds(driver.pid) - cpu0) / ((end - start) / 1e9) * 100.0
    finally:
        stop(driver)
        stop(subscriber)
        errors.close()
        device.close()
    if not out.exists():
        sys.exit(f'the subscriber wrote no results: {Path(errors.name).read_text()[-2000:]}')
    seqs, times = np.load(out)
    window = (times >= start) & (times < end)
    received = list(zip(seqs[window].tolist(), times[window].tolist(), strict=True))
    diag = np.load(str(out).replace('.npy', '_diag.npy'))
    diag = diag[(diag[:, 0] >= start) & (diag[:, 0] < end)] if len(diag) else diag
    return Run(device, received, cpu, diag)


@dataclass
class Run:
    device: BenchDevice
    received: list[tuple[int, int]]      # (seq, receive ns) at the subscriber
    cpu_percent: float
    diagnostics: np.ndarray              # rows: receive ns, samples published, lost samples

    def published_rate(self) -> float:
        """Samples/s driver_node published (its own count, from /diagnostics)."""
        d = self.diagnostics
        return (d[-1, 1] - d[0, 1]) / ((d[-1, 0] - d[0, 0]) / 1e9) if len(d) > 1 else 0.0

    def lost(self) -> int:
        """Samples the driver saw missing from the device's sequence in the window."""
        return int(self.diagnostics[-1, 2] - self.diagnostics[0, 2]) if len(
            self.diagnostics) > 1 else -1


def latencies_ms(run: Run) -> np.ndarray:
    """Device write -> PmaState received, per sample [ms]."""
    written = run.device.written_ns
    return np.array([(t - written[s]) / 1e6 for s, t in run.received if s in written])


def bare_readline_rate(seconds: float) -> float:
    """Lines/s a plain pyserial readline loop (its own process) gets from the same device."""
    device = BenchDevice(None)
    try:
        out = subprocess.run([sys.executable, __file__, '--bare', device.port, str(seconds)],
                             capture_output=True, text=True, timeout=seconds + 60, check=True)
    finally:
        device.close()
    return float(out.stdout.strip())


def bare_main(port_name: str, seconds: float) -> None:
    port = serial.Serial(port_name, 115200, timeout=0.5)
    port.write(protocol.encode_command(protocol.Command.HELLO))
    while not port.readline().startswith(b'$S'):
        pass
    count = 0
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        if port.readline().startswith(b'$S'):
            count += 1
    print(count / (time.monotonic() - start))
    port.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=5.0)
    parser.add_argument('--starts', type=int, default=6,
                        help='fresh driver starts under setpoint traffic')
    parser.add_argument('--subscribe', help=argparse.SUPPRESS)
    parser.add_argument('--setpoint-hz', type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument('--bare', nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.subscribe:
        subscriber_main(args.subscribe, args.setpoint_hz)
        return
    if args.bare:
        bare_main(args.bare[0], float(args.bare[1]))
        return
    isolate_ros_graph()
    if not DRIVER.exists():
        sys.exit(f'{DRIVER} not found: run `make setup`')
    work = Path(tempfile.mkdtemp(prefix='bench_driver_'))
    rows = []
    bare = bare_readline_rate(args.seconds)
    flat = run_driver(None, args.seconds, work)
    published = flat.published_rate()
    seqs = np.array([s for s, _ in flat.received], dtype=np.int64)
    sub_gaps = int(np.sum(np.diff(seqs) - 1)) if len(seqs) > 1 else 0
    rows.append(('throughput, flat out: published [samples/s]', f'{published:.0f}', '>= 2000'))
    rows.append(('  samples lost device -> driver (seq gaps)', f'{flat.lost()}', '0'))
    rows.append(('  bare pyserial readline [lines/s]', f'{bare:.0f}', ''))
    rows.append(('  ratio driver / bare readline', f'{published / bare:.2f}', ''))
    rows.append(('  received by a Python subscriber [samples/s]',
                 f'{len(flat.received) / args.seconds:.0f}', f'({sub_gaps} not delivered)'))
    rows.append(('  driver CPU flat out [% core]', f'{flat.cpu_percent:.0f}', ''))
    paced = run_driver(100.0, max(args.seconds, 10.0), work)
    latency_ms = latencies_ms(paced)
    rows.append(('latency line -> PmaState p50 [ms]', f'{np.percentile(latency_ms, 50):.2f}',
                 f'({len(latency_ms)} samples at 100 Hz)'))
    rows.append(('latency line -> PmaState p99 [ms]', f'{np.percentile(latency_ms, 99):.2f}',
                 '< 5'))
    for rate_hz in (20.0, 1000.0):
        run = run_driver(rate_hz, args.seconds, work)
        rows.append((f'driver CPU at {rate_hz:g} Hz [% core]', f'{run.cpu_percent:.1f}',
                     f'({run.published_rate():.0f} samples/s published)'))
    baseline_p99 = np.percentile(latency_ms, 99)
    cpus, p99s, worst = [], [], []
    for start in range(args.starts):
        run = run_driver(50.0, max(args.seconds, 20.0), work, setpoint_hz=50.0,
                         run_name=f'setpoints_{start}')
        latency = latencies_ms(run)
        cpus.append(run.cpu_percent)
        p99s.append(np.percentile(latency, 99))
        worst.append(latency.max())
    rows.append((f'50 Hz + 50 Hz setpoints, {args.starts} starts: driver CPU [% core]',
                 ' / '.join(f'{c:.0f}' for c in cpus), '< 30 each (a spinning executor: ~100)'))
    rows.append(('  latency p99 / 100 Hz run p99, worst start',
                 f'{max(p99s) / baseline_p99:.2f}', f'(p99 {max(p99s):.2f} ms)'))
    rows.append(('  latency worst sample, worst start [ms]', f'{max(worst):.1f}',
                 '(a starved link thread: 100s of ms)'))
    rows.append(load_row())
    print_table(rows)


if __name__ == '__main__':
    main()
