"""driver_node: the managed (lifecycle) ROS 2 driver of the PMA rig.

A thin node around link.SerialLink (port, handshake, heartbeats, reconnect),
clock_sync.ClockSync (device time to ROS time), calibration (raw to SI) and sweep
(the Sweep action's staircase). docs/driver.md documents parameters, topics, QoS,
diagnostics and the lifecycle.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import rclpy
import rclpy.exceptions
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.lifecycle import Node, State, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure, Range
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from pma_bag.record import DEFAULT_TOPICS
from pma_common.node import ros_context, spin_until_stopped
from pma_driver import protocol
from pma_driver.clock_sync import ClockSync
from pma_driver.link import LinkError, LinkState, PortOpenError, SerialLink
from pma_driver.parameters import (
    PARAMETERS,
    calibrations,
    check_parameters,
    descriptor,
    device_ceiling_pa,
    stall_timeout_s,
    startup_commands,
)
from pma_driver.protocol import Ack, Command, Hello
from pma_driver.sweep import SweepError, SweepPlan, plan_sweep
from pma_interfaces.action import Sweep
from pma_interfaces.msg import PmaState

FIELD_OF_VIEW_RAD = 0.26          # HC-SR04: about 15 degrees
# The recorder prints this when ready, and again whenever its topic count changes; we wait
# until it records every one of its default topics that has a publisher now (at least our
# own four: pma/state, pma/pressure, pma/range, /diagnostics), so that e.g. model_node's
# pma/prediction is in the bag from the first step on.
RECORDER_READY_RE = re.compile(r'recorder: recording (\d+) topics')
RECORDER_TOPICS = 4
FAULT_BITS = (protocol.STATUS_OVERPRESSURE | protocol.STATUS_HEARTBEAT_LOST
              | protocol.STATUS_SENSOR_RANGE)


def to_time_msg(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def recorder_executable() -> Path:
    """pma_bag's record executable (install/pma_bag/lib/pma_bag/record)."""
    try:
        from ament_index_python.packages import get_package_prefix
        return Path(get_package_prefix('pma_bag')) / 'lib' / 'pma_bag' / 'record'
    except (ImportError, LookupError, ValueError):
        return Path(sys.argv[0]).resolve().parents[2] / 'pma_bag' / 'lib' / 'pma_bag' / 'record'


class PmaDriver(Node):
    """Lifecycle node: configure opens the port, activate publishes, cleanup closes it."""

    def __init__(self, **kwargs):
        super().__init__('driver_node', **kwargs)
        for name, (default, _, _) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor(name))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._link: SerialLink | None = None
        self._clock_sync = ClockSync()
        self._pressure_cal, self._length_cal = calibrations(self._values())
        self._frame_id = self.get_parameter('frame_id').value
        self._ambient_pa = self.get_parameter('ambient_pressure_pa').value
        self._active = False
        self._published = 0
        self._unpublished = 0           # decoded while configured but not active
        self._latest: protocol.Sample | None = None
        self._latest_gauge_pa = math.nan
        self._last_fault = ('', '')          # (status text, ROS time) of the last fault bits
        self._sweep_lock = threading.Lock()
        self._sweep_running = False
        # Held from "may this pressure be commanded?" to "sent", and by deactivate around
        # "inactive + VENT", so no SET can overtake the VENT of a deactivation.
        self._command_lock = threading.RLock()
        self._rate_count = (0, time.monotonic())
        self._rate_hz = 0.0
        self._configure_error = ''
        self._pubs = None
        self._refusal_logged: dict[str, float] = {}

        self._diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 1)
        self._diagnostics_timer = self.create_timer(1.0, self._publish_diagnostics)
        self._setpoint_sub = self.create_subscription(
            Float64, 'pma/pressure_setpoint', self._on_setpoint, 10)
        self._sweep_server = ActionServer(
            self, Sweep, 'pma/sweep', execute_callback=self._execute_sweep,
            goal_callback=self._on_sweep_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        # Blocks on the device's reply, so it must not hold up the default group.
        self._tare_service = self.create_service(Trigger, '~/tare', self._on_tare,
                                                 callback_group=ReentrantCallbackGroup())
        self._autostart_timer = None
        if self.get_parameter('autostart').value:
            self._autostart_timer = self.create_timer(
                self.get_parameter('reconnect_period_s').value, self._autostart)
            self._autostart()

    # -- parameters ----------------------------------------------------------------------

    def _values(self, changed: list[Parameter] = ()) -> dict:
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        values.update({p.name: p.value for p in changed})
        return values

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Check only; no side effects (they happen in _apply_parameters)."""
        hello = self._link.hello if self._link is not None else None
        reason = check_parameters(self._values(params), hello)
        return SetParametersResult(successful=not reason, reason=reason)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        names = {p.name for p in params}
        values = self._values()
        if any(name.startswith('calibration.') for name in names):
            self._pressure_cal, self._length_cal = calibrations(values)
        self._ambient_pa = values['ambient_pressure_pa']
        link = self._link
        if link is None:
            return
        link.heartbeat_period_s = values['heartbeat_period_s']
        link.reconnect_period_s = values['reconnect_period_s']
        link.handshake_timeout_s = values['handshake_timeout_s']
        link.stall_timeout_s = stall_timeout_s(values['sample_rate_hz'])
        commands = {'sample_rate_hz': (Command.RATE, max(1, round(values['sample_rate_hz']))),
                    'max_gauge_pressure_pa': (Command.MAX, self._device_max_pa(values)),
                    'heartbeat_timeout_ms': (Command.HEARTBEAT_TIMEOUT,
                                             values['heartbeat_timeout_ms'])}
        for name, (command, value) in commands.items():
            if name in names and link.connected:
                self._send(command, value)

    def _device_max_pa(self, values: dict | None = None) -> int:
        """The ceiling to send with MAX: the parameter, never above the device's own."""
        values = values or self._values()
        hello = self._link.hello if self._link is not None else None
        return device_ceiling_pa(values['max_gauge_pressure_pa'], hello)

    def _startup_commands(self, hello: Hello):
        commands, warnings = startup_commands(self._values(), hello)
        for warning in warnings:
            self.get_logger().warning(warning)
        return commands

    # -- lifecycle -----------------------------------------------------------------------

    def _state_label(self) -> str:
        return self._state_machine.current_state[1]

    def _autostart(self) -> None:
        """Configure and activate by ourselves (no manager); retry while the port is missing."""
        label = self._state_label()
        if label == 'unconfigured':
            self.trigger_configure()
            label = self._state_label()
            if label == 'unconfigured':
                period = self.get_parameter('reconnect_period_s').value
                self.get_logger().warning(
                    f'autostart: configure failed ({self._configure_error}); retrying every '
                    f'{period:g} s', throttle_duration_sec=30.0)
        if label == 'inactive':
            self.trigger_activate()
        if self._state_label() in ('active', 'finalized') and self._autostart_timer is not None:
            self._autostart_timer.cancel()
            self.destroy_timer(self._autostart_timer)
            self._autostart_timer = None

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        values = self._values()
        reason = check_parameters(values, None)
        if reason:
            self._configure_error = reason
            self.get_logger().error(f'configure: {reason}')
            return TransitionCallbackReturn.FAILURE
        self._pressure_cal, self._length_cal = calibrations(values)
        link = SerialLink(
            values['port'], values['baud'], on_sample=self._on_sample, on_hello=self._on_hello,
            on_event=self._on_link_event, startup_commands=self._startup_commands,
            receive_clock_ns=lambda: self.get_clock().now().nanoseconds,
            reconnect_period_s=values['reconnect_period_s'],
            handshake_timeout_s=values['handshake_timeout_s'],
            heartbeat_period_s=values['heartbeat_period_s'],
            stall_timeout_s=stall_timeout_s(values['sample_rate_hz']))
        try:
            link.open()
        except PortOpenError as error:
            self._configure_error = str(error)
            self.get_logger().error(f'configure: {error}', throttle_duration_sec=30.0)
            return TransitionCallbackReturn.FAILURE
        self._configure_error = ''
        qos = QoSProfile(depth=values['qos_depth'], reliability=(
            ReliabilityPolicy.RELIABLE if values['qos_reliability'] == 'reliable'
            else ReliabilityPolicy.BEST_EFFORT))
        self._pubs = (self.create_lifecycle_publisher(PmaState, 'pma/state', qos),
                      self.create_lifecycle_publisher(FluidPressure, 'pma/pressure', qos),
                      self.create_lifecycle_publisher(Range, 'pma/range', qos))
        self._link = link
        link.start()
        self.get_logger().info(f'configured: {values["port"]} open at {values["baud"]} baud')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        result = super().on_activate(state)
        self._active = True
        self.get_logger().info('active: publishing pma/state, pma/pressure, pma/range')
        return result

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        with self._command_lock:
            self._active = False
            self._vent('deactivated')
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        with self._command_lock:
            self._active = False
            self._close_link(vent=True)
        for pub in self._pubs or ():
            self.destroy_publisher(pub)
        self._pubs = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self.shutdown_hardware()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.shutdown_hardware()
        return TransitionCallbackReturn.SUCCESS

    def shutdown_hardware(self) -> None:
        """Vent the muscle and close the port (shutdown, Ctrl-C, errors)."""
        with self._command_lock:
            self._active = False
            self._close_link(vent=True)

    def _close_link(self, vent: bool) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.stop(vent=vent)
            if self.context.ok():  # after Ctrl-C the context is gone and so is /rosout
                self.get_logger().info(f'closed {link.port}{" (vented)" if vent else ""}')

    # -- link callbacks (link thread) ------------------------------------------------------

    def _on_link_event(self, level: int, message: str) -> None:
        # One call site per severity: rclpy refuses to log from one line at two severities.
        logger = self.get_logger()
        if level >= logging.ERROR:
            logger.error(message)
        elif level >= logging.WARNING:
            logger.warning(message)
        elif level >= logging.INFO:
            logger.info(message)
        else:
            logger.debug(message)

    def _on_hello(self, hello: Hello) -> None:
        # The device clock restarted: the old offset means nothing now.
        self._clock_sync.reset()
        if self._pressure_cal.tare_offset_pa != 0.0:
            # The device forgets its tare when it restarts; our offset stays. They differ
            # until the next ~/tare (at rest).
            self.get_logger().warning(
                'the device (re)started and has no tare, while calibration.tare_offset_pa is '
                f'{self._pressure_cal.tare_offset_pa:.1f} Pa: call ~/tare again at rest')

    def _on_sample(self, sample: protocol.Sample, receive_ns: int) -> None:
        stamp_ns = self._clock_sync.stamp(sample.t_ms, receive_ns)
        gauge_pa = self._pressure_cal.adc_to_pa(sample.adc)
        self._latest = sample
        self._latest_gauge_pa = gauge_pa
        if sample.status & FAULT_BITS:
            self._last_fault = (protocol.status_text(sample.status & FAULT_BITS),
                                f'{stamp_ns / 1e9:.3f}')
        pubs = self._pubs
        if not self._active or pubs is None:
            self._unpublished += 1
            return
        header_stamp = to_time_msg(stamp_ns)
        state = PmaState()
        state.header.stamp = header_stamp
        state.header.frame_id = self._frame_id
        state.seq = sample.seq
        state.device_time_s = sample.t_ms / 1000.0
        state.gauge_pressure_pa = gauge_pa
        state.length_m = self._length_cal.echo_to_length_m(sample.echo_us)
        state.gauge_setpoint_pa = float(sample.setpoint_pa)
        state.valve_state = sample.valve
        state.status = sample.status
        state.pressure_adc = sample.adc
        state.echo_us = sample.echo_us

        pressure = FluidPressure()
        pressure.header = state.header
        pressure.fluid_pressure = gauge_pa + self._ambient_pa
        pressure.variance = self._pressure_cal.pa_per_count ** 2 / 12.0  # quantisation

        ranged = Range()
        ranged.header = state.header
        ranged.radiation_type = Range.ULTRASOUND
        ranged.field_of_view = FIELD_OF_VIEW_RAD
        ranged.min_range = self._length_cal.min_range_m
        ranged.max_range = self._length_cal.max_range_m
        # REP-117: +inf = nothing within range (no echo); NaN = a reading outside the span.
        ranged.range = (math.inf if sample.echo_us == 0
                        else self._length_cal.echo_to_range_m(sample.echo_us))
        try:
            pubs[0].publish(state)
            pubs[1].publish(pressure)
            pubs[2].publish(ranged)
        except Exception as error:  # shutting down under us: the link must survive it
            self.get_logger().warning(f'publish failed: {error}', throttle_duration_sec=5.0)
            return
        self._published += 1

    # -- commands ------------------------------------------------------------------------

    def _send(self, command: Command, *args: int) -> bool:
        """Send without blocking; a NAK or a timeout is logged."""
        link = self._link
        if link is None or not link.connected:
            self.get_logger().warning(
                f'{command.value} {args} not sent: link '
                f'{link.state.value if link else "not configured"}', throttle_duration_sec=2.0)
            return False

        def on_reply(reply) -> None:
            if not isinstance(reply, Ack):
                what = 'no reply' if reply is None else f'NAK {reply.reason}'
                self.get_logger().error(f'device refused {command.value} {args}: {what}')

        try:
            link.send_async(command, *args, on_reply=on_reply)
        except LinkError as error:
            self.get_logger().warning(str(error), throttle_duration_sec=2.0)
            return False
        return True

    def _vent(self, why: str) -> None:
        if self._link is not None and self._link.connected and self._send(Command.VENT):
            self.get_logger().info(f'vented ({why})')

    def _link_streaming(self) -> bool:
        """Commands need a streaming link: a stalled one too means nobody can watch them."""
        link = self._link
        return link is not None and link.state is LinkState.STREAMING

    def _link_text(self) -> str:
        link = self._link
        return f'link {link.state.value}' if link is not None else 'link closed'

    def setpoint_refusal(self, gauge_pa: float) -> tuple[str, str]:
        """(kind, reason) why this setpoint must not reach the device; ('', '') when it may."""
        limit = self._device_max_pa()
        if not math.isfinite(gauge_pa):
            return 'non-finite', f'setpoint {gauge_pa} is not a finite number'
        if gauge_pa < 0:
            return 'negative', f'setpoint {gauge_pa:.0f} Pa is negative (gauge pressure)'
        if gauge_pa > limit:
            return 'too high', (f'setpoint {gauge_pa:.0f} Pa is above max_gauge_pressure_pa '
                                f'{limit} Pa')
        if not self._active:
            return 'inactive', f'driver is {self._state_label()}, not active'
        if not self._link_streaming():
            return 'link', self._link_text()
        return '', ''

    def _on_setpoint(self, msg: Float64) -> None:
        with self._command_lock:
            kind, reason = self.setpoint_refusal(msg.data)
            if not reason and self._sweep_running:
                kind, reason = 'sweep', 'a sweep is running'
            if not reason:
                self._send(Command.SET, round(msg.data))
                return
        # Throttled per kind, so a flood of one kind of refusal hides no other kind.
        now = time.monotonic()
        if now - self._refusal_logged.get(kind, -math.inf) >= 1.0:
            self._refusal_logged[kind] = now
            self.get_logger().warning(f'refused setpoint: {reason}')

    # -- tare ------------------------------------------------------------------------------

    def _on_tare(self, _request, response):
        """Zero the pressure at rest, on the device and here, from the same ADC count.

        The device regulates on its own tared reading and the host converts the raw count
        with `calibration.tare_offset_pa`: TARE's ACK carries the count the device took as
        zero, and the host's offset is computed from exactly that count, so both agree.
        """
        response.success, response.message = self._tare()
        log = self.get_logger()
        if response.success:
            log.info(response.message)
        else:
            log.warning(f'tare refused: {response.message}')
        return response

    def _tare(self) -> tuple[bool, str]:
        with self._command_lock:
            if not self._active or not self._link_streaming():
                return False, (f'driver {self._state_label()}, {self._link_text()}: '
                               'nothing to tare')
            if self._sweep_running:
                return False, 'a sweep is running'
            latest = self._latest
            if latest is None or latest.setpoint_pa != 0:
                return False, ('the muscle is not vented: send setpoint 0.0 first and let the '
                               'pressure settle')
            try:
                reply = self._link.send(Command.TARE)   # held: cleanup takes the lock too
            except LinkError as error:
                return False, str(error)
        if not isinstance(reply, Ack) or reply.value is None:
            return False, (f'device refused TARE: {getattr(reply, "reason", reply)} (the reading '
                           'is not within 25 kPa of zero or outside the sensor span)')
        untared = replace(self._pressure_cal, tare_offset_pa=0.0)
        offset_pa = float(untared.adc_to_pa(reply.value))
        result = self.set_parameters([Parameter('calibration.tare_offset_pa', value=offset_pa)])[0]
        if not result.successful:
            return False, f'device tared, but calibration.tare_offset_pa refused: {result.reason}'
        return True, (f'tared: ADC {reply.value} is 0 Pa on the device and here '
                      f'(calibration.tare_offset_pa = {offset_pa:.1f} Pa)')

    # -- sweep action ----------------------------------------------------------------------

    def _plan(self, goal) -> SweepPlan:
        return plan_sweep(goal.max_gauge_pressure_pa, goal.step_pa, goal.hold_s, goal.cycles,
                          list(goal.reversal_pressures_pa), ceiling_pa=self._device_max_pa())

    def _on_sweep_goal(self, goal) -> GoalResponse:
        try:
            self._plan(goal)
        except SweepError as error:
            self.get_logger().error(f'sweep goal rejected: {error}')
            return GoalResponse.REJECT
        if not self._active or self._link is None or not self._link.connected:
            self.get_logger().error(f'sweep goal rejected: driver {self._state_label()}, '
                                    f'{self._link_text()}')
            return GoalResponse.REJECT
        with self._sweep_lock:
            if self._sweep_running:
                self.get_logger().error('sweep goal rejected: another sweep is running')
                return GoalResponse.REJECT
            self._sweep_running = True
        return GoalResponse.ACCEPT

    def _execute_sweep(self, goal_handle):
        try:
            return self._run_sweep(goal_handle)
        finally:
            with self._sweep_lock:
                self._sweep_running = False

    def _run_sweep(self, goal_handle):
        goal = goal_handle.request
        result = Sweep.Result()
        start_count = self._published   # reset once the recorder runs: count what it can see

        def finish(outcome: str, message: str):
            if outcome != 'succeed':
                # Whatever stopped the run (cancel, NAK, lost reply, stall, deactivation), the
                # muscle must not stay at the last step's pressure.
                self._vent(f'sweep {outcome}')
            result.message = message
            result.sample_count = self._published - start_count
            result.success = outcome == 'succeed'
            getattr(goal_handle, {'succeed': 'succeed', 'abort': 'abort',
                                  'cancel': 'canceled'}[outcome])()
            summary = f'sweep {outcome}: {message} ({result.sample_count} samples)'
            if result.success:
                self.get_logger().info(summary)
            else:
                self.get_logger().warning(summary)
            return result

        try:
            plan = self._plan(goal)
        except SweepError as error:
            return finish('abort', str(error))
        recorder = None
        if goal.record:
            bag = Path(goal.bag_path).expanduser() if goal.bag_path else (
                Path.cwd() / time.strftime('sweep_%Y%m%d_%H%M%S'))
            try:
                recorder = self._start_recorder(bag.resolve())
            except RuntimeError as error:
                return finish('abort', f'recorder: {error}')
            result.bag_path = str(bag.resolve())
            start_count = self._published
        try:
            outcome, message = self._follow_plan(goal_handle, plan, start_count)
        finally:
            if recorder is not None:
                self._stop_recorder(recorder)
        return finish(outcome, message)

    def _follow_plan(self, goal_handle, plan: SweepPlan, start_count: int) -> tuple[str, str]:
        tolerance = self.get_parameter('sweep.tolerance_pa').value
        step_timeout = self.get_parameter('sweep.step_timeout_s').value
        feedback = Sweep.Feedback(step_count=plan.step_count)
        self.get_logger().info(f'sweep: {plan.step_count} steps up to '
                               f'{max(plan.setpoints_pa):.0f} Pa, hold {plan.hold_s:g} s')

        def send_feedback(index: int, setpoint: float, hold_fraction: float) -> None:
            feedback.progress = plan.progress(index, hold_fraction)
            feedback.gauge_setpoint_pa = setpoint
            feedback.sample_count = self._published - start_count
            feedback.step_index = index
            goal_handle.publish_feedback(feedback)

        def interrupted() -> tuple[str, str] | None:
            if goal_handle.is_cancel_requested:
                return 'cancel', 'canceled; vented to 0 Pa'
            if not self._active:
                return 'abort', 'driver deactivated; vented'
            if not self._link_streaming():
                return 'abort', (f'{self._link_text()} during the sweep; vented (the device '
                                 'also vents on heartbeat loss)')
            return None

        for index, setpoint in enumerate(plan.setpoints_pa):
            with self._command_lock:
                stop = interrupted()
                if stop:
                    return stop
                limit = self._device_max_pa()   # the parameter may have been lowered
                if setpoint > limit:
                    return 'abort', (f'step {setpoint:.0f} Pa is above max_gauge_pressure_pa '
                                     f'{limit} Pa (lowered during the sweep); vented')
                reply, error = self._set_with_retry(round(setpoint))
            if reply is None:
                return 'abort', f'SET {setpoint:.0f} Pa failed: {error}; vented'
            if not isinstance(reply, Ack):
                return 'abort', (f'device refused SET {setpoint:.0f} Pa: NAK {reply.reason}; '
                                 'vented')
            send_feedback(index, setpoint, 0.0)
            deadline = time.monotonic() + step_timeout
            while not abs(self._latest_gauge_pa - setpoint) <= tolerance:  # NaN: not reached
                stop = interrupted()
                if stop:
                    return stop
                if time.monotonic() > deadline:
                    self.get_logger().warning(
                        f'sweep step {index}: {setpoint:.0f} Pa not reached within '
                        f'{step_timeout:g} s (at {self._latest_gauge_pa:.0f} Pa); holding')
                    break
                time.sleep(0.02)
            hold_end = time.monotonic() + plan.hold_s
            next_feedback = time.monotonic() + 0.5
            while (now := time.monotonic()) < hold_end:
                stop = interrupted()
                if stop:
                    return stop
                if now >= next_feedback:
                    send_feedback(index, setpoint, 1.0 - (hold_end - now) / plan.hold_s)
                    next_feedback = now + 0.5
                time.sleep(min(0.05, hold_end - now))
        send_feedback(plan.step_count - 1, plan.setpoints_pa[-1], 1.0)
        return 'succeed', f'{plan.step_count} steps done'

    def _set_with_retry(self, gauge_pa: int):
        """SET, once more if the reply got lost (SET is idempotent): (reply, error text)."""
        error = ''
        for _ in range(2):
            link = self._link
            if link is None:
                return None, 'link closed'
            try:
                return link.send(Command.SET, gauge_pa), ''
            except LinkError as failure:
                error = str(failure)
        return None, error

    def _start_recorder(self, bag: Path) -> subprocess.Popen:
        exe = recorder_executable()
        if not exe.exists():
            raise RuntimeError(f'{exe} not found (build the workspace)')
        argv = [str(exe), '-o', str(bag), '--ros-args', '-r',
                f'__ns:={self.get_namespace()}']
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, text=True, start_new_session=True,
                                env=dict(os.environ, PYTHONUNBUFFERED='1'))
        expected = max(RECORDER_TOPICS, sum(
            1 for topic in DEFAULT_TOPICS
            if self.count_publishers(self.resolve_topic_name(topic)) > 0))
        ready = threading.Event()       # the recorder has subscribed every published topic
        announced = threading.Event()   # it has started (maybe with 0 topics yet)
        failed = threading.Event()      # it cannot write the bag (it says why and stays up)
        tail: list[str] = []

        def pump() -> None:
            for line in proc.stdout:
                tail.append(line.rstrip())
                del tail[:-20]
                if line.startswith('recorder: ERROR'):
                    failed.set()
                match = RECORDER_READY_RE.search(line)
                if match:
                    announced.set()
                    if int(match.group(1)) >= expected:
                        ready.set()
                self.get_logger().debug(f'recorder: {line.rstrip()}')

        threading.Thread(target=pump, daemon=True).start()
        start = time.monotonic()
        while not ready.wait(0.1):
            waited = time.monotonic() - start
            if proc.poll() is not None or failed.is_set() or waited > 15.0:
                self._stop_recorder(proc)
                if failed.is_set():
                    raise RuntimeError(' | '.join(t for t in tail if 'ERROR' in t))
                raise RuntimeError(f'did not start (exit code {proc.returncode}): '
                                   + ' | '.join(tail[-5:]))
            if announced.is_set() and waited > 5.0:
                self.get_logger().warning(
                    f'recorder: not all of the {expected} published topics subscribed after '
                    f'5 s: {tail[-1:]}')
                break
        self.get_logger().info(f'recording to {bag}')
        return proc

    def _stop_recorder(self, proc: subprocess.Popen) -> None:
        for sig, wait in ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            proc.send_signal(sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(wait)
        if proc.returncode not in (0, None):
            self.get_logger().warning(f'recorder exited with code {proc.returncode}')

    # -- diagnostics -----------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        count, since = self._rate_count
        self._rate_hz = (self._published - count) / max(1e-3, now - since)
        self._rate_count = (self._published, now)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [self.diagnostic_status()]
        self._diagnostics_pub.publish(array)

    def diagnostic_status(self) -> DiagnosticStatus:
        status = DiagnosticStatus()
        status.name = f'{self.get_fully_qualified_name()}: serial link'
        status.hardware_id = self.get_parameter('port').value
        values: dict[str, str] = {'lifecycle state': self._state_label()}
        link = self._link
        if link is None:
            status.level = DiagnosticStatus.ERROR if self._configure_error else DiagnosticStatus.OK
            status.message = self._configure_error or f'not configured ({self._state_label()})'
        else:
            stats = link.stats()
            pubs = self._pubs
            status.level, status.message = self._link_level(stats)
            values.update({
                'link state': stats.state.value,
                'baud': str(link.baud),
                'firmware': (f'{stats.hello.firmware} {stats.hello.fw_version}'
                             if stats.hello else '-'),
                'device ceiling at handshake [Pa]': (str(stats.hello.ceiling_pa) if stats.hello
                                                     else '-'),
                'device limit [Pa]': str(stats.hello.limit_pa) if stats.hello else '-',
                'sample rate [Hz]': f'{self._rate_hz:.1f}',
                'samples published': str(self._published),
                # matched readers, as this writer sees them: "is anyone listening?"
                'state subscribers': str(pubs[0].get_subscription_count() if pubs else 0),
                'samples decoded': str(stats.samples),
                'samples while inactive': str(self._unpublished),
                'samples before handshake': str(stats.ignored_before_hello),
                'frames': str(stats.frames),
                'bad frames': str(stats.dropped_total),
                **{f'bad frames ({reason})': str(n) for reason, n in
                   sorted(stats.dropped.items())},
                # By seq: what never came, apart from late, repeated and stray numbers.
                'lost samples': str(stats.sequence.lost),
                'sequence gaps': str(stats.sequence.gaps),
                'late samples': str(stats.sequence.late),
                'duplicate samples': str(stats.sequence.duplicates),
                'stray sequence numbers': str(stats.sequence.stray),
                'sequence restarts': str(stats.sequence.restarts),
                'connects': str(stats.connects),
                'disconnects': str(stats.disconnects),
                'ACK': str(stats.acks), 'NAK': str(stats.naks),
                'command timeouts': str(stats.command_timeouts),
                'last NAK': stats.last_nak or '-',
                'last error': stats.last_error or '-',
                'last fault': (f'{self._last_fault[0]} at {self._last_fault[1]} s'
                               if self._last_fault[0] else '-'),
                'clock offset [s]': f'{self._clock_sync.offset_s:.6f}',
                'clock drift [ppm]': f'{self._clock_sync.drift_ppm:.0f}',
            })
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return status

    def _link_level(self, stats) -> tuple[bytes, str]:
        state = stats.state
        if state is LinkState.STREAMING:
            latest = self._latest
            if latest is not None and latest.status & FAULT_BITS:
                return (DiagnosticStatus.ERROR,
                        f'device fault: {protocol.status_text(latest.status & FAULT_BITS)}')
            if latest is not None and latest.status & protocol.STATUS_ECHO_TIMEOUT:
                return DiagnosticStatus.WARN, 'streaming; ultrasonic echo timeout'
            return DiagnosticStatus.OK, 'streaming'
        if state in (LinkState.HANDSHAKE, LinkState.STALLED):
            return DiagnosticStatus.WARN, stats.state_detail or state.value
        if state is LinkState.DISCONNECTED and stats.connects:
            return DiagnosticStatus.ERROR, f'disconnected, reconnecting: {stats.state_detail}'
        return DiagnosticStatus.ERROR, stats.state_detail or state.value


def main(args=None) -> int:
    with ros_context(args) as stop:
        try:
            node = PmaDriver()
        except rclpy.exceptions.InvalidParameterValueException as error:
            print(f'driver_node: bad parameter: {error}', file=sys.stderr)
            return 2
        executor = MultiThreadedExecutor(num_threads=4)
        try:
            spin_until_stopped(executor, node, stop)
        finally:
            node.shutdown_hardware()        # vent and close the port, whatever comes in
            executor.shutdown()
            node.destroy_node()
    return 0


if __name__ == '__main__':
    sys.exit(main())
