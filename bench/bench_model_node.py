"""model_node service round trip and burst, stream latency, drops at 1 kHz, CPU, and soaks.

    . tools/env.sh && python bench/bench_model_node.py [--seconds 10] [--calls 2000]
        [--burst-rounds 5] [--soak-s 300] [--soak-rates-hz 1000 100]

* service: sequential calls from this process to model_node's `pressure_for_length`
  (length_m=0.27, branch=1), interleaved with calls to a trivial std_srvs/Trigger server
  (a minimal rclpy node process started here, with the same service QoS: the baseline);
  p50/p99 of both and the ratios model / trigger (target <= 1.5). 2000 calls each, so that
  a p99 stands on 20 calls, not 5 (how far 500 let it wander: docs/model-history.md).
* burst: 4 client processes (tests/helpers/service_burst.py) each send 50 requests at once,
  200 in flight; every request must be answered (target: all). Rounds alternate between
  model_node and the Trigger server; p50/p99 from send to answer, and the ratio.
* stream latency: a publisher process sends PmaState on pma/state at 100 Hz (header stamped
  with its ROS clock, monotonic send time kept per stamp); the PmaPrediction with the same
  header stamp is received here; p50/p99 of publish -> prediction received. Baseline: a bare
  relay process (each state straight back out with its header, model_node's QoS) fed the
  same states at the same time; p99 ratio model / relay (target <= 1.5; the 5 ms budget
  the p99 is judged against is shown beside it).
* drops at 1 kHz: PmaState published vs PmaPrediction received (target 0), split with
  model_node's own /diagnostics 'samples' count into the state subscription and the
  prediction topic (both reliable).
* model_node CPU (utime + stime from /proc) at 100 Hz and 1 kHz, % of one core.
* soaks (--soak-s, 0 skips them): the real chain for that long at each of --soak-rates-hz:
  1 kHz, the stress (twenty times the firmware's 50 Hz: a laser or draw-wire sensor's
  rate), and 100 Hz, twice what the rig can send; the target at both is nothing lost:
  fake_arduino --rate R -> driver_node (sample_rate_hz R) -> a fresh model_node, with
  `ros2 run pma_bag record` on its default topics. Losses per component: device -> driver
  (driver's 'lost samples'), states published by driver_node that model_node never received
  (its 'samples', and by PmaState.seq its 'states_lost'), predictions model_node published
  that the recorder never received (bag), states the recorder never received (by seq, bag),
  and the states in the bag without their prediction in the bag (target under 0.1 %); CPU of
  each process.
It exits 1 when any target is missed (rows marked MISSED).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from benchlib import (
    check,
    cpu_seconds,
    isolate_ros_graph,
    load_row,
    print_table,
    read_line,
    serve,
    stop,
)
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger

from pma_common import names
from pma_common.background import BackgroundSpin
from pma_common.sequence import SequenceTracker
from pma_common.service import SERVICE_QOS
from pma_interfaces.msg import PmaPrediction, PmaState
from pma_interfaces.srv import PressureForLength
from pma_model.model_node import PREDICTION_QUEUE_DEPTH, STATE_QUEUE_DEPTH

ROOT = Path(__file__).resolve().parents[1]
INSTALL = ROOT / 'ros2_ws' / 'install'
MODEL_NODE = INSTALL / 'pma_model' / 'lib' / 'pma_model' / 'model_node'
FAKE_ARDUINO = INSTALL / 'pma_sim' / 'lib' / 'pma_sim' / 'fake_arduino'
DRIVER_NODE = INSTALL / 'pma_driver' / 'lib' / 'pma_driver' / 'driver_node'
RECORDER = INSTALL / 'pma_bag' / 'lib' / 'pma_bag' / 'record'
BURST_CLIENT = ROOT / 'tests' / 'helpers' / 'service_burst.py'
BURST_CLIENTS = 4
BURST_PER_CLIENT = 50
TRIGGER_SERVICE = 'bench_trigger'
RELAYED_TOPIC = 'bench_relayed_prediction'
STREAM_P99_RATIO = 1.5     # model_node's state -> prediction p99 against the relay's
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

    node.create_service(Trigger, TRIGGER_SERVICE, on_trigger, qos_profile=SERVICE_QOS)
    serve(node)


def relay_main() -> None:
    """Baseline of the stream latency: each state straight back out as a PmaPrediction with
    its header, taken and sent with model_node's QoS, nothing else in the node."""
    rclpy.init()
    node = rclpy.create_node('bench_relay')
    publisher = node.create_publisher(PmaPrediction, RELAYED_TOPIC, PREDICTION_QUEUE_DEPTH)
    node.create_subscription(
        PmaState, names.STATE, lambda msg: publisher.publish(PmaPrediction(header=msg.header)),
        QoSProfile(depth=STATE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE))
    serve(node)


def publisher_main(rate_hz: float, seconds: float, out: str, subscribers: int) -> None:
    """PmaState on pma/state at rate_hz, once `subscribers` match; saves (stamp ns,
    monotonic send ns, seq) to out."""
    rclpy.init()
    node = rclpy.create_node('bench_state_publisher')
    # driver_node's default data QoS (reliable, qos_depth 1000).
    publisher = node.create_publisher(PmaState, names.STATE, QoSProfile(depth=1000))
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < subscribers:
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
        self.listener: BackgroundSpin | None = None
        self.predictions: list[tuple[int, int]] = []     # (header stamp ns, receive mono ns)
        self.relayed: list[tuple[int, int]] = []         # the same, from the relay
        self.diagnostics: list[tuple[int, int]] = []     # (receive mono ns, samples)
        self.node_values: dict[str, dict[str, str]] = {}  # node name -> last diagnostics
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
        if self.listener is not None:
            self.listener.close()
        for log in self.logs:
            log.close()

    # service round trip ---------------------------------------------------------------

    def start_trigger_server(self) -> subprocess.Popen:
        trigger = self.start([sys.executable, __file__, '--trigger-server'], 'trigger_server',
                             pipe=True)
        read_line(trigger, 30, 'trigger server start')
        return trigger

    def services(self, calls: int) -> dict[str, np.ndarray]:
        node = rclpy.create_node('bench_model_node_client')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        model_request = PressureForLength.Request(length_m=0.27, branch=1)
        clients = {
            'model': (node.create_client(PressureForLength, names.PRESSURE_FOR_LENGTH),
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
        return {name: np.array(t) / 1e6 for name, t in times.items()}

    # burst ---------------------------------------------------------------------------

    def burst(self, rounds: int) -> dict[str, dict]:
        """Bursts of BURST_CLIENTS x BURST_PER_CLIENT requests, model and trigger in turn."""
        go_dir = self.work / 'burst'
        go_dir.mkdir()
        clients = [self.start([sys.executable, str(BURST_CLIENT), '--count',
                               str(BURST_PER_CLIENT), '--go-dir', str(go_dir), '--services',
                               f'pressure_for_length,{TRIGGER_SERVICE}'], f'burst_client{i}',
                              pipe=True) for i in range(BURST_CLIENTS)]
        for i, client in enumerate(clients):
            line = read_line(client, 60, 'burst client start')
            if line != 'ready':
                raise RuntimeError(f'burst client: {line} {self.log_tail(f"burst_client{i}")}')
        results = {name: {'sent': 0, 'answered': 0, 'latency_ms': []}
                   for name in ('model', 'trigger')}
        services = {'model': names.PRESSURE_FOR_LENGTH, 'trigger': TRIGGER_SERVICE}
        order = ['model', 'trigger']
        for round_ in range(2 * rounds):
            name = order[round_ % 2] if (round_ // 2) % 2 == 0 else order[1 - round_ % 2]
            go = go_dir / f'.go-{round_}'
            go.write_text(services[name])
            go.rename(go_dir / f'go-{round_}')      # every client sees it at once, whole
            for client in clients:
                result = json.loads(read_line(client, 90, f'burst round {round_}'))
                results[name]['sent'] += result['sent']
                results[name]['answered'] += result['answered']
                results[name]['latency_ms'] += result['latency_ms']
        (go_dir / 'stop').touch()
        for client in clients:
            stop(client)
        return results

    # soak ------------------------------------------------------------------------------

    def latest_values(self, node_name: str) -> dict[str, str]:
        """The last /diagnostics values of a node (its status name starts with /node_name:)."""
        return dict(self.node_values.get(node_name, {}))

    def settled(self, node_name: str, keys: tuple[str, ...], timeout: float) -> dict[str, str]:
        """A node's diagnostics values once two reports in a row agree on `keys`."""
        deadline = time.monotonic() + timeout
        previous = None
        while time.monotonic() < deadline:
            time.sleep(1.1)
            values = self.latest_values(node_name)
            current = tuple(values.get(key) for key in keys)
            if None not in current and current == previous:
                return values
            previous = current
        raise TimeoutError(f'{node_name} /diagnostics {keys} did not settle in {timeout:.0f} s')

    def soak(self, seconds: float, rate_hz: float) -> Soak:
        work = self.work / f'soak_{rate_hz:g}'
        work.mkdir()
        port, bag = work / 'ttyPMA', work / 'bag'
        for node in ('driver_node', 'model_node'):   # a soak before this one left its values
            self.node_values.pop(node, None)
        fake = self.start([str(FAKE_ARDUINO), '--link', str(port), '--rate', f'{rate_hz:g}'],
                          'soak_fake_arduino')
        deadline = time.monotonic() + 30
        while not port.exists():
            if time.monotonic() > deadline or fake.poll() is not None:
                raise RuntimeError(f'fake_arduino: {self.log_tail("soak_fake_arduino")}')
            time.sleep(0.05)
        model = self.start([str(MODEL_NODE), '--ros-args', '--log-level', 'warn'],
                           'soak_model_node')
        self.samples_settled(time.monotonic_ns(), 30)     # model_node is up and reporting
        recorder = self.start([str(RECORDER), '-o', str(bag)], 'soak_recorder')
        # Subscribed to model_node's three topics (up already) before the first state exists.
        self.wait_for(lambda: any(int(n) >= 3 for n in re.findall(
            r'recording (\d+) topics', self.log_tail('soak_recorder'))), 30, 'recorder start')
        driver = self.start([str(DRIVER_NODE), '--ros-args', '-p', f'port:={port}',
                             '-p', f'sample_rate_hz:={float(rate_hz)}', '--log-level', 'warn'],
                            'soak_driver_node')
        self.wait_for(lambda: int(self.latest_values('driver_node').get(
            'samples published', 0)) > rate_hz, 30, 'driver_node publishing')   # a second
        procs = {'fake_arduino': fake, 'driver_node': driver, 'model_node': model,
                 'recorder': recorder}
        cpu0 = {name: cpu_seconds(proc.pid) for name, proc in procs.items()}
        start = time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - start
        cpu = {name: (cpu_seconds(proc.pid) - cpu0[name]) / elapsed * 100.0
               for name, proc in procs.items()}
        load = os.getloadavg()[0]
        # The stream ends with driver_node deactivated, its publisher still there: a
        # backlog in model_node's queue is then still predicted (stopping the device or the
        # driver instead would end the soak on a loss of its own).
        self.deactivate('driver_node')
        driver_values = self.settled('driver_node', ('samples published',), 30)
        model_values = self.settled('model_node', ('samples', 'states_lost'), 30)
        stop(recorder)                               # closes the bag
        for proc in (driver, fake, model):
            stop(proc)
        states, predictions = read_soak_bag(bag)
        tracker = SequenceTracker()
        for seq in states.values():
            tracker.add(seq)
        first_predicted = min(predictions, default=0)
        first_stamp = min(states, default=0)
        missed = sorted((states[stamp], (stamp - first_stamp) / 1e9) for stamp in states
                        if stamp >= first_predicted and stamp not in predictions)
        return Soak(rate_hz=rate_hz, seconds=elapsed,
                    published=int(driver_values['samples published']),
                    device_lost=int(driver_values['lost samples']),
                    model_samples=int(model_values['samples']),
                    model_states_lost=int(model_values['states_lost']),
                    model_state_gaps=int(model_values['state_gaps']),
                    bag_states=len(states), bag_states_lost=tracker.stats().lost,
                    bag_predictions=len(predictions),
                    bag_states_without_prediction=len(set(states) - predictions),
                    bag_states_before_model=sum(1 for stamp in states if stamp < first_predicted),
                    unpredicted_runs=runs_of(missed),
                    cpu_percent=cpu, load=load)

    def deactivate(self, lifecycle_node: str) -> None:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        node = rclpy.create_node('bench_model_node_lifecycle')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            client = node.create_client(ChangeState, f'{lifecycle_node}/change_state')
            if not client.wait_for_service(timeout_sec=10):
                raise TimeoutError(f'{lifecycle_node}/change_state not available')
            future = client.call_async(ChangeState.Request(
                transition=Transition(id=Transition.TRANSITION_DEACTIVATE)))
            deadline = time.monotonic() + 10
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
            if not future.done() or not future.result().success:
                raise RuntimeError(f'{lifecycle_node} did not deactivate')
        finally:
            executor.shutdown()
            node.destroy_node()

    def wait_for(self, predicate, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise TimeoutError(f'{what}: not within {timeout:.0f} s')
            time.sleep(0.1)

    # stream --------------------------------------------------------------------------

    def stop_listening_to_predictions(self) -> None:
        self._listener_node.destroy_subscription(self._prediction_sub)

    def start_listener(self) -> None:
        node = rclpy.create_node('bench_model_node_listener')

        def arrival(msg: PmaPrediction) -> tuple[int, int]:
            now = time.monotonic_ns()
            stamp = msg.header.stamp
            return stamp.sec * 1_000_000_000 + stamp.nanosec, now

        def on_prediction(msg: PmaPrediction) -> None:
            self.predictions.append(arrival(msg))

        def on_relayed(msg: PmaPrediction) -> None:
            self.relayed.append(arrival(msg))

        def on_diagnostics(msg: DiagnosticArray) -> None:
            now = time.monotonic_ns()
            for status in msg.status:
                node_name = status.name.split(':', 1)[0].rsplit('/', 1)[-1]
                self.node_values[node_name] = {kv.key: kv.value for kv in status.values}
                if node_name != 'model_node':
                    continue
                for kv in status.values:
                    if kv.key == 'samples':
                        self.diagnostics.append((now, int(kv.value)))

        self._listener_node = node
        self._prediction_sub = node.create_subscription(
            PmaPrediction, names.PREDICTION, on_prediction,
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(PmaPrediction, RELAYED_TOPIC, on_relayed,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
        self.listener = BackgroundSpin(node)

    def samples_settled(self, after_ns: int, timeout: float) -> int:
        """model_node's 'samples' once two reports received after after_ns agree."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            fresh = [s for t, s in self.diagnostics if t > after_ns]
            if len(fresh) >= 2 and fresh[-1] == fresh[-2]:
                return fresh[-1]
            time.sleep(0.1)
        raise TimeoutError(f'model_node /diagnostics did not settle within {timeout:.0f} s')

    def stream(self, model: subprocess.Popen, rate_hz: float, seconds: float,
               relay: bool = False) -> StreamRun:
        """`relay`: the baseline relay takes the same states meanwhile (its latency too)."""
        samples_before = self.samples_settled(time.monotonic_ns(), 10)
        self.predictions, self.relayed = [], []
        relay_proc = None
        if relay:
            relay_proc = self.start([sys.executable, __file__, '--relay'], 'relay', pipe=True)
            read_line(relay_proc, 30, 'relay start')
            self.wait_for(lambda: self._listener_node.count_publishers(RELAYED_TOPIC) >= 1,
                          30, 'relay publisher')
        out = self.work / f'published_{rate_hz:g}.npy'
        name = f'publisher_{rate_hz:g}'
        publisher = self.start([sys.executable, __file__, '--publish', str(rate_hz),
                                str(SETTLE_S + seconds + TAIL_S), str(out),
                                str(1 + relay)], name, pipe=True)
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
        if relay_proc is not None:
            stop(relay_proc)
        stamps, sent, _ = np.load(out)
        received = dict(self.predictions)

        def latency_ms(arrivals: dict[int, int]) -> np.ndarray:
            return np.array([(arrivals[stamp] - sent_ns) / 1e6 for stamp, sent_ns
                             in zip(stamps.tolist(), sent.tolist(), strict=True)
                             if stamp in arrivals and start <= sent_ns < end])

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
                         latency_ms=latency_ms(received),
                         relay_latency_ms=latency_ms(dict(self.relayed)), cpu_percent=cpu,
                         window_published=int(np.sum(in_window)))


def read_soak_bag(bag: Path) -> tuple[dict[int, int], set[int]]:
    """({state header stamp ns: seq}, {prediction header stamp ns}) of a recorded bag."""
    from rclpy.serialization import deserialize_message

    from pma_bag import BagReader

    states: dict[int, int] = {}
    predictions: set[int] = set()
    with BagReader(bag) as reader:
        topics = {name: info.type_name for name, info in reader.topics.items()}
        wanted = [name for name, kind in topics.items()
                  if kind in ('pma_interfaces/msg/PmaState', 'pma_interfaces/msg/PmaPrediction')]
        for message in reader.messages(wanted):
            if topics[message.topic] == 'pma_interfaces/msg/PmaState':
                state = deserialize_message(message.data, PmaState)
                stamp = state.header.stamp
                states[stamp.sec * 1_000_000_000 + stamp.nanosec] = state.seq
            else:
                stamp = deserialize_message(message.data, PmaPrediction).header.stamp
                predictions.add(stamp.sec * 1_000_000_000 + stamp.nanosec)
    return states, predictions


@dataclass
class Soak:
    rate_hz: float
    seconds: float
    published: int              # PmaState published by driver_node ('samples published')
    device_lost: int            # device -> driver_node, by the device's seq
    model_samples: int          # states model_node received
    model_states_lost: int      # by seq, as model_node counted (device losses included)
    model_state_gaps: int
    bag_states: int             # distinct states in the bag
    bag_states_lost: int        # by seq, inside the recorded span (device losses included)
    bag_predictions: int
    bag_states_without_prediction: int
    # Of those, the states recorded before the first one model_node received (it predicts
    # every state it gets): the recorder matched the new driver's publisher first, in DDS
    # discovery at start-up, 2.2-2.5 s at 1 kHz on this machine whatever the model costs.
    bag_states_before_model: int
    # Where the rest were: (first seq, count, seconds into the bag) of each run of
    # consecutive states without a prediction, for the next look at a loss.
    unpredicted_runs: list[tuple[int, int, float]]
    cpu_percent: dict[str, float]
    load: float


def runs_of(missed: list[tuple[int, float]]) -> list[tuple[int, int, float]]:
    """(first seq, count, time) of each run of consecutive seqs in sorted (seq, time)."""
    runs: list[list] = []
    for seq, at_s in missed:
        if runs and seq == runs[-1][0] + runs[-1][1]:
            runs[-1][1] += 1
        else:
            runs.append([seq, 1, at_s])
    return [tuple(run) for run in runs]


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
    relay_latency_ms: np.ndarray  # the same through the relay (empty: no relay in the run)
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
        trigger = bench.start_trigger_server()
        times = bench.services(args.calls)
        bursts = bench.burst(args.burst_rounds) if args.burst_rounds else None
        stop(trigger)
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

        if bursts is not None:
            model_burst, trigger_burst = bursts['model'], bursts['trigger']
            answered = model_burst['answered']
            rows.append((f'burst: {BURST_CLIENTS} clients x {BURST_PER_CLIENT} requests in '
                         'flight, answered', f'{answered}',
                         check(answered == model_burst['sent'],
                               f'all {model_burst["sent"]} ({args.burst_rounds} bursts)')))
            b50, b99 = percentiles(np.array(model_burst['latency_ms']))
            t50, t99 = percentiles(np.array(trigger_burst['latency_ms']))
            rows.append(('  burst send -> answer p50 / p99 [ms]', f'{b50:.2f}', f'/ {b99:.2f}'))
            rows.append(('  baseline Trigger burst p50 / p99 [ms]', f'{t50:.2f}',
                         f'/ {t99:.2f} ({trigger_burst["answered"]} of '
                         f'{trigger_burst["sent"]} answered)'))
            # No latency target: a burst waits in the queue, so its p99 is the time to serve
            # all 200, and says how much more each request costs model_node than a bare node.
            rows.append(('  ratio model / trigger burst p50 / p99',
                         f'{b50 / t50:.2f}', f'/ {b99 / t99:.2f}'))

        bench.start_listener()
        slow = bench.stream(model, 100.0, args.seconds, relay=True)
        fast = bench.stream(model, 1000.0, args.seconds)
        if len(slow.latency_ms) == 0:
            raise RuntimeError('no prediction received at 100 Hz: '
                               f'{slow.published} published, {slow.model_samples} seen by '
                               f'model_node\n{bench.log_tail("model_node")}')
        s50, s99 = percentiles(slow.latency_ms)
        r50, r99 = percentiles(slow.relay_latency_ms)
        rows.append(('latency PmaState -> PmaPrediction p50 [ms]', f'{s50:.2f}',
                     f'({len(slow.latency_ms)} of {slow.window_published} at 100 Hz)'))
        rows.append(('latency PmaState -> PmaPrediction p99 [ms]', f'{s99:.2f}',
                     '(budget 5 ms: ' + ('within' if s99 < 5.0 else 'over') + ')'))
        rows.append(('  baseline relay p50 / p99 [ms]', f'{r50:.2f}',
                     f'/ {r99:.2f} ({len(slow.relay_latency_ms)} of the same states)'))
        rows.append(('  ratio model / relay p50 / p99', f'{s50 / r50:.2f}',
                     f'/ {s99 / r99:.2f} ' + check(s99 / r99 <= STREAM_P99_RATIO,
                                                   f'p99 <= {STREAM_P99_RATIO:g}')))
        dropped = fast.published - fast.received
        rows.append(('1 kHz: PmaState published', f'{fast.published}',
                     f'(in {fast.publish_seconds:.2f} s)'))
        rows.append(('1 kHz: PmaPrediction received', f'{fast.received}', ''))
        rows.append(('1 kHz: dropped', f'{dropped}', check(dropped == 0, '0')))
        rows.append(('  of which state -> model_node (reliable)',
                     f'{fast.published - fast.model_samples}', "(model_node 'samples')"))
        rows.append((f'  of which prediction -> here (reliable, depth {PREDICTION_QUEUE_DEPTH})',
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
        if args.soak_s > 0:
            stop(model)
            # The soak judges whether the rig's chain fits the machine: this process must not
            # be a fifth 1 kHz subscriber beside the recorder (it took 30-40 % of a core).
            bench.stop_listening_to_predictions()
            for rate_hz in args.soak_rates_hz:
                rows += soak_rows(bench.soak(args.soak_s, rate_hz))
    finally:
        bench.close()
        rclpy.try_shutdown()
    rows.append(load_row())
    return rows


# Issue 47's target for the soaks: under this share of the bag's states without a prediction.
MAX_WITHOUT_PREDICTION_PERCENT = 0.1


def soak_rows(soak: Soak) -> list[tuple[str, str, str]]:
    # By seq, inside the stream each subscriber saw, less what the device itself lost; the
    # rest of `published - samples` went out before the subscription had matched the new
    # publisher (discovery at start-up: a volatile topic does not keep them).
    model_lost = max(soak.model_states_lost - soak.device_lost, 0)
    before_match = soak.published - soak.model_samples - model_lost
    recorder_lost = max(soak.bag_states_lost - soak.device_lost, 0)
    not_recorded = soak.model_samples - soak.bag_predictions
    # The target is the chain's capacity, so it counts from model_node's first state on;
    # what the recorder had before that is reported beside it.
    unpredicted = soak.bag_states_without_prediction - soak.bag_states_before_model
    percent = 100.0 * unpredicted / max(soak.bag_states - soak.bag_states_before_model, 1)
    cpu = ', '.join(f'{name} {value:.0f}' for name, value in soak.cpu_percent.items())
    return [
        (f'soak {soak.rate_hz:g} Hz, {soak.seconds:.0f} s: PmaState published by driver_node',
         f'{soak.published}', '(fake_arduino -> driver_node -> model_node, recorder)'),
        ('  device -> driver_node lost (serial)', f'{soak.device_lost}', ''),
        ('  states model_node never received (by seq)', f'{model_lost}',
         check(model_lost == 0, '0') + f' ({soak.model_state_gaps} gaps; '
         f'{soak.model_samples} received, {before_match} sent before it matched)'),
        ('  predictions the recorder never received', f'{not_recorded}',
         check(not_recorded == 0, '0') + f' ({soak.bag_predictions} of '
         f'{soak.model_samples} in the bag)'),
        ('  states the recorder never received (by seq)', f'{recorder_lost}',
         f'({soak.bag_states} in the bag)'),
        ('  states in the bag without their prediction', f'{unpredicted}',
         check(percent < MAX_WITHOUT_PREDICTION_PERCENT,
               f'< {MAX_WITHOUT_PREDICTION_PERCENT:g} %') + f' ({percent:.3f} %, from '
         'model_node\'s first state on)'),
        ('  states recorded before model_node had one', f'{soak.bag_states_before_model}',
         '(start-up: the recorder matched the driver first)'),
        ('  runs without a prediction (seq x count at s)', f'{len(soak.unpredicted_runs)}',
         ', '.join(f'{seq} x {count} at {at_s:.1f}'
                   for seq, count, at_s in soak.unpredicted_runs[:5])
         + (' ...' if len(soak.unpredicted_runs) > 5 else '')),
        ('  CPU [% core]', f'{sum(soak.cpu_percent.values()):.0f}',
         f'({cpu}; load average {soak.load:.1f})'),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=10.0,
                        help='measuring window of each stream rate [s]')
    parser.add_argument('--calls', type=int, default=2000, help='service calls per server')
    parser.add_argument('--burst-rounds', type=int, default=5,
                        help=f'bursts of {BURST_CLIENTS} x {BURST_PER_CLIENT} requests per '
                             'server (0 skips)')
    parser.add_argument('--soak-s', type=float, default=300.0,
                        help='length of each soak through driver, model and recorder [s] '
                             '(0 skips them)')
    parser.add_argument('--soak-rates-hz', type=float, nargs='+', default=[1000.0, 100.0],
                        metavar='HZ', help='sample rate of each soak (default 1000 100)')
    parser.add_argument('--trigger-server', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--publish', nargs=4, help=argparse.SUPPRESS)
    parser.add_argument('--relay', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.trigger_server:
        trigger_server_main()
        return
    if args.publish:
        publisher_main(float(args.publish[0]), float(args.publish[1]), args.publish[2],
                       int(args.publish[3]))
        return
    if args.relay:
        relay_main()
        return
    isolate_ros_graph()
    if not MODEL_NODE.exists():
        sys.exit(f'{MODEL_NODE} not found: run `make setup`')
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))   # clean up on SIGTERM too
    work = Path(tempfile.mkdtemp(prefix='bench_model_node_'))
    rows = run(args, work)                         # an error leaves `work` (its logs)
    print_table(rows)
    missed = [name.strip() for name, _, target in rows if target.startswith('MISSED')]
    if missed:
        print(f'\nmissed: {"; ".join(missed)}\nthe processes\' logs and the bags: {work}')
        sys.exit(1)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == '__main__':
    main()
