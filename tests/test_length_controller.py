"""length_controller against the simulated rig: fake_arduino, driver_node and the controller as
real processes over DDS, without model_node: the controller needs none (test_launch_files and
`make demo` run it beside model_node).

The probe sends MoveToLength goals and streams pma/length_setpoint like `ros2 action
send_goal` and `ros2 topic pub -r 50` would, and reads the measured length from pma/state.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.action import ActionClient
from std_msgs.msg import Float64

from pma_common import names
from pma_interfaces.action import Sweep
from pma_interfaces.msg import ControlState, LengthSetpoint
from pma_model.params import paper_table1
from pma_sim.fake_arduino import TruthLog
from support.control_probe import ControlProbe
from support.ros import shutdown, wait_for_action_server, wait_until

pytestmark = pytest.mark.integration

STROKE_M = paper_table1().stroke_m


@pytest.fixture(scope='module')
def rig(module_procs, tmp_path_factory):
    work = tmp_path_factory.mktemp('rig')
    port, truth = work / 'pma', work / 'truth.csv'
    fake = module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port),
                                 '--rate', '50', '--seed', '3', '--truth', str(truth))
    fake.wait_for_line('device at', 20)
    driver = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=[
        '-p', f'port:={port}', '-p', 'sample_rate_hz:=50.0'])
    controller = module_procs.ros2_run('pma_control', 'length_controller')
    driver.wait_for_line('active: publishing', 30)
    controller.wait_for_line('length_controller ready', 30)
    probe = ControlProbe()
    wait_until(lambda: len(probe.states) > 20 and len(probe.control) > 5, 20,
               'pma/state and pma/control_state')
    yield {'driver': driver, 'controller': controller, 'probe': probe, 'port': port,
           'procs': module_procs, 'truth': truth}
    probe.close()
    shutdown()


def test_move_to_length_settles_and_holds(rig):
    probe = rig['probe']
    handle = probe.send_goal(0.265, tolerance_m=0.002, settle_s=1.0)
    result = probe.result(handle)
    assert result.success, result.message
    assert abs(result.estimated_length_m - 0.265) <= 0.002
    assert 0.0 < result.settle_time_s < 15.0
    wait_until(lambda: rig['probe'].control[-1].mode == ControlState.MODE_HOLD, 5,
               'MODE_HOLD after the goal (it read MODE_STREAM, a stream nobody sent)')
    since = time.monotonic()
    time.sleep(3.0)                                  # the controller keeps holding it
    held = probe.lengths_since(since)
    held = held[np.isfinite(held)]
    assert abs(held.mean() - 0.265) < 0.0015, held.mean()


def test_an_unreachable_target_is_refused_with_the_reachable_range(rig):
    result = rig['probe'].result(rig['probe'].send_goal(0.20))
    assert not result.success
    assert 'reachable [' in result.message and '0.20' in result.message
    # `pma move 27cm --settle 1e9` ran until its 30 s timeout, within tolerance all along.
    result = rig['probe'].result(rig['probe'].send_goal(0.27, timeout_s=5.0, settle_s=1e9))
    assert not result.success and 'could never succeed' in result.message, result.message


def test_a_parameter_it_cannot_work_with_is_refused_and_a_good_one_applies(rig):
    """As `ros2 param set /length_controller creep_lead_max_share ...` would."""
    spinning = rig['probe'].spinning

    def set_parameter(name: str, value: float):
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        request = SetParameters.Request(parameters=[Parameter(name=name, value=value)])
        return spinning.call(SetParameters, 'length_controller/set_parameters',
                             request).results[0]

    def get_parameter(name: str) -> float:
        response = spinning.call(GetParameters, 'length_controller/get_parameters',
                                 GetParameters.Request(names=[name]), idempotent=True)
        return response.values[0].double_value

    for name, bad in (('creep_lead_max_share', 0.95), ('ki_per_s', -1.0)):
        refused = set_parameter(name, bad)
        assert not refused.successful and name in refused.reason, refused.reason
    assert get_parameter('creep_lead_max_share') == 0.5
    assert set_parameter('creep_lead_max_share', 0.0).successful
    assert get_parameter('creep_lead_max_share') == 0.0
    assert set_parameter('creep_lead_max_share', 0.5).successful


def test_bad_start_up_parameters_keep_the_defaults_and_say_so(rig):
    """`ros2 run pma_control length_controller --ros-args -p kp:=1 ...`: an integer for a
    float, a value out of range and an unknown mode used to end the node with a traceback.
    It runs on the defaults instead, says why once in the log and on /diagnostics until a
    valid change is applied. A second controller, namespaced away from the rig's."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    spinning = rig['probe'].spinning
    arrays, diagnostics = spinning.collect(DiagnosticArray, '/diagnostics', 50)

    def spare_status() -> DiagnosticStatus | None:
        mine = [s for array in list(arrays) for s in array.status
                if s.name.startswith('/spare/')]
        return mine[-1] if mine else None

    spare = rig['procs'].ros2_run('pma_control', 'length_controller', ros_args=[
        '-r', '__ns:=/spare', '-p', 'kp:=1', '-p', 'creep_lead_max_share:=0.95',
        '-p', 'mode:=foo', '-p', 'ki_per_s:=2.0'])
    try:
        line = spare.wait_for_line('invalid parameters refused, kept the defaults', 30)
        assert 'kp is a float parameter: write 1.0, not 1' in line
        assert 'creep_lead_max_share out of range' in line and "got 'foo'" in line
        spare.wait_for_line('length_controller ready: mode ff_fb', 30)
        response = spinning.call(GetParameters, '/spare/length_controller/get_parameters',
                                 GetParameters.Request(names=['kp', 'creep_lead_max_share',
                                                              'mode', 'ki_per_s']),
                                 idempotent=True)
        kp, share, mode, ki = response.values
        assert (kp.double_value, share.double_value, mode.string_value) == (0.3, 0.5, 'ff_fb')
        assert ki.double_value == 2.0                 # a good override is still taken
        wait_until(spare_status, 20, "the spare controller's diagnostics")
        assert spare_status().level == DiagnosticStatus.WARN
        assert 'start-up parameters refused' in spare_status().message
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=1.0)
        result = spinning.call(SetParameters, '/spare/length_controller/set_parameters',
                               SetParameters.Request(parameters=[
                                   Parameter(name='kp', value=value)])).results[0]
        assert result.successful, result.reason
        wait_until(lambda: spare_status().level == DiagnosticStatus.OK, 10,
                   'the warning cleared by a valid change')
        assert spare.alive()
    finally:
        spinning.node.destroy_subscription(diagnostics)
        spare.stop()


@pytest.mark.serial
def test_a_streamed_sine_is_tracked_end_to_end(rig):
    """A 0.1 Hz sine over DDS: RMSE against the true length within the issue's 2 % of stroke.

    Five Python processes share the machine: 1.31-1.47 % on a quiet one, 1.18-1.52 % beside
    two or four busy loops (docs/control.md). Larger errors here (10-28 %) came from a driver
    spinning in rclpy's MultiThreadedExecutor and reading its samples late (docs/driver.md,
    Threads); feedback alone ('fb') measured 4.2-4.4 %.
    """
    probe = rig['probe']
    wait_until(lambda: probe.setpoints.get_subscription_count() > 0, 10, 'controller subscribed')
    frequency, low, high = 0.1, 0.25, 0.295
    # Times are ROS (wall clock) times: each setpoint's when it was sent, each sample's its
    # header stamp (acquisition), so a busy probe's late receptions do not shift the match.
    start = time.time()
    reference: list[tuple[float, float]] = []
    while (now := time.time()) - start < 25.0:
        t = now - start
        target = (low + high) / 2 - (high - low) / 2 * math.cos(2 * math.pi * frequency * t)
        probe.setpoints.publish(LengthSetpoint(length_m=target))
        reference.append((now, target))
        time.sleep(0.02)                              # 50 Hz, as `ros2 topic pub -r 50`
    with probe.lock:
        states = [(s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec, s.seq)
                  for _, s in probe.states]
    states = [(t, seq) for t, seq in states if start + 10.0 <= t <= reference[-1][0]]
    truth = TruthLog.true_lengths(rig['truth'])       # the controller never sees it
    times = np.array([t for t, _ in states])
    true = np.array([truth[seq] for _, seq in states])
    ref = np.interp(times, *map(np.array, zip(*reference, strict=True)))
    rmse = float(np.sqrt(np.mean((true - ref) ** 2)))
    print(f'streamed sine 0.1 Hz over DDS: RMSE against the true length {rmse * 1000:.2f} mm '
          f'({100 * rmse / STROKE_M:.2f} % of stroke), {true.size} samples')
    assert rmse <= 0.02 * STROKE_M
    with probe.lock:
        modes = {c.mode for c in probe.control[-50:]}
    assert ControlState.MODE_STREAM in modes


def test_another_command_source_releases_the_target(rig):
    """The controller holds what a goal reached until something else commands the pressure:
    then it lets go, and the other command stands. Both used to fight: a setpoint from
    `ros2 topic pub` was overwritten within a sample, and a sweep run meanwhile ended at the
    held length's pressure instead of 0 Pa (the driver had refused the controller's
    setpoints during the sweep, and took them again after it)."""
    probe, node = rig['probe'], rig['probe'].spinning.node

    def setpoints_since(since: float) -> set[float]:
        with probe.lock:
            return {s.gauge_setpoint_pa for t, s in probe.states if t >= since}

    def hold(length_m: float) -> None:
        result = probe.result(probe.send_goal(length_m, settle_s=0.5))
        assert result.success, result.message
        wait_until(lambda: probe.control[-1].mode != ControlState.MODE_IDLE, 5, 'holding')

    # As `ros2 topic pub --once /pma/pressure_setpoint std_msgs/msg/Float64 "{data: 60000.0}"`.
    hold(0.27)
    publisher = node.create_publisher(Float64, names.PRESSURE_SETPOINT, 10)
    wait_until(lambda: publisher.get_subscription_count() >= 1, 10, 'the driver')
    deadline = time.monotonic() + 3.0        # and the controller, which listens there too
    while publisher.get_subscription_count() < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    publisher.publish(Float64(data=60_000.0))
    wait_until(lambda: probe.control[-1].mode == ControlState.MODE_IDLE, 5, 'released')
    rig['controller'].wait_for_line('released the target: another node commanded 60000 Pa', 5)
    wait_until(lambda: setpoints_since(time.monotonic() - 0.1) == {60_000.0}, 5, '60 kPa')
    since = time.monotonic()
    time.sleep(1.5)
    assert setpoints_since(since) == {60_000.0}

    # A sweep (0 -> 100 -> 0 kPa) while a length is held.
    hold(0.27)
    sweep = ActionClient(node, Sweep, names.SWEEP)
    wait_for_action_server(sweep)
    goal = Sweep.Goal(max_gauge_pressure_pa=100_000.0, step_pa=100_000.0, hold_s=2.0, cycles=1)
    handle = probe.spinning.send_goal(sweep, goal)
    result = probe._wait(probe.spinning.in_executor(handle.get_result_async), 60).result
    assert result.success, result.message
    rig['controller'].wait_for_line('released the target: the device holds', 5)
    since = time.monotonic()
    time.sleep(1.5)
    assert setpoints_since(since) == {0.0}
    assert probe.control[-1].mode == ControlState.MODE_IDLE


def test_losing_the_driver_aborts_the_goal_and_says_why(rig):
    probe = rig['probe']
    handle = probe.send_goal(0.28, settle_s=30.0, timeout_s=60.0)
    time.sleep(1.0)
    rig['driver'].stop()
    result = probe.result(handle)
    assert not result.success and 'no usable pma/state' in result.message
