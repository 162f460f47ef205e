"""model_node: online branch-aware length prediction and the pressure_for_length service.

A thin ROS wrapper around pma_model.params / memory / adaptation: it declares the model's
parameters, validates any change as a whole (an invalid set is rejected with the reason and
the old model stays), follows `pma/state`, and answers the inverse model.
"""

from __future__ import annotations

import math
import os
import sys
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy

from pma_common import names
from pma_common.diagnostics import publish_status
from pma_common.node import run_single_threaded, take_queued
from pma_common.parameters import declare_or_keep_default
from pma_common.sequence import SequenceTracker
from pma_common.service import SERVICE_QOS
from pma_interfaces.msg import ModelParams as ModelParamsMsg
from pma_interfaces.msg import PmaPrediction, PmaState
from pma_interfaces.srv import PressureForLength
from pma_model.branches import BRANCH_FORMS
from pma_model.detector import BRANCH_NAMES
from pma_model.identification import (
    CORRECTION_KNOTS_PA,
    CREEP_TIME_CONSTANTS_S,
    MAX_EXCESS_LOSS_M2S,
)
from pma_model.params import ModelParams, ParamsError, default_params

_DESCRIPTIONS = {
    'branch_form': 'branch shape: ' + ' or '.join(
        f"'{name}' ({form.formula})" for name, form in BRANCH_FORMS.items()),
    'memory': "minor-loop memory: 'mix' ('identify' and 'play' side by side, each learning, "
              "weighted by their recent errors), 'identify' (learned blend of Madelung and "
              "play-like scanning curves), 'play' (friction band between the branches), "
              "'madelung' (turning-point stack) or 'switch' (the paper's jump between the "
              'major branches)',
    'deadband_pa': 'pressure must move this far against the current direction before a '
                   'reversal counts [Pa]',
    'max_gauge_pressure_pa': 'highest gauge pressure the inverse may answer with [Pa]',
}
# Queues sized in time at the driver's top rate (1 kHz), so that a stall of the node or of a
# subscriber loses nothing while it lasts less than this (stalls measured in the soak of
# bench/bench_model_node.py: docs/model.md §7-8).
STATE_QUEUE_DEPTH = 2000        # 2 s
PREDICTION_QUEUE_DEPTH = 1000   # 1 s
QUEUED_STATES_LIMIT = 100       # states predicted at once before the service gets a turn

_RANGES = {
    'deadband_pa': (0.0, 250_000.0),
    'max_gauge_pressure_pa': (10_000.0, 1_000_000.0),
    'adaptation.time_constant_s': (1.0, 3600.0),
    'identification.play_share_rising': (0.0, 1.0),
    'identification.play_share_falling': (0.0, 1.0),
    # Within the share's own limit too (IdentificationSettings): the share stays within 0..1.
    'identification.play_share_slope_rising': (-1.0, 1.0),
    'identification.play_share_slope_falling': (-1.0, 1.0),
    'identification.play_rule_excess_loss_m2s': (-MAX_EXCESS_LOSS_M2S, MAX_EXCESS_LOSS_M2S),
}


def _describe(name: str) -> str:
    if name in _DESCRIPTIONS:
        return _DESCRIPTIONS[name]
    if name.startswith('adaptation.'):
        return f'online drift adaptation (rest-length shift, stroke gain): {name.split(".", 1)[1]}'
    if name.startswith('identification.'):
        return (f'online identification (docs/model.md): {name.split(".", 1)[1]}; the learned '
                'values are published on pma/model_params')
    direction, form, field = name.split('.')
    return f'{direction} branch, {form} form: {field} (SI units; suffix names the unit)'


class ModelNode(Node):
    def __init__(self, **kwargs):
        super().__init__('model_node', **kwargs)
        self._lock = threading.Lock()
        defaults = default_params()
        # The model's own parameter names (others, e.g. use_sim_time, are not the model's).
        self._model_parameter_names = tuple(defaults.to_ros_parameters())
        refused = []     # start-up overrides of the wrong type or out of range (defaults kept)
        for name, value in defaults.to_ros_parameters().items():
            descriptor = ParameterDescriptor(description=_describe(name))
            if name in _RANGES:
                low, high = _RANGES[name]
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=low, to_value=high, step=0.0)]
            refused.append(declare_or_keep_default(self, name, value, descriptor))
        self.declare_parameter('params_file', '', ParameterDescriptor(
            description='params file (refit output) loaded at start and reloaded when it '
                        'changes; empty = none'))
        refused.append(declare_or_keep_default(
            self, 'params_file_check_period_s', 1.0, ParameterDescriptor(
                description='how often the params file is checked for changes [s]',
                floating_point_range=[FloatingPointRange(from_value=0.1, to_value=60.0,
                                                         step=0.0)])))
        refused = [reason for reason in refused if reason is not None]

        # Why the start-up overrides were not all taken (shown in /diagnostics until a
        # valid change is applied); None: they were.
        self._startup_problem: str | None = None
        self._ready = False
        if refused:
            self._startup_problem = f'refused, kept the defaults: {"; ".join(refused)}'
            self.get_logger().error(f'invalid parameters {self._startup_problem}')
        try:
            self._params = ModelParams.from_ros_parameters(self._model_parameter_values())
        except ParamsError as error:
            # Overrides given with --ros-args/--params-file that do not validate: say so and
            # run on the shipped defaults rather than not at all, and show the defaults as
            # the parameters (else `ros2 param get` would show values not in use, and every
            # later change would be judged together with the bad one).
            self.get_logger().error(f'invalid model parameters, using the defaults: {error}')
            self._startup_problem = f'invalid, running on the defaults: {error}'
            self._params = defaults
            self.set_parameters([Parameter(name, value=value) for name, value
                                 in defaults.to_ros_parameters().items()])
        self._model = self._params.build_online()
        self._published_learning = -1
        self._latest_state: PmaState | None = None
        self._stats = {'samples': 0, 'nan_pressure': 0, 'nan_length': 0, 'sum_sq_residual': 0.0,
                       'residuals': 0}
        # States that never reached this node, by the device's PmaState.seq: each is a
        # prediction that will never be made (the driver's own losses included).
        self._state_sequence = SequenceTracker()

        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        self._params_pub = self.create_publisher(ModelParamsMsg, names.MODEL_PARAMS, latched)
        self._prediction_pub = self.create_publisher(PmaPrediction, names.PREDICTION,
                                                     PREDICTION_QUEUE_DEPTH)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 1)
        # Every sample is predicted, so pma/state is taken as a recorder takes it: reliable,
        # and queued for 2 s. Best effort (REP-2003's sensor data, for consumers that want
        # the latest) lost every sample beyond Fast DDS's 512-sample shared-memory port once
        # the process stalled over half a second; reliable has them resent from the driver's
        # history, and the driver's keep-last writer is never held up by a slow reader. A
        # driver that publishes best effort is followed in best effort (said in the log).
        self._state_reliability = ReliabilityPolicy.RELIABLE
        self._state_subscription = self._subscribe_states()
        # Queues a burst (pma_common.service.SERVICE_QOS): with the default 10, of 200
        # requests in flight from 4 clients only 11-41 were answered.
        self.create_service(PressureForLength, names.PRESSURE_FOR_LENGTH,
                            self._on_pressure_for_length, qos_profile=SERVICE_QOS)
        self.create_timer(1.0, self._publish_diagnostics)

        # What the params file looked like when last read (inode, size, mtime), or the
        # reason it could not be stat'ed; and why its last version was refused (None: loaded).
        self._params_file_seen: tuple | str | None = None
        self._params_file_problem: str | None = None
        period = self.get_parameter('params_file_check_period_s').value
        self.create_timer(period, self._check_params_file)
        self._check_params_file(at_start=True)
        self._publish_params()
        self._ready = True
        self.get_logger().info(
            f'model_node ready: {self._params.branch_form} branches, {self._params.memory} '
            f'memory, adaptation {"on" if self._params.adaptation.enabled else "off"}')

    # --- parameters -----------------------------------------------------------------

    def _model_parameter_values(self, changes: dict | None = None) -> dict:
        values = {name: self.get_parameter(name).value for name in self._model_parameter_names}
        values.update(changes or {})
        return values

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Validate the new set as a whole; no side effects here (rclpy's contract).

        A new params_file is read and validated here too (on top of the rest of the set), so
        a missing, unreadable or invalid file is refused to the caller, not only in the log.
        """
        changes = {p.name: p.value for p in parameters if p.name in self._model_parameter_names}
        params_file = next((p.value for p in parameters if p.name == 'params_file'), '')
        if not changes and not params_file:
            return SetParametersResult(successful=True)
        try:
            params = ModelParams.from_ros_parameters(self._model_parameter_values(changes))
            if params_file:
                ModelParams.load_yaml(params_file, base=params)
        except ParamsError as error:
            reason = f'rejected, the model is unchanged: {error}'
            self.get_logger().warning(reason)
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        if any(p.name in self._model_parameter_names for p in parameters):
            self._apply_model_parameters()
        if any(p.name == 'params_file' for p in parameters):
            self._params_file_seen = self._params_file_problem = None
            self._check_params_file()

    def _apply_model_parameters(self) -> None:
        params = ModelParams.from_ros_parameters(self._model_parameter_values())
        with self._lock:
            built = params
            if params.branches() == self._params.branches() and \
                    params.identification == self._params.identification:
                # Same muscle, same starting point: keep what has been learned about it.
                built = params.with_learned(self._model.learned())
            model = built.build_online()
            model.resume_from(self._model)  # keep the muscle's history, not "at rest"
            self._params = params
            self._model = model
            if self._ready:     # a valid change after start-up replaces what start-up refused
                self._startup_problem = None
        self.get_logger().info(
            f'model updated: {params.branch_form} branches, {params.memory} memory, adaptation '
            f'{"on" if params.adaptation.enabled else "off"}')
        self._publish_params()

    def _check_params_file(self, at_start: bool = False) -> None:
        """Load the params file at start and whenever it changes (hot reload after a refit).

        Polled by stat (which never blocks); a version that cannot be read or does not
        validate is refused once, with a log line and the /diagnostics message, and the
        model in use stays until a good version appears.
        """
        path = self.get_parameter('params_file').value
        if not path:
            self._params_file_problem = None
            return
        try:
            info = os.stat(path)
            seen: tuple | str = (info.st_ino, info.st_size, info.st_mtime_ns)
        except OSError as error:
            seen = f'cannot read params file {path}: {error.strerror}'
        if seen == self._params_file_seen:
            return
        self._params_file_seen = seen
        if isinstance(seen, str):
            self._refuse_params_file(seen, at_start)
            return
        try:
            loaded = ModelParams.load_yaml(path, base=self._params)
        except ParamsError as error:
            self._refuse_params_file(str(error), at_start)
            return
        result = self.set_parameters_atomically([
            Parameter(name, value=value) for name, value in loaded.to_ros_parameters().items()])
        if not result.successful:
            self._refuse_params_file(result.reason, at_start)
            return
        self._params_file_problem = None
        self.get_logger().info(f'loaded model parameters from {path}')

    def _refuse_params_file(self, reason: str, at_start: bool) -> None:
        self._params_file_problem = reason
        if at_start:
            self.get_logger().error(
                f'params file not loaded, running on the start-up parameters (the defaults '
                f'and any --ros-args overrides): {reason}; checking the file again')
        else:
            self.get_logger().error(f'params file not loaded, the model is unchanged: {reason}'
                                    '; checking the file again')

    def _publish_params(self) -> None:
        with self._lock:
            learned = self._model.learned()
            drift = self._model.drift
            counts = (self._model.samples_learned, self._model.samples_rejected)
            mix = self._model.weights_by_rule()
        # What this message says was learned: the diagnostics tick republishes only when more
        # has been (the start-up message must not be sent twice, unchanged).
        self._published_learning = counts[0]
        params = self._params.with_learned(learned)
        msg = ModelParamsMsg()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.form = params.branch_form
        msg.memory = params.memory
        msg.parameters_yaml = params.to_yaml()
        msg.deadband_pa = float(params.deadband_pa)
        msg.max_gauge_pressure_pa = float(params.max_gauge_pressure_pa)
        msg.adaptation_enabled = bool(params.adaptation.enabled)
        msg.identification_enabled = bool(learned.enabled)
        msg.play_share_rising = learned.play_share_rising
        msg.play_share_falling = learned.play_share_falling
        msg.play_share_slope_rising = learned.play_share_slope_rising
        msg.play_share_slope_falling = learned.play_share_slope_falling
        msg.branch_correction_pressures_pa = list(CORRECTION_KNOTS_PA)
        msg.branch_correction_m = list(learned.branch_correction_m)
        msg.branch_difference_m = list(learned.branch_difference_m)
        msg.creep_time_constants_s = list(CREEP_TIME_CONSTANTS_S)
        msg.creep_gains = list(learned.creep_gains)
        msg.mix_rules, msg.mix_weights = list(mix), list(mix.values())
        msg.play_rule_correction_m = list(learned.play_rule_correction_m)
        msg.play_rule_difference_m = list(learned.play_rule_difference_m)
        msg.play_rule_creep_gains = list(learned.play_rule_creep_gains)
        msg.samples_learned, msg.samples_rejected = counts
        msg.adaptation_offset_m = drift.offset_m if params.adaptation.enabled else 0.0
        msg.adaptation_gain = drift.gain if params.adaptation.enabled else 1.0
        self._params_pub.publish(msg)

    # --- stream ---------------------------------------------------------------------

    def _subscribe_states(self):
        return self.create_subscription(
            PmaState, names.STATE, self._on_states,
            QoSProfile(depth=STATE_QUEUE_DEPTH, reliability=self._state_reliability),
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=self._on_incompatible_state_qos))

    def _on_incompatible_state_qos(self, event) -> None:
        policy = QoSPolicyKind(event.last_policy_kind)
        if policy != QoSPolicyKind.RELIABILITY:
            self.get_logger().error(f'{self._state_subscription.topic_name}: a publisher\'s '
                                    f'QoS does not match ({policy.name.lower()})')
            return
        if self._state_reliability == ReliabilityPolicy.BEST_EFFORT:
            return        # another best-effort publisher: the switch is made or on its way
        self._state_reliability = ReliabilityPolicy.BEST_EFFORT
        # Not from inside the subscription's own event callback: from a timer, at once.
        self._resubscribe_timer = self.create_timer(0.0, self._resubscribe_states)

    def _resubscribe_states(self) -> None:
        self.destroy_timer(self._resubscribe_timer)
        old = self._state_subscription
        topic = old.topic_name
        self._state_subscription = self._subscribe_states()
        self.destroy_subscription(old)
        self.get_logger().warning(
            f'{topic} is published best effort (the driver\'s qos_reliability): '
            'subscribed best effort to match; a stall of this node over about half a second '
            'at 1 kHz now loses samples')

    def _on_states(self, state: PmaState) -> None:
        """The executor's state, then those queued behind it (pma_common.node.take_queued)."""
        self._on_state(state)
        for queued, _info in take_queued(self._state_subscription, QUEUED_STATES_LIMIT):
            self._on_state(queued)

    def _on_state(self, state: PmaState) -> None:
        pressure = state.gauge_pressure_pa
        measured = state.length_m
        with self._lock:
            self._stats['samples'] += 1
            first = self._stats['samples'] == 1
            self._state_sequence.add(state.seq)
            if not math.isfinite(pressure):
                # Still one prediction per sample (NaN), so the two streams line up.
                self._stats['nan_pressure'] += 1
                self.get_logger().warning(
                    f'sample seq {state.seq}: pressure is {pressure}; predicted length NaN',
                    throttle_duration_sec=5.0)
            else:
                self._latest_state = state
            stamp = state.header.stamp
            prediction = self._model.step(pressure, measured,
                                          stamp.sec + 1e-9 * stamp.nanosec or None)
            predicted, branch = prediction.length_m, prediction.branch
            offset, gain = ((prediction.offset_m, prediction.gain)
                            if self._params.adaptation.enabled else (0.0, 1.0))
            if math.isfinite(measured) and math.isfinite(predicted):
                residual = measured - predicted
                self._stats['sum_sq_residual'] += residual * residual
                self._stats['residuals'] += 1
            else:
                residual = math.nan
                if not math.isfinite(measured):
                    self._stats['nan_length'] += 1
        msg = PmaPrediction()
        msg.header = state.header
        msg.gauge_pressure_pa = pressure
        msg.measured_length_m = measured
        msg.predicted_length_m = predicted
        msg.residual_m = residual
        msg.branch = branch
        msg.adaptation_offset_m = offset
        msg.adaptation_gain = gain
        if first:
            # 'no pma/state received yet' ends now: say so at once, before the prediction,
            # not up to a second later (a status read then would show the stale warning).
            self._publish_diagnostics()
        self._prediction_pub.publish(msg)

    # --- service --------------------------------------------------------------------

    def _on_pressure_for_length(self, request, response):
        target = request.length_m
        refusal = None
        if not math.isfinite(target):
            refusal = f'length_m must be a finite number, got {target}'
        elif target <= 0.0:
            refusal = f'length_m must be positive (metres), got {target}'
        elif request.branch not in BRANCH_NAMES:
            refusal = (f'unknown branch {request.branch}: use 0 (auto), 1 (increasing) or '
                       '2 (decreasing)')
        elif request.branch == PressureForLength.Request.BRANCH_AUTO and \
                self._latest_state is None:
            refusal = ('BRANCH_AUTO needs the current state, and no pma/state sample has been '
                       'received yet: is the driver running? Or ask for branch 1 or 2.')
        if refusal:
            response.success, response.message = False, refusal
            response.gauge_pressure_pa = math.nan
            response.min_length_m = response.max_length_m = math.nan
            return response
        with self._lock:
            result = self._model.pressure_for_length(target, request.branch)
        response.success = result.success
        response.message = result.message
        response.gauge_pressure_pa = result.gauge_pressure_pa
        response.branch = result.branch
        response.min_length_m, response.max_length_m = result.min_length_m, result.max_length_m
        return response

    # --- diagnostics ----------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        with self._lock:
            stats = dict(self._stats)
            sequence = self._state_sequence.stats()
            adapting = self._params.adaptation.enabled
            drift = self._model.drift
            learned = self._model.learned()
            learned_count = self._model.samples_learned
            mix = self._model.weights_by_rule()
            local_offset_m = self._model.local_offset_m if mix else math.nan
            first_loading = 'ended' if self._model.first_loading_ended else \
                f'{1e3 * self._model.virgin_term_m:.2f}'
        status = DiagnosticStatus()
        status.name = f'{self.get_fully_qualified_name()}: hysteresis model'
        status.hardware_id = 'model'
        rms = math.sqrt(stats['sum_sq_residual'] / stats['residuals']) \
            if stats['residuals'] else math.nan
        if stats['samples'] == 0:
            status.level, status.message = DiagnosticStatus.WARN, 'no pma/state received yet'
        elif stats['nan_pressure']:
            status.level = DiagnosticStatus.WARN
            status.message = f'{stats["nan_pressure"]} samples with non-finite pressure skipped'
        else:
            status.level, status.message = DiagnosticStatus.OK, 'predicting'
        if self._startup_problem is not None:
            status.level = DiagnosticStatus.WARN
            status.message = f'start-up parameters {self._startup_problem}; {status.message}'
        problem = self._params_file_problem
        if problem is not None:
            status.level = DiagnosticStatus.WARN
            status.message = f'params file not loaded, model unchanged: {problem}; ' \
                             f'{status.message}'
        values = {
            'samples': stats['samples'], 'samples_nan_pressure': stats['nan_pressure'],
            'samples_nan_length': stats['nan_length'], 'rms_residual_m': f'{rms:.6f}',
            'states_lost': sequence.lost, 'state_gaps': sequence.gaps,
            'state_reliability': self._state_reliability.name.lower(),
            'branch_form': self._params.branch_form, 'memory': self._params.memory,
            'params_file': self.get_parameter('params_file').value or '(none)',
            'params_file_loaded': 'no' if problem is not None else 'yes',
        }
        if adapting:
            values.update(adaptation_offset_m=f'{drift.offset_m:.6f}',
                          adaptation_gain=f'{drift.gain:.6f}')
        if learned.enabled:
            values.update(
                samples_learned=learned_count,
                play_share_rising=f'{learned.play_share_rising:.3f}',
                play_share_falling=f'{learned.play_share_falling:.3f}',
                play_share_slope_rising=f'{learned.play_share_slope_rising:.3f}',
                play_share_slope_falling=f'{learned.play_share_slope_falling:.3f}',
                branch_correction_mm=_millimetres(learned.branch_correction_m),
                branch_difference_mm=_millimetres(learned.branch_difference_m),
                creep_gains=' '.join(f'{v:.3f}' for v in learned.creep_gains),
                # A rested muscle's first loading, learned apart (docs/model.md §5): its
                # term in mm until the muscle has travelled 500 kPa, then 'ended'.
                first_loading_term_mm=first_loading)
        if mix:
            values.update(
                mix_weights=' '.join(f'{rule} {weight:.3f}' for rule, weight in mix.items()),
                # What the rules leave here, carried until pressure moves on (local_offset.py).
                local_offset_mm=f'{1e3 * local_offset_m:.2f}',
                play_rule_correction_mm=_millimetres(learned.play_rule_correction_m),
                play_rule_difference_mm=_millimetres(learned.play_rule_difference_m),
                play_rule_creep_gains=' '.join(f'{v:.3f}' for v in learned.play_rule_creep_gains))
        publish_status(self, self._diagnostics_pub, status, values)
        if (learned.enabled or adapting) and learned_count != self._published_learning:
            # What it has learned, latched at 1 Hz at most: a recording (or a restart from
            # its parameters_yaml) keeps it.
            self._publish_params()


def _millimetres(values) -> str:
    return ' '.join(f'{1e3 * v:.2f}' for v in values)


def main(args=None) -> int:
    return run_single_threaded(ModelNode, args)


if __name__ == '__main__':
    sys.exit(main())
