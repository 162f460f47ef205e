"""demo (`make demo`): the whole pipeline on the simulated rig, one run under runs/<timestamp>/.

fake_arduino, driver_node, model_node, the recorder and foxglove_live (the live view: open its
ws:// URL in Foxglove) run as separate processes, exactly as `ros2 run` starts them; this
script is the operator: it runs the paper's pressure levels and a minor-loop run through the Sweep
action, asks pressure_for_length on both branches, refits the model from the new bag (with
the time series and the minor loops against every model's prediction among its figures, all
stamped with the run id), lets model_node hot-load the refit, and says where everything is.
Every process is stopped on success, failure and Ctrl-C.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from pma_common import names
from pma_common.commands import installed_executable as executable
from pma_common.processes import STOP_STEPS, Child, start_child, stop_children
from pma_common.stop import STOP_SIGNALS, ignore_stop_signals


def say(text: str) -> None:
    print(f'[demo] {text}', flush=True)


class Processes:
    """Children in their own process groups, logs in the run directory, stopped in reverse;
    each ends with the demo if the demo ends without stopping it (pma_common.processes)."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.children: dict[str, Child] = {}

    def start(self, name: str, package: str, exe: str, *args: str,
              ros_args: list[str] | None = None) -> subprocess.Popen:
        argv = [str(executable(package, exe)), *args]
        if ros_args:
            argv += ['--ros-args', *ros_args]
        # Every child starts before the demo has a second thread (die_with_parent's rule).
        child = start_child(name, argv, log_path=self.log_dir / f'{name}.log',
                            die_with_parent=True)
        self.children[name] = child
        return child.popen

    def wait_for_log(self, name: str, text: str, timeout: float) -> str:
        path = self.log_dir / f'{name}.log'
        child = self.children[name].popen
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in path.read_text(errors='replace').splitlines():
                if text in line:
                    return line
            if child.poll() is not None:
                break
            time.sleep(0.05)
        tail = '\n'.join(path.read_text(errors='replace').splitlines()[-15:])
        raise RuntimeError(f'{name} did not say "{text}" within {timeout} s '
                           f'(exit code {child.poll()}); its log ({path}) ends:\n{tail}')

    def stop(self, name: str, timeout: float = 10.0) -> int | None:
        child = self.children[name]
        stop_children([child], ((signal.SIGINT, timeout), *STOP_STEPS[1:]))
        return child.popen.returncode

    def stop_all(self) -> None:
        for name in reversed(list(self.children)):
            if self.children[name].running():
                self.stop(name)


def start_live_view(procs: Processes, port: int) -> str | None:
    """foxglove_live, first, so a viewer can watch the whole run; its URL (None if it failed)."""
    procs.start('foxglove_live', 'pma_bringup', 'foxglove_live', ros_args=['-p', f'port:={port}'])
    try:
        url = re.search(r'ws://\S+', procs.wait_for_log('foxglove_live', 'ws://', 20)).group(0)
        layout = procs.wait_for_log('foxglove_live', 'layout: ', 5).split('layout: ', 1)[1]
    except RuntimeError as error:
        say(f'live view not available (the demo goes on without it): {error}')
        return None
    say(f'live view: {url}  (Foxglove desktop or web app -> Open connection -> '
        'Foxglove WebSocket)')
    say(f'   its layout: {layout.split(" (")[0]}  (Foxglove: Layouts -> Import from file)')
    return url


def progress_bar(fraction: float, width: int = 30) -> str:
    filled = round(max(0.0, min(1.0, fraction)) * width)
    return '#' * filled + '-' * (width - filled)


def run_sweep(spin, client, label: str, goal, timeout: float):
    """One Sweep goal through `client` (the demo's one pma/sweep action client); its
    requests are made on `spin`'s thread (pma_common.background)."""
    if not client.wait_for_server(timeout_sec=20):
        raise RuntimeError('the pma/sweep action server (driver_node) is not available')
    last_print = [0.0, -1]
    # On a terminal one line redrawn in place; in a log (CI, `| tee`) one line per step.
    interactive = sys.stdout.isatty()

    def on_feedback(message):
        feedback = message.feedback
        now = time.monotonic()
        if interactive:
            due = now - last_print[0] >= 1.0 or feedback.progress >= 1.0
        else:
            due = feedback.step_index != last_print[1]
        if due:
            last_print[:] = [now, feedback.step_index]
            start = '\r' if interactive else ''
            print(f'{start}[demo] {label}: '
                  f'[{progress_bar(feedback.progress)}] {100 * feedback.progress:5.1f} %  '
                  f'step {feedback.step_index + 1}/{feedback.step_count}  setpoint '
                  f'{feedback.gauge_setpoint_pa / 1e3:5.0f} kPa  {feedback.sample_count} samples',
                  end='' if interactive else '\n', flush=True)

    from pma_common.action import ServerWatch

    # Feedback is a sign of life: the wait ends if the driver goes away (its result lost).
    watch = ServerWatch(client, call=spin.call)

    def on_message(message) -> None:
        watch.alive()
        on_feedback(message)

    handle = spin.send_goal(client, goal, 20, 'the sweep goal to be accepted',
                            feedback_callback=on_message)
    if not handle.accepted:
        raise RuntimeError(f'{label}: the driver rejected the sweep goal (see driver_node.log)')
    try:
        response = spin.wait_for_result(client, handle, timeout, f'{label} to finish',
                                        server='driver_node (pma/sweep)', watch=watch)
    finally:
        if interactive:
            print(flush=True)
    result = response.result
    if not result.success:
        # The status tells a run that failed (ABORTED, with the driver's reason) from a goal
        # the driver no longer knew (UNKNOWN, empty result).
        raise RuntimeError(f'{label} failed (goal status {response.status}): '
                           f'{result.message or "no message; see driver_node.log"}')
    say(f'{label}: done, {result.sample_count} samples ({result.message})')
    return result


def _wait(future, timeout: float, what: str) -> None:
    from pma_common.service import poll

    if not poll(future.done, timeout):
        raise RuntimeError(f'timed out after {timeout:.0f} s waiting for {what}')


class ServiceClients:
    """The demo's service clients, made with its node before it spins and kept.

    Made just before its first call, a client's answer can be lost while the server's reply
    writer is still matching it (pma_common.service; a command is sent once), and made or
    destroyed while the node spins in its thread it can break the wait (rclpy, see the
    action clients in main).
    """

    def __init__(self, node):
        from rcl_interfaces.srv import SetParameters

        from pma_interfaces.srv import PressureForLength, StartRecording, StopRecording

        self.pressure_for_length = node.create_client(PressureForLength, names.PRESSURE_FOR_LENGTH)
        self.start_recording = node.create_client(StartRecording, 'recorder/start')
        self.stop_recording = node.create_client(StopRecording, 'recorder/stop')
        self.model_parameters = node.create_client(SetParameters, 'model_node/set_parameters')


def ask_pressures(client, lengths_m: list[float]) -> list[tuple]:
    """`client` is ServiceClients.pressure_for_length."""
    from pma_common.service import ask, poll
    from pma_interfaces.srv import PressureForLength

    if not client.wait_for_service(timeout_sec=20):
        raise RuntimeError('pressure_for_length (model_node) is not available')
    answers = []
    for branch in (PressureForLength.Request.BRANCH_INCREASING,
                   PressureForLength.Request.BRANCH_DECREASING,
                   PressureForLength.Request.BRANCH_AUTO):
        for length_m in lengths_m:
            answer = ask(client, PressureForLength.Request(length_m=length_m, branch=branch),
                         10, poll)
            if answer is None:
                raise RuntimeError('pressure_for_length (model_node) did not answer in 10 s')
            answers.append((length_m, branch, answer))
    return answers


def set_parameter(client, name: str, value: str) -> str:
    """`ros2 param set` of a string through `client` (a set_parameters client); the refusal's
    reason ('' if set). Setting a value twice is setting it once: resent while unanswered."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    from pma_common.service import ask, poll

    if not client.wait_for_service(timeout_sec=10):
        return f'nothing serves {client.srv_name}'
    response = ask(client, SetParameters.Request(parameters=[Parameter(
        name=name, value=ParameterValue(type=ParameterType.PARAMETER_STRING,
                                        string_value=value))]), 20, poll)
    if response is None:
        raise RuntimeError(f'timed out after 20 s waiting for {client.srv_name}')
    result = response.results[0]
    return '' if result.successful else result.reason


def record_bag(clients: ServiceClients, path: Path | None,
               custom_data: dict[str, str] | None = None) -> str:
    """Start (path, with its custom_data) or stop (None) a bag on the idle recorder; its
    answer's message. A start is sent again while unanswered, under one request_id."""
    from pma_common.service import ask, poll, start_recording_request
    from pma_interfaces.srv import StopRecording

    client, request = ((clients.start_recording,
                        start_recording_request(str(path), custom_data or {}))
                       if path is not None else (clients.stop_recording, StopRecording.Request()))
    if not client.wait_for_service(timeout_sec=10):
        raise RuntimeError('the recorder does not answer (see logs/recorder.log)')
    if path is not None:
        response = ask(client, request, 20, poll)
    else:
        future = client.call_async(request)
        _wait(future, 20, 'the recorder')
        response = future.result()
    if response is None:
        raise RuntimeError('timed out after 20 s waiting for the recorder')
    if not response.success:
        raise RuntimeError(f'recorder: {response.message}')
    return response.message


MOVE_TIMEOUT_S = 20.0   # each demo move's own timeout_s
MOVE_LATE_S = 20.0      # how much later than that its result may come before the demo gives up


def move_to(spin, client, length_m: float) -> str:
    """One MoveToLength goal (the fields `ros2 action send_goal` would send); a one-line
    summary."""
    from pma_interfaces.action import MoveToLength

    handle = spin.send_goal(client, MoveToLength.Goal(
        length_m=length_m, tolerance_m=0.002, settle_s=1.0, timeout_s=MOVE_TIMEOUT_S), 10,
        'move_to_length accepted')
    # The goal ends itself after its timeout_s; a server gone meanwhile ends the wait sooner.
    result = spin.wait_for_result(client, handle, MOVE_TIMEOUT_S + MOVE_LATE_S,
                                  'the move_to_length result',
                                  server='length_controller (pma/move_to_length)').result
    if not result.success:
        raise RuntimeError(f'move_to_length {length_m} m: {result.message}')
    return (f'{length_m * 100:.1f} cm: settled in {result.settle_time_s:.2f} s, '
            f'measured {result.measured_length_m * 100:.2f} cm (estimated '
            f'{result.estimated_length_m * 100:.2f} cm)')


def run_control(spin, client, services: ServiceClients, run_dir: Path, truth_csv: Path, *,
                rate_hz: float) -> list[tuple[str, Path]]:
    """Steps (through `client`, the pma/move_to_length action client) and a streamed sine
    through length_controller, recorded, plotted against the simulated truth (the run and the
    bag's metadata in the footer); the outputs."""
    import numpy as np
    from rclpy.qos import qos_profile_sensor_data

    from pma_control.plots import plot_control_run
    from pma_interfaces.msg import ControlState, LengthSetpoint, PmaState
    from pma_model.offline.provenance import input_run
    from pma_model.params import paper_table1
    from pma_sim.fake_arduino import TruthLog

    node = spin.node
    stroke_m = paper_table1().stroke_m
    steps: list = []
    seqs: dict[int, int] = {}
    node.create_subscription(ControlState, names.CONTROL_STATE, steps.append, 1000)
    node.create_subscription(
        PmaState, names.STATE,
        lambda s: seqs.__setitem__(s.header.stamp.sec * 10**9 + s.header.stamp.nanosec, s.seq),
        qos_profile_sensor_data)
    if not client.wait_for_server(timeout_sec=20):
        raise RuntimeError('no pma/move_to_length (see logs/length_controller.log)')
    bag = run_dir / 'control'
    record_bag(services, bag, {'run_id': run_dir.name,
                           'note': 'demo: MoveToLength steps, then a streamed 0.1 Hz sine'})
    begin = len(steps)
    for length_m in (0.255, 0.285, 0.265):
        say(f'   move_to_length {move_to(spin, client, length_m)}')
    say('   following a streamed sine, 25.0 <-> 29.5 cm at 0.1 Hz, for 25 s '
        '(pma/length_setpoint at 50 Hz)')
    setpoints = node.create_publisher(LengthSetpoint, names.LENGTH_SETPOINT, 10)
    start = time.time()
    while (now := time.time()) - start < 25.0:
        phase = 2 * math.pi * 0.1 * (now - start)
        setpoints.publish(LengthSetpoint(length_m=0.2725 - 0.0225 * math.cos(phase)))
        time.sleep(0.02)
    streamed_until = now
    time.sleep(0.5)
    say(f'   {record_bag(services, None)}')
    truth = TruthLog.true_lengths(truth_csv)
    rows = []
    for c in steps[begin:]:
        stamp = c.header.stamp.sec * 10**9 + c.header.stamp.nanosec
        if stamp in seqs and seqs[stamp] in truth:
            rows.append((stamp / 1e9, c.setpoint_length_m, c.measured_length_m,
                         truth[seqs[stamp]], c.gauge_pressure_command_pa, c.gauge_pressure_pa))
    if not rows:
        raise RuntimeError('no pma/control_state matched to the simulated truth')
    t, setpoint, measured, true, command, pressure = (np.array(c) for c in zip(*rows,
                                                                            strict=True))
    # The sine's second period on, while it was streamed: after the stream the controller
    # goes idle, with no setpoint (NaN), before the bag ends.
    sine = (t >= start + 10.0) & (t <= streamed_until)
    error = true[sine] - setpoint[sine]
    rmse = float(np.sqrt(np.mean(error ** 2)))
    say(f'   sine tracking against the simulated truth: RMSE {rmse * 1000:.2f} mm '
        f'({100 * rmse / stroke_m:.2f} % of stroke), max {1000 * np.max(np.abs(error)):.2f} mm')
    plot = plot_control_run(run_dir / 'plots' / 'control.png', t_s=t - t[0], target_m=setpoint,
                            measured_m=measured, command_pa=command, pressure_pa=pressure,
                            true_m=true, run=input_run(bag, run_dir.name),
                            title=f'length_controller: steps, then a 0.1 Hz sine '
                                  f'(simulated rig, {rate_hz:g} Hz)')
    return [('the control run (bag)', bag), ('the control run (plot)', plot)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--hold-s', type=float, default=1.0,
                        help='hold time at each pressure step [s] (default 1.0)')
    parser.add_argument('--rate-hz', type=float, default=50.0, help='sample rate (default 50)')
    parser.add_argument('--runs-dir', type=Path, default=Path('runs'),
                        help='where the run directory goes (default ./runs)')
    parser.add_argument('--live-port', type=int, default=8765,
                        help='TCP port of the live view (default 8765; 0 = any free port)')
    args = parser.parse_args(argv)

    run_dir = (args.runs_dir / datetime.datetime.now().strftime('%Y%m%d-%H%M%S')).resolve()
    logs = run_dir / 'logs'
    logs.mkdir(parents=True)
    procs = Processes(logs)
    started = time.monotonic()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(50 + os.getpid() % 50))

    def on_signal(_signum, _frame):
        # The first Ctrl-C, SIGTERM (docker stop, launch) or SIGHUP (a closed terminal) ends
        # the demo; later ones are ignored, so the cleanup that stops the children (in sessions
        # of their own, out of the terminal's reach) runs whole.
        ignore_stop_signals()
        raise KeyboardInterrupt

    for sig in STOP_SIGNALS:
        signal.signal(sig, on_signal)
    import rclpy
    from rclpy.action import ActionClient
    from rclpy.node import Node

    from pma_common.background import BackgroundSpin
    from pma_common.node import init_without_signal_handlers
    from pma_interfaces.action import MoveToLength, Sweep

    major_bag = run_dir / 'major_loop'            # the Sweep action's own bags, one per run
    minor_bag = run_dir / 'minor_loops'
    params_out = run_dir / 'refit_params.yaml'
    node = spin = None
    try:
        say(f'run directory: {run_dir}')
        start_live_view(procs, args.live_port)
        say('1/8 starting fake_arduino (simulated rig on a pseudo-terminal)')
        port = run_dir / 'pma0'
        truth_csv = logs / 'true_length.csv'     # the simulated truth, for the control plot
        procs.start('fake_arduino', 'pma_sim', 'fake_arduino', '--link', str(port),
                    '--seed', '1', '--max-rate', str(int(args.rate_hz)), '--truth',
                    str(truth_csv))
        procs.wait_for_log('fake_arduino', 'device at', 15)
        say('2/8 starting driver_node, model_node, the recorder and length_controller')
        procs.start('driver_node', 'pma_driver', 'driver_node', ros_args=[
            '-p', f'port:={port}', '-p', f'sample_rate_hz:={args.rate_hz}'])
        procs.start('model_node', 'pma_model', 'model_node')
        # Idle until the Sweep action asks it for a bag (the driver calls its ~/start).
        procs.start('recorder', 'pma_bag', 'record', '--idle', '--compression', 'zstd')
        procs.start('length_controller', 'pma_control', 'length_controller')

        init_without_signal_handlers()    # on_signal above stops the demo
        node = Node('pma_demo')
        # The action clients are made before the node spins in its thread, and live as long
        # as it does: rclpy (Jazzy) can break the wait when one is created or destroyed under
        # it (ros2/rclpy#1589, #1385; seen under load: "action client pointer is invalid"
        # after the first sweep, which was the last; pma_common.background).
        sweeps = ActionClient(node, Sweep, names.SWEEP)
        moves = ActionClient(node, MoveToLength, names.MOVE_TO_LENGTH)
        services = ServiceClients(node)
        spin = BackgroundSpin(node)   # its callbacks only collect

        from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data

        from pma_interfaces.msg import ModelParams, PmaState
        from pma_model.detector import BRANCH_NAMES

        states: list = []
        node.create_subscription(PmaState, names.STATE, states.append, qos_profile_sensor_data)
        model_params: list = []
        node.create_subscription(ModelParams, names.MODEL_PARAMS, model_params.append,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        deadline = time.monotonic() + 30
        while len(states) < 10:
            if time.monotonic() > deadline:
                raise RuntimeError('no pma/state from driver_node within 30 s '
                                   f'(see {logs}/driver_node.log)')
            time.sleep(0.05)
        first = states[-1]
        say(f'   streaming: {first.gauge_pressure_pa / 1e3:.1f} kPa, '
            f'{first.length_m * 100:.2f} cm at rest')
        procs.wait_for_log('recorder', 'idle', 20)

        say("3/8 the paper's pressure levels: 0 -> 500 -> 0 kPa in 50 kPa steps, "
            f'{args.hold_s:g} s each')
        run_sweep(spin, sweeps, 'major loop', Sweep.Goal(
            max_gauge_pressure_pa=500e3, step_pa=50e3, hold_s=args.hold_s, cycles=1,
            record=True, bag_path=str(major_bag), note=f'demo {run_dir.name}: major loop'),
            300)
        say('4/8 minor loops on both branches: 0 -> 300 -> 150 -> 500 -> 200 -> 350 -> 0 kPa')
        run_sweep(spin, sweeps, 'minor loops', Sweep.Goal(
            max_gauge_pressure_pa=500e3, step_pa=100e3, hold_s=args.hold_s, cycles=1,
            reversal_pressures_pa=[300e3, 150e3, 500e3, 200e3, 350e3],
            record=True, bag_path=str(minor_bag), note=f'demo {run_dir.name}: minor loops'),
            300)

        say('5/8 pressure_for_length (the inverse model)')
        print('        length     branch             gauge pressure   reachable on that branch')
        for length_m, branch, answer in ask_pressures(services.pressure_for_length,
                                                      [0.29, 0.27, 0.25]):
            name = BRANCH_NAMES[branch] if branch else f'auto: {BRANCH_NAMES[answer.branch]}'
            if answer.success:
                reach = f'{answer.min_length_m * 100:.2f}..{answer.max_length_m * 100:.2f} cm'
                print(f'      {length_m * 100:6.2f} cm  {name:17s}'
                      f'  {answer.gauge_pressure_pa / 1e3:8.1f} kPa       {reach}')
            else:
                print(f'      {length_m * 100:6.2f} cm  {name:17s}  refused: {answer.message}')

        say("6/8 refitting the model from the major loop's bag and scoring the memory rules "
            "along the minor loops' bag")
        refit = subprocess.run(
            [str(executable('pma_model', 'refit')), str(major_bag),
             '--memory-check', str(minor_bag),
             '--json', str(run_dir / 'refit.json'), '--params-out', str(params_out),
             '--plots', str(run_dir / 'plots'), '--run-id', run_dir.name],
            capture_output=True, text=True, check=False)
        (logs / 'refit.log').write_text(refit.stdout + refit.stderr)
        print(refit.stdout, end='')
        if refit.returncode:
            raise RuntimeError(f'refit failed (exit {refit.returncode}): {refit.stderr.strip()}')

        say('7/8 model_node loads the refit (ros2 param set /model_node params_file ...); '
            'the controller follows')
        loaded_before = len(model_params)
        refused = set_parameter(services.model_parameters, 'params_file', str(params_out))
        if refused:
            raise RuntimeError(f'model_node refused the refit: {refused}')
        deadline = time.monotonic() + 15
        while len(model_params) <= loaded_before and time.monotonic() < deadline:
            time.sleep(0.1)
        if len(model_params) > loaded_before:
            latest = model_params[-1]
            say(f'   model_node now runs the refit: {latest.form} branches, '
                f'{latest.memory} memory')
        else:
            say('   model_node did not report new parameters (see logs/model_node.log)')

        say('8/8 length control: steps 25.5 -> 28.5 -> 26.5 cm (MoveToLength), then a sine')
        control_outputs = run_control(spin, moves, services, run_dir, truth_csv,
                                      rate_hz=args.rate_hz)

        elapsed = time.monotonic() - started
        say(f'done in {elapsed:.0f} s. Outputs:')
        for label, path in (("the Sweep action's bags: major loop", major_bag),
                            ('                         minor loops', minor_bag),
                            ('refit report (JSON)', run_dir / 'refit.json'),
                            ('refit parameters (model_node params file)', params_out),
                            *control_outputs,
                            ('plots (PNG)', run_dir / 'plots'), ('process logs', logs)):
            print(f'      {label:45s} {path}')
        return 0
    except KeyboardInterrupt:
        say('interrupted: stopping every process')
        return 130
    except (RuntimeError, TimeoutError) as error:
        say(f'FAILED: {error}')
        say(f'logs: {logs}')
        return 1
    finally:
        ignore_stop_signals()    # the cleanup runs whole, however it was reached
        if spin is not None:
            spin.close()     # the node is not destroyed under its wait
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
        procs.stop_all()


if __name__ == '__main__':
    sys.exit(main())
