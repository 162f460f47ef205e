"""Length control: the controller modes on every simulated muscle, and the loop latency.

    . tools/env.sh && python bench/bench_control.py [--seconds 20] [--families NAME ...]
                                                    [--device-seeds N ...] [--load 2]
                                                    [--latency-only]

* tracking (ROS-free, simulated time, the simulated device's own sensors and regulator;
  the true length is known only to the evaluation), on every simulated muscle family and
  the Bouc-Wen muscle (--set tuning|validation: that set of pma_sim.splits instead; the
  validation set's figures are reported, never tuned on): feedforward only ('ff'),
  feedback only ('fb'), feedforward + feedback ('ff_fb') on
  - steps 25.5 -> 28.5 -> 26.5 cm: settle time to +/-2 mm of the truth, overshoot, steady
    error (mean of the last 2 s of each step);
  - sines 25 <-> 29.5 cm at 0.05, 0.1 and 0.2 Hz: RMSE and max error against the truth in %
    of Table 1's stroke (5.86 cm), after the first period.
  Targets: ff_fb RMSE at 0.1 Hz <= 2 % of stroke and <= 1/2 of fb's, on every muscle;
  steady error within the HC-SR04's 3 mm resolution. The 0.1 Hz sine again with every
  setpoint reaching the device 50 ms late (DDS, serial line and firmware; gains must not be
  tuned to a zero-delay simulation): ff_fb still <= 2 %; and 150 ms late (a loaded host),
  reported. Every run is repeated on several device seeds (sensor noise, valve timing;
  --device-seeds, six by default, two processes): one seed's 0.1 Hz RMSE moved by up to
  10 % with the seed. The table gives the mean over seeds and the worst one; the targets
  hold on the worst.
* loop latency over DDS at 50 Hz: a publisher process sends pma/state; length_controller
  (holding a target) answers each with pma/pressure_setpoint and then pma/control_state,
  whose header is the state's; this process receives all three and takes, per state, the
  setpoint's arrival - that state's arrival: the control state names its state (by stamp,
  not the latest state) and the command it sent, which pairs it with its setpoint message
  (CommandMatcher). Baseline: a bare relay node (state in, a ControlState with its header
  out) measured the same way in the same run, alternating with the controller. On a quiet
  machine and again with --load busy processes beside it (2 by default: a load average of
  about 2 on the two cores of the development machine, issue 47's condition). Target: the
  setpoint's p99 under load at most RELAY_P99_RATIO times the relay's p99 in the same run;
  the absolute figure is reported (docs/control.md says why it is not the target).
  --latency-only skips the tracking table.
It exits 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from benchlib import check, isolate_ros_graph, load_row, print_table, read_line, serve, stop

from pma_common import names
from pma_control.simulated_runs import sine_error_m, sine_profile
from pma_control.simulated_runs import track as run
from pma_sim import splits
from pma_sim.evaluation import SCORED_FAMILIES, STROKE_M
from pma_sim.registry import family_argument

ROOT = Path(__file__).resolve().parents[1]
CONTROLLER = ROOT / 'ros2_ws' / 'install' / 'pma_control' / 'lib' / 'pma_control' / \
    'length_controller'
MODES = ('ff', 'fb', 'ff_fb')
STEPS = ((0.0, 0.255), (10.0, 0.285), (20.0, 0.265))
STEP_END_S = 30.0
SINE_HZ = (0.05, 0.1, 0.2)
TOLERANCE_M = 0.002
# Setpoint to device: ~10-50 ms on a quiet host (DDS, serial line, the firmware's next loop),
# 150 ms seen on a loaded one. The 2 % target holds up to DELAY_TARGET_S.
COMMAND_DELAYS_S = (0.05, 0.15)
DELAY_TARGET_S = 0.05
# The loop's latency target under load, against a bare relay timed in the same run: the
# model's work per state may at most double what DDS and the scheduler already cost. An
# absolute bound would judge the machine: the relay alone has a p99 of 6-12 ms at a load
# average of 2 on the 2-core development machine.
RELAY_P99_RATIO = 2.0
RESOLUTION_M = 0.003


# --- tracking on the simulated muscles -----------------------------------------------------

DEVICE_SEEDS = tuple(range(11, 17))


def step_profile(t_s: float) -> float:
    return [length for start, length in STEPS if t_s >= start][-1]


def step_metrics(t, true, _reference) -> dict[str, float]:
    settle, overshoot, steady = [], [], []
    for k in range(1, len(STEPS)):
        start, target = STEPS[k]
        end = STEPS[k + 1][0] if k + 1 < len(STEPS) else STEP_END_S
        inside = (t >= start) & (t < end)
        error, since = true[inside] - target, t[inside] - start
        outside = np.nonzero(np.abs(error) > TOLERANCE_M)[0]
        if outside.size == 0:
            settle.append(0.0)
        elif outside[-1] + 1 < since.size:
            settle.append(float(since[outside[-1] + 1]))
        else:
            settle.append(math.inf)
        direction = np.sign(target - STEPS[k - 1][1])
        overshoot.append(max(0.0, float(np.max(error * direction))))
        steady.append(abs(float(np.mean(error[since > since[-1] - 2.0]))))
    return {'settle_s': max(settle), 'overshoot_mm': 1000 * max(overshoot),
            'steady_mm': 1000 * max(steady)}


def sine_metrics(t, true, reference, frequency_hz: float) -> dict[str, float]:
    error = sine_error_m(t, true, reference, frequency_hz)
    return {'rmse_pct': 100 * float(np.sqrt(np.mean(error ** 2))) / STROKE_M,
            'max_pct': 100 * float(np.max(np.abs(error))) / STROKE_M}


def tracking_runs(family: str, seed: int) -> dict[str, object]:
    """Every run of one muscle on one device seed (a process of the pool runs it)."""
    runs: dict[str, object] = {}
    for mode in MODES:
        runs[mode] = {'steps': step_metrics(*run(mode, family, step_profile, STEP_END_S,
                                                 seed=seed))}
        for frequency in SINE_HZ:
            duration = 1.0 / frequency * 3 + 2.0
            runs[mode][frequency] = sine_metrics(*run(mode, family, sine_profile(frequency),
                                                      duration, seed=seed), frequency)
    for delay_s in COMMAND_DELAYS_S:
        runs[delay_s] = sine_metrics(*run('ff_fb', family, sine_profile(0.1), 32.0, seed=seed,
                                          command_delay_s=delay_s), 0.1)['rmse_pct']
    return runs


def spread(values) -> str:
    """'mean (worst)' of a figure over the device seeds."""
    values = np.asarray(values, dtype=float)
    if np.isinf(values).any():       # a step that never settled
        return f'never on {np.isinf(values).sum()}/{values.size}'
    return f'{values.mean():.2f} ({values.max():.2f})'


def tracking_table(families: list[str], seeds: tuple[int, ...]
                   ) -> tuple[list[tuple[str, str, str]], bool]:
    with ProcessPoolExecutor(min(2, os.cpu_count() or 1)) as pool:
        jobs = {(family, seed): pool.submit(tracking_runs, family, seed)
                for family in families for seed in seeds}
        by_seed = {key: job.result() for key, job in jobs.items()}
    print(f'device seeds {", ".join(map(str, seeds))}; mean over them, the worst in brackets',
          flush=True)
    print(f'{"muscle":<12}{"mode":<7}{"step settle [s]":>17}{"overshoot [mm]":>16}'
          f'{"steady [mm]":>14}' + ''.join(f'{f"{f:g} Hz RMSE %":>16}{"max %":>15}'
                                             for f in SINE_HZ), flush=True)
    rows, ok = [], True
    for family in families:
        runs = [by_seed[family, seed] for seed in seeds]
        for mode in MODES:
            steps = {key: [r[mode]['steps'][key] for r in runs] for key in runs[0][mode]['steps']}
            print(f'{family:<12}{mode:<7}{spread(steps["settle_s"]):>17}'
                  f'{spread(steps["overshoot_mm"]):>16}{spread(steps["steady_mm"]):>14}'
                  + ''.join(f'{spread([r[mode][f]["rmse_pct"] for r in runs]):>16}'
                            f'{spread([r[mode][f]["max_pct"] for r in runs]):>15}'
                            for f in SINE_HZ), flush=True)
        steady = max(r['ff_fb']['steps']['steady_mm'] for r in runs)
        steady_ok = steady <= RESOLUTION_M * 1000
        ok &= steady_ok
        rows.append((f'{family}: ff_fb steady error, worst seed [mm]', f'{steady:.2f}',
                     check(steady_ok, '<= 3 mm (sensor resolution)')))
        for delay_s in COMMAND_DELAYS_S:
            delayed = [r[delay_s] for r in runs]
            print(f'{family:<12}ff_fb with {1000 * delay_s:.0f} ms command delay: 0.1 Hz '
                  f'RMSE {spread(delayed)} %', flush=True)
            label = (f'{family}: ff_fb RMSE at 0.1 Hz, {1000 * delay_s:.0f} ms delay, '
                     'worst seed [% stroke]')
            if delay_s <= DELAY_TARGET_S:
                ok &= max(delayed) <= 2.0
                rows.append((label, f'{max(delayed):.2f}', check(max(delayed) <= 2.0, '<= 2 %')))
            else:
                rows.append((label, f'{max(delayed):.2f}', 'reported (a loaded host)'))
        combined = [r['ff_fb'][0.1]['rmse_pct'] for r in runs]
        ratios = [r['fb'][0.1]['rmse_pct'] / r['ff_fb'][0.1]['rmse_pct'] for r in runs]
        within, ratio_ok = max(combined) <= 2.0, min(ratios) >= 2.0
        ok &= within and ratio_ok
        rows.append((f'{family}: ff_fb RMSE at 0.1 Hz, worst seed [% stroke]',
                     f'{max(combined):.2f}',
                     check(within, '<= 2 %') + f'; mean {np.mean(combined):.2f}'))
        rows.append((f'{family}: fb / ff_fb RMSE at 0.1 Hz, worst seed', f'{min(ratios):.2f}',
                     check(ratio_ok, '>= 2') + f'; mean {np.mean(ratios):.2f}'))
    return rows, ok


# --- loop latency over DDS -----------------------------------------------------------------

def publisher_main(rate_hz: float) -> None:
    """PmaState on pma/state at rate_hz, like driver_node (reliable, depth 10), with the last
    pma/pressure_setpoint as the device's setpoint, as a device reports it (the controller
    lets go of a target when the device holds a setpoint it did not send)."""
    import rclpy
    from std_msgs.msg import Float64

    from pma_interfaces.msg import PmaState

    rclpy.init()
    node = rclpy.create_node('bench_state_publisher')
    publisher = node.create_publisher(PmaState, names.STATE, 10)
    seq = 0
    setpoint_pa = 0.0

    def on_setpoint(msg: Float64) -> None:
        nonlocal setpoint_pa
        setpoint_pa = float(round(msg.data))       # the driver sends whole Pa

    node.create_subscription(Float64, names.PRESSURE_SETPOINT, on_setpoint, 10)

    def tick():
        nonlocal seq
        msg = PmaState(seq=seq, gauge_pressure_pa=200_000.0 + 500.0 * math.sin(seq / 7.0),
                       length_m=0.27, gauge_setpoint_pa=setpoint_pa)
        msg.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(msg)
        seq += 1

    node.create_timer(1.0 / rate_hz, tick)
    serve(node)


def relay_main() -> None:
    """Baseline: every state straight back out as a ControlState with its header, nothing
    else in the node (the controller publishes its setpoint, then the same)."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data

    from pma_interfaces.msg import ControlState, PmaState

    rclpy.init()
    node = rclpy.create_node('bench_relay')
    publisher = node.create_publisher(ControlState, names.CONTROL_STATE, 10)
    node.create_subscription(PmaState, names.STATE,
                             lambda msg: publisher.publish(ControlState(header=msg.header)),
                             qos_profile_sensor_data)
    serve(node)


def busy_main() -> None:
    """A load: spin a core until stopped."""
    while True:
        pass


class CommandMatcher:
    """Pairs each control state that reports a command with the pma/pressure_setpoint message
    that carried it (the same value, the oldest first), whichever of the two arrives first:
    the command's arrival - its state's [ms]. A Float64 has no header, and its control state
    names the state it answers."""

    def __init__(self):
        self.commands: list[tuple[float, int]] = []      # (value, arrival) not yet paired
        self.waiting: list[tuple[float, int]] = []       # (value, state's arrival) unpaired
        self.latencies: list[float] = []

    def command(self, value: float, arrived_ns: int) -> None:
        state_ns = self._take(self.waiting, value)
        if state_ns is None:
            self.commands.append((value, arrived_ns))
        else:
            self.latencies.append((arrived_ns - state_ns) / 1e6)

    def control_state(self, value: float, state_ns: int) -> None:
        arrived_ns = self._take(self.commands, value)
        if arrived_ns is None:
            self.waiting.append((value, state_ns))
        else:
            self.latencies.append((arrived_ns - state_ns) / 1e6)

    @staticmethod
    def _take(pending: list[tuple[float, int]], value: float) -> int | None:
        """Remove the oldest entry of `pending` for `value`; its time, or None."""
        for k, (pending_value, ns) in enumerate(pending):
            if pending_value == value:
                del pending[k]
                return ns
        return None

    def clear(self) -> None:
        self.commands.clear()
        self.waiting.clear()
        self.latencies.clear()


def measure_latency(argv: list[str], seconds: float, needs_target: bool
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Start `argv` (the node between state and control state), measure for `seconds`: per
    state, its control state's arrival - its own, matched by header stamp, and its command's
    (pma/pressure_setpoint, CommandMatcher; none from the relay) [ms]."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64

    from pma_interfaces.msg import ControlState, LengthSetpoint, PmaState

    node = rclpy.create_node('bench_control_probe')
    lock = threading.Lock()
    state_at: dict[tuple[int, int], int] = {}
    latencies: list[float] = []
    commands = CommandMatcher()

    def stamp(msg) -> tuple[int, int]:
        return msg.header.stamp.sec, msg.header.stamp.nanosec

    def on_state(msg):
        with lock:
            state_at[stamp(msg)] = time.monotonic_ns()

    def on_control(msg):
        now = time.monotonic_ns()
        with lock:
            sent = state_at.pop(stamp(msg), None)
            if sent is not None:
                latencies.append((now - sent) / 1e6)
                if msg.mode in (ControlState.MODE_GOAL, ControlState.MODE_STREAM,
                                ControlState.MODE_HOLD):       # it sent a command first
                    commands.control_state(msg.gauge_pressure_command_pa, sent)

    def on_command(msg):
        now = time.monotonic_ns()
        with lock:
            commands.command(msg.data, now)

    node.create_subscription(PmaState, names.STATE, on_state, 100)
    node.create_subscription(ControlState, names.CONTROL_STATE, on_control, 100)
    node.create_subscription(Float64, names.PRESSURE_SETPOINT, on_command, 100)
    target = node.create_publisher(LengthSetpoint, names.LENGTH_SETPOINT, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not latencies:
            if needs_target:
                target.publish(LengthSetpoint(length_m=0.265))
            executor.spin_once(timeout_sec=0.1)
        with lock:
            latencies.clear()
            state_at.clear()
            commands.clear()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.1)
        with lock:
            return np.array(latencies), np.array(commands.latencies)
    finally:
        stop(proc)
        node.destroy_node()


def latency_rows(seconds: float, load: int) -> tuple[list[tuple[str, str, str]], bool]:
    """The controller against the relay, on a quiet machine and with `load` busy processes."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    publisher = subprocess.Popen([sys.executable, __file__, '--publish', '50'],
                                 stdout=subprocess.PIPE, text=True)
    rows, ok = [], True
    try:
        read_line(publisher, 30, 'state publisher')
        for busy_count in (0, load):
            busy = [subprocess.Popen([sys.executable, __file__, '--busy'])
                    for _ in range(busy_count)]
            try:
                runs = {'relay': [], 'controller': [], 'command': []}
                for _ in range(2):    # alternate, so a noisy moment does not favour one side
                    relay_run, _ = measure_latency([sys.executable, __file__, '--relay'],
                                                   seconds / 2, False)
                    runs['relay'].append(relay_run)
                    control_run, command_run = measure_latency([str(CONTROLLER)],
                                                               seconds / 2, True)
                    runs['controller'].append(control_run)
                    runs['command'].append(command_run)
                load_average = os.getloadavg()[0]
            finally:
                for proc in busy:
                    proc.kill()
                    proc.wait()
            relay, controller, command = (np.concatenate(runs[k])
                                          for k in ('relay', 'controller', 'command'))
            p50, p99 = np.percentile(command, [50, 99])
            c50, c99 = np.percentile(controller, [50, 99])
            r50, r99 = np.percentile(relay, [50, 99])
            where = (f'{busy_count} busy processes, load average {load_average:.1f}'
                     if busy_count else f'quiet, load average {load_average:.1f}')
            target_here = busy_count == load
            within = bool(p99 <= RELAY_P99_RATIO * r99)
            ok &= within or not target_here
            rows += [
                (f'loop latency state -> setpoint p50 [ms] ({where})', f'{p50:.2f}',
                 f'relay {r50:.2f} ms'),
                ('loop latency state -> setpoint p99 [ms]', f'{p99:.2f}', 'reported'),
                ('  p50 / relay p50', f'{p50 / r50:.2f}', f'{command.size} setpoints of '
                 f'{controller.size} states'),
                ('  p99 / relay p99', f'{p99 / r99:.2f}',
                 (check(within, f'<= {RELAY_P99_RATIO:g}') + '; ' if target_here else '')
                 + f'relay p99 {r99:.2f} ms, {relay.size} samples'),
                ('  state -> control state p50 / p99 [ms]', f'{c50:.2f} / {c99:.2f}',
                 'after the setpoint, with its explanation'),
            ]
    finally:
        stop(publisher)
        rclpy.try_shutdown()
    return rows, ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0, help='latency window')
    parser.add_argument('--families', nargs='+', type=family_argument,
                        help='only these simulated muscles (default: the scored ones; '
                             'any registered one: duhem:RISING:FALLING, gpi[:BULGE], '
                             'friction[:WIDEST], creep:INNER:SHARE:TAU; see '
                             'bench_memory_families.py --help)')
    parser.add_argument('--set', choices=tuple(splits.SETS), dest='muscle_set',
                        help='the families of this declared set (pma_sim.splits) instead')
    parser.add_argument('--device-seeds', nargs='+', type=int, default=DEVICE_SEEDS,
                        metavar='N', help='simulated device seeds (sensor noise, valve timing)')
    parser.add_argument('--load', type=int, default=2,
                        help='busy processes beside the second latency run (default 2)')
    parser.add_argument('--latency-only', action='store_true',
                        help='only the loop latency (no tracking table)')
    parser.add_argument('--publish', type=float, help=argparse.SUPPRESS)
    parser.add_argument('--relay', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--busy', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publisher_main(args.publish)
        return 0
    if args.relay:
        relay_main()
        return 0
    if args.busy:
        busy_main()
        return 0
    isolate_ros_graph()
    families = args.families or (splits.SETS[args.muscle_set].families if args.muscle_set
                                 else SCORED_FAMILIES)
    rows, ok = [], True
    if not args.latency_only:
        rows, ok = tracking_table(list(families), tuple(args.device_seeds))
    latency, latency_ok = latency_rows(args.seconds, args.load)
    print()
    print_table([*rows, *latency, load_row()])
    return 0 if ok and latency_ok else 1


if __name__ == '__main__':
    sys.exit(main())
