"""length_controller: hold the muscle at a length, or follow a stream of lengths.

A thin ROS wrapper around pma_control.controller (docs/control.md): every `pma/state`
sample runs one control step and publishes `pma/pressure_setpoint` (the driver still
enforces its own limits) and `pma/control_state`. Targets come from the `pma/move_to_length`
action or the `pma/length_setpoint` stream; the latest one wins. The hysteresis model is the
one model_node runs: its latched `pma/model_params` is followed (a refit that model_node
loads reaches the controller too); without model_node the shipped defaults are used.

The controller lets go of its target (a running goal aborts, a held length is no longer
held) whenever the muscle is taken out of its hands, and then commands nothing until a new
goal, or a stream that starts again, asks (docs/control.md has the table):
- no usable sample for `stale_timeout_s` (the driver stopped, crashed, restarted or was
  deactivated, its link lost; echo lost in 'fb' mode): a fault until samples come again;
- the device vented by itself (its OVERPRESSURE or HEARTBEAT_LOST bit rose) or restarted
  (its clock went back);
- another command source (a pressure setpoint from another node, or a device setpoint that
  is not the controller's for OTHER_SOURCE_S, e.g. a sweep): the last command wins, and the
  two never fight over the valve;
- a cancel (the pressure stays where it is; so it does when the node stops cleanly).
While it holds a target it holds a commander lease on the driver (pma_common.lease): if the
controller vanishes (its host or the network to the driver is lost, or it is killed), the
driver brings the muscle to its safe state within commander_timeout_s.
A re-armed target after any of these would re-pressurise a muscle someone may be handling:
so a stream that kept sending through it must go quiet for STREAM_REARM_QUIET_S first.
A NaN pressure skips the sample; a NaN length alone is no fault (the estimate carries on
from the model). A new goal or stream setpoint preempts the running goal (it aborts).
"""

from __future__ import annotations

import collections
import math
import sys
import time
from dataclasses import fields

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from std_msgs.msg import Float64

from pma_common import names
from pma_common.diagnostics import publish_status
from pma_common.lease import MIN_COMMANDER_TIMEOUT_S, LeaseHolder, commander_name
from pma_common.node import run_single_threaded
from pma_common.parameters import declare_or_keep_default
from pma_common.service import SERVICE_QOS
from pma_control.controller import (
    MAX_CREEP_LEAD_SHARE,
    MODES,
    ControllerSettings,
    ControlOutput,
    LengthController,
    RecentMean,
)
from pma_interfaces.action import MoveToLength
from pma_interfaces.msg import ControlState, LengthSetpoint, PmaState
from pma_interfaces.msg import ModelParams as ModelParamsMsg
from pma_model.identification import IdentificationSettings
from pma_model.params import ModelParams, ParamsError, default_params

DEFAULT_TOLERANCE_M = 0.002
DEFAULT_SETTLE_S = 1.0
DEFAULT_TIMEOUT_S = 30.0
TICK_S = 0.1          # goal bookkeeping, feedback and the stale check run this often
# Commands of the controller's own that a setpoint on pma/pressure_setpoint, or the device's,
# may still be (the driver coalesces; the device answers a sample or two later).
OWN_COMMANDS_S = 2.0
# The device's setpoint is none of those for this long: something else commands it (a sweep
# runs, whose setpoints the driver takes instead of the controller's).
OTHER_SOURCE_S = 1.0
# After the target was let go, a stream that is still sending takes the muscle again only once
# it has been quiet this long: a trajectory sender restarted, not one that never noticed.
STREAM_REARM_QUIET_S = 0.5
# Status bits with which the device says it vented by itself.
DEVICE_VENT_BITS = PmaState.STATUS_OVERPRESSURE | PmaState.STATUS_HEARTBEAT_LOST
# The shortest window a goal's result averages the measured length over [s].
MIN_MEASURED_WINDOW_S = 0.5
# A target taken before the first pma/state sample (a goal sent while this node was still
# starting: discovery takes about a second) waits this long for it. Nothing is commanded
# without a sample, so the wait is safe; stale_timeout_s counts once samples have come.
FIRST_SAMPLE_WAIT_S = 5.0

# ControllerSettings field -> (description, low, high)
SETTING_DESCRIPTIONS = {
    'max_gauge_pressure_pa': ('highest pressure the controller ever commands [Pa]', 1e3, 1e6),
    'kp': ('ff_fb: proportional gain on the length error [m/m]', 0.0, 10.0),
    'ki_per_s': ('ff_fb: integral gain on the length error [1/s]', 0.0, 100.0),
    'fb_kp_pa_per_m': ('fb: proportional gain [Pa/m]', 0.0, 1e9),
    'fb_ki_pa_per_m_s': ('fb: integral gain [Pa/(m s)]', 0.0, 1e10),
    'fb_filter_time_constant_s': ('fb: time constant of the length filter [s]', 0.0, 10.0),
    'error_deadband_m': ('errors below this are not integrated [m]', 0.0, 0.01),
    'max_pressure_rate_pa_s': ('pressure-rate limit of the command [Pa/s]', 1e3, 1e7),
    'max_setpoint_rate_m_s': ('length-rate limit of the setpoint [m/s]', 1e-4, 1.0),
    'creep_lead_max_share': ('the feedforward leads for learned creep up to this share of '
                             'a change (0: no lead) [1]', 0.0, MAX_CREEP_LEAD_SHARE),
    'bias_process_noise_m': ('how fast the model error may wander [m/sqrt(s)]', 0.0, 0.1),
    'length_noise_m': ('length sensor noise, one sigma [m]', 1e-5, 0.05),
}


def goal_limits(request) -> tuple[float, float, float]:
    """(tolerance_m, settle_s, timeout_s) of a MoveToLength goal, a 0 being the default."""
    return (request.tolerance_m or DEFAULT_TOLERANCE_M, request.settle_s or DEFAULT_SETTLE_S,
            request.timeout_s or DEFAULT_TIMEOUT_S)


def _range(low: float, high: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]


class LengthControllerNode(Node):
    def __init__(self, **kwargs):
        super().__init__('length_controller', **kwargs)
        defaults = ControllerSettings()
        refused = []     # start-up overrides of the wrong type or out of range (defaults kept)
        refused.append(declare_or_keep_default(self, 'mode', defaults.mode, ParameterDescriptor(
            description=f"'ff_fb' (model feedforward + feedback), 'ff' or 'fb' ({MODES})")))
        for name, (description, low, high) in SETTING_DESCRIPTIONS.items():
            refused.append(declare_or_keep_default(
                self, name, float(getattr(defaults, name)), ParameterDescriptor(
                    description=description, floating_point_range=_range(low, high))))
        refused.append(declare_or_keep_default(self, 'stale_timeout_s', 0.5, ParameterDescriptor(
            description='no usable pma/state sample for this long is a fault [s]',
            floating_point_range=_range(0.05, 10.0))))
        self.declare_parameter('follow_model_node', True, ParameterDescriptor(
            description="use model_node's model (its latched pma/model_params)",
            read_only=True))
        refused = [reason for reason in refused if reason is not None]
        mode = self.get_parameter('mode').value
        if mode not in MODES:      # the one setting its descriptor cannot check
            refused.append(f'mode must be one of {MODES}, got {mode!r}')
            self.set_parameters([Parameter('mode', value=defaults.mode)])
        # Why start-up overrides were refused (on /diagnostics until a valid change is
        # applied); empty: every one was taken.
        self._startup_problem = '; '.join(refused)
        if refused:
            self.get_logger().error(f'invalid parameters refused, kept the defaults: '
                                    f'{self._startup_problem}')
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._params = default_params()
        self._controller = LengthController(self._params.build_online(), self._settings())
        self._goal = None                    # the running goal handle
        self._streamed = False               # the target came from pma/length_setpoint
        self._goal_started = 0.0
        self._inside_since: float | None = None   # since when the goal is within tolerance
        self._last_sample_at: float | None = None
        self._armed_at = time.monotonic()
        self._last_state: PmaState | None = None
        self._last_output: ControlOutput | None = None
        self._fault = ''
        # Why the target was last let go, and whether a fault did it ('' / False: it was
        # not, or a new target came since); the last one stays for /diagnostics.
        self._let_go_reason, self._let_go_by_fault = '', False
        self._last_let_go = '-'
        self._last_stream_at: float | None = None      # monotonic time of the last message
        self._last_status = 0
        self._last_device_time_s: float | None = None
        self._measured = RecentMean(DEFAULT_SETTLE_S)
        self._stats = {'steps': 0, 'nan_pressure': 0, 'nan_length': 0, 'faults': 0,
                       'released to another source': 0, 'holds ended by a fault': 0}
        self._sent: collections.deque[tuple[float, int]] = collections.deque()  # (t, Pa)
        self._sent_counts: collections.Counter[int] = collections.Counter()
        self._device_differs_since: float | None = None

        self._command_pub = self.create_publisher(Float64, names.PRESSURE_SETPOINT, 10)
        self._lease = LeaseHolder(self, commander_name(self))
        self._state_pub = self.create_publisher(ControlState, names.CONTROL_STATE, 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 1)
        # One thread runs everything: every sample is one control step, published at once.
        self.create_subscription(PmaState, names.STATE, self._on_state, qos_profile_sensor_data)
        self.create_subscription(LengthSetpoint, names.LENGTH_SETPOINT, self._on_setpoint, 10)
        self.create_subscription(Float64, names.PRESSURE_SETPOINT, self._on_pressure_setpoint,
                                 10)
        if self.get_parameter('follow_model_node').value:
            latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                 reliability=ReliabilityPolicy.RELIABLE)
            self.create_subscription(ModelParamsMsg, names.MODEL_PARAMS, self._on_model_params,
                                     latched)
        self._action = ActionServer(
            self, MoveToLength, names.MOVE_TO_LENGTH,
            execute_callback=lambda handle: MoveToLength.Result(),   # replaced per goal
            goal_callback=self._on_goal, handle_accepted_callback=self._on_accepted,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
            # Its goal, result and cancel services are services: a burst from several
            # clients must not be lost in rclpy's default queue of 10.
            goal_service_qos_profile=SERVICE_QOS, result_service_qos_profile=SERVICE_QOS,
            cancel_service_qos_profile=SERVICE_QOS)
        self.create_timer(TICK_S, self._on_tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f'length_controller ready: mode {self._controller.settings.mode}, '
                               f'{self._params.branch_form} model, {self._params.memory} memory')

    # -- parameters --------------------------------------------------------------------

    def _settings(self, changes: dict | None = None) -> ControllerSettings:
        values = {item.name: self.get_parameter(item.name).value
                  for item in fields(ControllerSettings)}
        values.update(changes or {})
        return ControllerSettings(**values)

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in parameters
                   if p.name in {item.name for item in fields(ControllerSettings)}}
        try:
            self._settings(changes)
        except (ValueError, TypeError) as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        settings = self._settings()
        self._startup_problem = ''     # a valid change replaces what start-up refused
        if settings.mode != self._controller.settings.mode:
            target = self._controller.target_m
            self._controller = LengthController(self._controller.model, settings)
            if target is not None:
                self._controller.set_target(target)
        else:
            self._controller.settings = settings

    def _on_model_params(self, msg: ModelParamsMsg) -> None:
        try:
            params = ModelParams.from_yaml(msg.parameters_yaml)
        except ParamsError as error:
            self.get_logger().error(f'pma/model_params not usable, keeping the model: {error}')
            return
        unlearned = params.with_learned(IdentificationSettings())
        if unlearned == self._params.with_learned(IdentificationSettings()):
            return      # only what model_node learned moved: this model learns the same
        self._params = params
        self._controller.replace_model(params.build_online())
        self.get_logger().info(f"following model_node's model: {params.branch_form} "
                               f'branches, {params.memory} memory')

    # -- the loop ----------------------------------------------------------------------

    def _on_state(self, state: PmaState) -> None:
        self._check_device(state)
        if not math.isfinite(state.gauge_pressure_pa):
            self._stats['nan_pressure'] += 1
            return
        self._stats['steps'] += 1
        now = time.monotonic()
        self._measured.add(now, state.length_m)
        length_ok = math.isfinite(state.length_m)
        if not length_ok:
            self._stats['nan_length'] += 1
        if length_ok or self._controller.settings.mode != 'fb':   # 'fb' is blind without echo
            self._last_sample_at = now
            if self._fault:
                self.get_logger().info('samples again: the fault is cleared; nothing is '
                                       'commanded until a new goal or stream')
                self._fault = ''
        self._check_device_setpoint(state.gauge_setpoint_pa)
        t_s = state.header.stamp.sec + state.header.stamp.nanosec * 1e-9
        output = self._controller.command(t_s, state.gauge_pressure_pa, state.length_m)
        self._last_state, self._last_output = state, output
        if self._controller.target_m is not None and not self._fault:
            silent = self._lease.silent_s()
            if silent >= MIN_COMMANDER_TIMEOUT_S:
                self._let_go(f'this node renewed its commander lease for none of {silent:.1f} s '
                             '(paused or starved): the driver may have taken the muscle back '
                             'and vented it', fault=True)
            else:
                self._command(float(output.command_pa))
        output = self._last_output = self._controller.explain(output)   # off the command's path
        self._state_pub.publish(self._control_state(state, output))

    # -- the muscle taken out of the controller's hands ---------------------------------

    def _check_device(self, state: PmaState) -> None:
        """Let go when the device vented by itself or restarted: what the controller would
        command next assumes a muscle that is no longer there."""
        rose = state.status & DEVICE_VENT_BITS & ~self._last_status
        went_back = (self._last_device_time_s is not None
                     and state.device_time_s < self._last_device_time_s)
        self._last_status, self._last_device_time_s = state.status, state.device_time_s
        if self._controller.target_m is None:
            return
        if rose:
            names = [name for bit, name in ((PmaState.STATUS_OVERPRESSURE, 'overpressure'),
                                            (PmaState.STATUS_HEARTBEAT_LOST, 'heartbeat lost'))
                     if rose & bit]
            self._let_go(f'the device vented by itself ({", ".join(names)})', fault=True)
        elif went_back:
            self._let_go('the device restarted (its clock went back)', fault=True)

    def _let_go(self, reason: str, *, fault: bool) -> None:
        """Stop steering: the target goes, a running goal aborts with the reason, and nothing
        is commanded until a new goal or stream (STREAM_REARM_QUIET_S) asks."""
        self._controller.clear_target()
        self._device_differs_since = None
        self._let_go_reason, self._let_go_by_fault = reason, fault
        self._last_let_go = f'{reason} (at {self.get_clock().now().nanoseconds / 1e9:.3f} s)'
        self._sync_lease()
        if fault:
            self._stats['holds ended by a fault'] += 1
            self.get_logger().warning(f'hold ended: {reason}; nothing is commanded until a '
                                      'new goal or stream')
        if self._goal is not None:
            self._end_goal(self._goal, False, reason, 'abort')

    def _armed(self) -> None:
        """A new target was taken (goal or stream): the last let-go is history."""
        self._let_go_reason, self._let_go_by_fault = '', False
        self._armed_at = time.monotonic()
        self._sync_lease()

    # -- other command sources ---------------------------------------------------------

    def _command(self, pressure_pa: float) -> None:
        whole_pa = round(pressure_pa)       # as the driver sends it
        self._sent.append((time.monotonic(), whole_pa))
        self._sent_counts[whole_pa] += 1
        self._command_pub.publish(Float64(data=pressure_pa))

    def _sent_lately(self, pressure_pa: float, tolerance_pa: int = 0) -> bool:
        """Whether the controller commanded this (to whole Pa) within OWN_COMMANDS_S."""
        now = time.monotonic()
        while self._sent and now - self._sent[0][0] > OWN_COMMANDS_S:
            _, whole_pa = self._sent.popleft()
            self._sent_counts[whole_pa] -= 1
            if not self._sent_counts[whole_pa]:
                del self._sent_counts[whole_pa]
        if not math.isfinite(pressure_pa):
            return False
        whole_pa = round(pressure_pa)
        return any(whole_pa + delta in self._sent_counts
                   for delta in range(-tolerance_pa, tolerance_pa + 1))

    def _on_pressure_setpoint(self, msg: Float64) -> None:
        """A setpoint that is not one of ours: someone (`pma set`, `ros2 topic pub`, another
        controller) commands the pressure. Released, and theirs is sent again: the
        controller may have published one more command after theirs reached the driver."""
        if self._controller.target_m is None or self._sent_lately(msg.data):
            return
        self._release(f'another node commanded {msg.data:.0f} Pa on pma/pressure_setpoint')
        if math.isfinite(msg.data) and \
                0.0 <= msg.data <= self._controller.settings.max_gauge_pressure_pa:
            self._command(float(msg.data))

    def _check_device_setpoint(self, device_setpoint_pa: float) -> None:
        """Release when the device has held a setpoint the controller did not send for
        OTHER_SOURCE_S (the driver rounds to whole Pa, hence the tolerance)."""
        now = time.monotonic()
        if (self._controller.target_m is None or self._fault
                or self._sent_lately(device_setpoint_pa, tolerance_pa=1) or not self._sent):
            self._device_differs_since = None
            return
        if self._device_differs_since is None:
            self._device_differs_since = now
        elif now - self._device_differs_since >= OTHER_SOURCE_S:
            self._release(f'the device holds {device_setpoint_pa:.0f} Pa, which the controller '
                          f'did not command, for {OTHER_SOURCE_S:g} s: a sweep runs, or the '
                          'driver refuses these commands (its log says why)')

    def _release(self, reason: str) -> None:
        """Give the valve up to whoever commands it now: the target goes, a goal aborts."""
        self._stats['released to another source'] += 1
        self.get_logger().warning(f'released the target: {reason}')
        self._let_go(f'released: {reason}', fault=False)

    def _control_state(self, state: PmaState, output: ControlOutput) -> ControlState:
        msg = ControlState()
        msg.header = state.header
        target = self._controller.target_m
        if self._fault:
            msg.mode, msg.message = ControlState.MODE_FAULT, self._fault
        elif target is None:
            msg.mode = ControlState.MODE_IDLE
            if self._let_go_reason:
                msg.message = f'hold ended: {self._let_go_reason}'
        elif self._goal is not None:
            msg.mode = ControlState.MODE_GOAL
        else:
            msg.mode = ControlState.MODE_STREAM if self._streamed else ControlState.MODE_HOLD
        msg.target_length_m = math.nan if target is None else target
        msg.setpoint_length_m = output.setpoint_length_m
        msg.measured_length_m = state.length_m
        msg.estimated_length_m = output.estimated_length_m
        msg.model_length_m = output.model_length_m
        msg.bias_m = output.bias_m
        msg.gauge_pressure_pa = state.gauge_pressure_pa
        msg.feedforward_pa = output.feedforward_pa
        msg.feedback_pa = output.feedback_pa
        msg.gauge_pressure_command_pa = output.command_pa
        msg.saturated_low, msg.saturated_high = output.saturated_low, output.saturated_high
        msg.rate_limited = output.rate_limited
        return msg

    def _on_tick(self) -> None:
        """Goal bookkeeping and the stale check, TICK_S apart."""
        self._check_stale()
        if self._goal is not None:
            self._follow_goal(self._goal)
        self._sync_lease()

    def _sync_lease(self) -> None:
        """Hold the driver's commander lease exactly while steering a target."""
        if self._controller.target_m is not None and not self._fault:
            self._lease.hold()
        else:
            self._lease.release()

    def destroy_node(self) -> None:
        """A clean stop lets go of the lease (the pressure stays, as after a cancel), and
        waits briefly for the driver to have it: an unheard release would vent the muscle."""
        self._lease.release_before_exit()
        super().destroy_node()

    def _check_stale(self) -> None:
        if self._fault or self._controller.target_m is None:
            return
        timeout = self.get_parameter('stale_timeout_s').value
        last = self._last_sample_at
        if last is not None and time.monotonic() - last <= timeout:
            return
        if last is None:
            timeout = max(timeout, FIRST_SAMPLE_WAIT_S)
            if time.monotonic() - self._armed_at <= timeout:
                return
        age = 'none yet' if last is None else f'{time.monotonic() - last:.1f} s old'
        self._fault = (f'no usable pma/state sample for {timeout:g} s (latest: {age}): is the '
                       'driver running and active?')
        self._stats['faults'] += 1
        self.get_logger().error(self._fault)
        self._let_go(self._fault, fault=True)

    # -- targets -----------------------------------------------------------------------

    def _on_setpoint(self, msg: LengthSetpoint) -> None:
        now = time.monotonic()
        continued = (self._last_stream_at is not None
                     and now - self._last_stream_at < STREAM_REARM_QUIET_S)
        self._last_stream_at = now
        reason = self._fault
        if not reason and self._controller.target_m is None and self._let_go_reason \
                and continued:
            reason = (f'the hold ended ({self._let_go_reason}); a stream takes the muscle '
                      f'again after {STREAM_REARM_QUIET_S:g} s without a message, or send a goal')
        reason = reason or self._controller.set_target(msg.length_m)
        if reason:
            self.get_logger().warning(f'refused pma/length_setpoint: {reason}',
                                      throttle_duration_sec=2.0)
            return
        self._armed()
        self._streamed = True
        if self._goal is not None:
            self._end_goal(self._goal, False, 'preempted by pma/length_setpoint', 'abort')

    def _on_goal(self, _goal) -> GoalResponse:
        """Accept every goal: a refusal is an abort with the reason in the result, which a
        user at a terminal sees (a rejection would only say `accepted: false`)."""
        return GoalResponse.ACCEPT

    def _on_accepted(self, goal_handle) -> None:
        """Start steering at once; the goal's result is produced when it ends (_end_goal).

        One thread runs this node, so a goal must not wait inside a callback: it is followed
        by the tick. (A multi-threaded executor, which a blocking execute callback needs,
        added half a millisecond to every control step.)
        """
        request = goal_handle.request
        bad = next((f'{name} must be a finite number >= 0, got {value}' for name, value in
                    (('tolerance_m', request.tolerance_m), ('settle_s', request.settle_s),
                     ('timeout_s', request.timeout_s))
                    if not (math.isfinite(value) and value >= 0)), '')
        _, settle_s, timeout_s = goal_limits(request)
        if not bad and settle_s >= timeout_s:
            bad = (f'settle_s {settle_s:g} s is not shorter than timeout_s {timeout_s:g} s: '
                   'the goal could never succeed')
        reason = bad or self._fault or self._controller.set_target(request.length_m)
        if reason:
            self._end_goal(goal_handle, False, reason, 'abort')
            return
        if self._goal is not None:
            self._end_goal(self._goal, False, 'preempted by a new goal', 'abort')
        self._armed()
        self._goal, self._streamed = goal_handle, False
        self._goal_started = time.monotonic()
        self._inside_since = None
        self._measured.window_s = max(settle_s, MIN_MEASURED_WINDOW_S)

    def _follow_goal(self, goal_handle) -> None:
        request = goal_handle.request
        now = time.monotonic()
        elapsed = now - self._goal_started
        if goal_handle.is_cancel_requested:
            self._end_goal(goal_handle, False, 'canceled; the pressure stays where it is',
                           'canceled')
            self._let_go('the goal was canceled', fault=False)
            return
        output = self._last_output
        if output is None:        # no sample yet: _check_stale gives up after its wait
            return
        tolerance, settle_s, timeout_s = goal_limits(request)
        error = request.length_m - output.estimated_length_m
        goal_handle.publish_feedback(MoveToLength.Feedback(
            measured_length_m=self._last_state.length_m,
            estimated_length_m=output.estimated_length_m, error_m=error,
            gauge_pressure_command_pa=output.command_pa))
        if abs(error) > tolerance:
            self._inside_since = None
        elif self._inside_since is None:
            self._inside_since = now
        elif now - self._inside_since >= settle_s:
            settle_time = self._inside_since - self._goal_started
            self._end_goal(goal_handle, True, f'settled within {tolerance * 1000:.1f} mm for '
                           f'{settle_s:g} s after {settle_time:.2f} s; holding', 'succeed',
                           settle_time)
            return
        if elapsed > timeout_s:
            self._end_goal(goal_handle, False, f'not settled within {timeout_s:g} s (error '
                           f'{error * 1000:.1f} mm); still holding the target', 'abort')

    def _end_goal(self, goal_handle, success: bool, message: str, outcome: str,
                  settle_time_s: float = math.nan) -> None:
        """Produce the goal's result now: execute() runs the callback that reports it."""
        if self._goal is goal_handle:
            self._goal = None
        output = self._last_output
        result = MoveToLength.Result(
            success=success, message=message, settle_time_s=settle_time_s,
            measured_length_m=self._measured.mean(time.monotonic()),
            estimated_length_m=output.estimated_length_m if output is not None else math.nan)

        def report(handle):
            getattr(handle, {'succeed': 'succeed', 'abort': 'abort',
                             'canceled': 'canceled'}[outcome])()
            return result

        goal_handle.execute(report)
        text = f'move_to_length {goal_handle.request.length_m:.4f} m: {message}'
        if success:             # one call site per severity: rclpy refuses two at one line
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    # -- diagnostics -------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        output, target, fault = self._last_output, self._controller.target_m, self._fault
        stats, settings = self._stats, self._controller.settings
        status = DiagnosticStatus(name=f'{self.get_fully_qualified_name()}: length control',
                                  hardware_id='controller')
        if fault:
            status.level, status.message = DiagnosticStatus.ERROR, fault
        elif target is None and self._let_go_by_fault:
            status.level = DiagnosticStatus.WARN
            status.message = f'idle: the hold ended: {self._let_go_reason}'
        elif target is None:
            status.level, status.message = DiagnosticStatus.OK, 'idle (no target)'
        else:
            status.level, status.message = DiagnosticStatus.OK, f'holding {target:.4f} m'
        if self._startup_problem and not fault:
            status.level = DiagnosticStatus.WARN
            status.message = f'start-up parameters refused, kept the defaults: ' \
                             f'{self._startup_problem}; {status.message}'
        values = {'mode': settings.mode, 'target [m]': '-' if target is None else f'{target:.5f}',
                  'last hold ended': self._last_let_go,
                  **{key: str(value) for key, value in stats.items()}}
        if output is not None:
            values.update({'estimated length [m]': f'{output.estimated_length_m:.5f}',
                           'bias [m]': f'{output.bias_m:.5f}',
                           'command [Pa]': f'{output.command_pa:.0f}',
                           'saturated': str(output.saturated_low or output.saturated_high)})
        publish_status(self, self._diagnostics_pub, status, values)


def main(args=None) -> int:
    return run_single_threaded(LengthControllerNode, args)


if __name__ == '__main__':
    sys.exit(main())

