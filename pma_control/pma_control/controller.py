"""Length control of the muscle: hysteresis-model feedforward plus feedback, without ROS.

The plant from pressure to length is nonlinear (flat near 0 and 500 kPa) and hysteretic
(the length depends on the path). The model is model_node's own (pma_model's OnlineModel:
the memory rule, and what it learns online about this muscle). The feedforward inverts it
*from the muscle's current state* (pressure_for_length with BRANCH_AUTO: memory included),
which turns the plant into roughly "length in, length out". Where the model has learned
creep (a share of each change arriving over seconds), the feedforward aims ahead of the
setpoint by the share still lagging (OnlineModel.settled_aim_m), so the length arrives now
instead of a second or two late. The feedback is a PI
on the remaining length error, in metres, passed through the same inverse, so its gains are
dimensionless and need no retuning where the muscle is stiff or soft. It does not integrate
while the setpoint is still ramping to a new target: the error then is the valves' lag behind
a command the feedforward already gave, and integrating it overshoots the step.

The length sensor (HC-SR04) is noisy (~1.5 mm) and quantised (3 mm), so the error is taken
from an estimate, not from the raw reading: the model's length for the measured pressure
(smooth, no lag) plus a slowly learned bias (a scalar Kalman filter on measured - model),
which absorbs what the model gets wrong (a muscle unlike the fit, drift, creep). The
mix's own local offset (pma_model.local_offset) is off in the controller's model: this bias
is its measured-minus-model feedback, and one is enough.

Three modes, compared on the same simulated muscles in docs/control.md:
  'ff_fb'  feedforward + feedback (the default)
  'ff'     feedforward only: the model's inverse of the setpoint, nothing learned
  'fb'     feedback only: a PI from length error to pressure, no model (gains in Pa/m)

Safety: every command is within [0, max_gauge_pressure_pa]; a target outside the reachable
lengths is refused with the range.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass, fields

from pma_model.detector import BRANCH_AUTO
from pma_model.identification import OnlineRule

MODES = ('ff_fb', 'ff', 'fb')
MAX_CREEP_LEAD_SHARE = 0.9


@dataclass(frozen=True)
class ControllerSettings:
    """Every tuning knob, in SI units (docs/control.md explains each and how to retune)."""

    mode: str = 'ff_fb'
    max_gauge_pressure_pa: float = 500_000.0
    # 'ff_fb' feedback, in the length domain: correction_m = kp * e + ki * integral(e).
    kp: float = 0.3
    ki_per_s: float = 3.0
    # 'fb' feedback, in the pressure domain: p = -(kp * e + ki * integral(e)). Table 1's
    # mean slope is 500 kPa / 5.86 cm = 8.5e6 Pa/m; these are 0.6 and 2 /s times it.
    fb_kp_pa_per_m: float = 5.0e6
    fb_ki_pa_per_m_s: float = 1.7e7
    fb_filter_time_constant_s: float = 0.15
    # Errors smaller than this are not integrated: a quantised sensor must not hunt [m].
    error_deadband_m: float = 0.0005
    max_pressure_rate_pa_s: float = 600_000.0
    max_setpoint_rate_m_s: float = 0.05
    # The feedforward leads for at most this creep share (0: no lead; docs/control.md).
    creep_lead_max_share: float = 0.5
    # Bias observer: how fast the model's error may wander [m/sqrt(s)], and the sensor noise.
    bias_process_noise_m: float = 0.001
    length_noise_m: float = 0.0018

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {self.mode!r}')
        for item in fields(self):
            value = getattr(self, item.name)
            if item.name != 'mode' and not (isinstance(value, (int, float))
                                            and math.isfinite(value) and value >= 0):
                raise ValueError(f'{item.name} must be a finite number >= 0, got {value!r}')
        for name in ('max_gauge_pressure_pa', 'max_pressure_rate_pa_s', 'max_setpoint_rate_m_s',
                     'length_noise_m'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)!r}')
        if not self.creep_lead_max_share <= MAX_CREEP_LEAD_SHARE:
            raise ValueError(f'creep_lead_max_share must be <= {MAX_CREEP_LEAD_SHARE} (the lead '
                             f'is 1 / (1 - share) times the change), got '
                             f'{self.creep_lead_max_share!r}')


@dataclass(frozen=True)
class ControlOutput:
    """One step of the loop: what was commanded and why (ControlState on the ROS side)."""

    command_pa: float
    feedforward_pa: float          # the model's inverse of the setpoint; NaN in 'fb'
    feedback_pa: float             # what the feedback added before the limits
    setpoint_length_m: float       # after the setpoint-rate limit; NaN without a target
    estimated_length_m: float
    model_length_m: float          # NaN in 'fb'
    bias_m: float                  # learned measured - model
    saturated_low: bool
    saturated_high: bool
    rate_limited: bool


def _feedback_only_here(model: OnlineRule) -> OnlineRule:
    """The model without the mix's local offset: the bias filter below is this controller's
    measured-minus-model feedback, and the offset would learn the same residual a second time
    (measured: 0.1 Hz tracking 4-14 % worse with both, docs/control.md)."""
    return model.without_local_offset()


class LengthController:
    """Feed it every sample (`update`, or `command` then `explain`); aim it with `set_target`."""

    def __init__(self, model: OnlineRule, settings: ControllerSettings | None = None):
        self.settings = settings or ControllerSettings()
        self.model = _feedback_only_here(model)
        self.reset()

    # -- state -------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget target, integral and bias (a new muscle, or after a fault)."""
        self.target_m: float | None = None
        self._setpoint_m: float | None = None
        self._ramping = False
        self._integral = 0.0
        self._bias_m = 0.0
        self._bias_var = (10.0 * self.settings.length_noise_m) ** 2     # unknown at first
        self._filtered_m = math.nan
        self._command_pa: float | None = None
        self._last_t: float | None = None
        self._dt = 0.0
        # (aim, wanted, the command before) of the last `command`, until `explain`
        self._unexplained: tuple[float, float, float] | None = None

    def replace_model(self, model: OnlineRule) -> None:
        """A new fit (a refit was loaded): keep the muscle's history and the learned bias."""
        model = _feedback_only_here(model)
        model.resume_from(self.model)
        self.model = model

    @property
    def command_pa(self) -> float | None:
        return self._command_pa

    @property
    def bias_m(self) -> float:
        return self._bias_m

    def reachable_range_m(self) -> tuple[float, float]:
        """Lengths the muscle can be held at: the model's over 0..max, plus the learned bias."""
        p_max = self.settings.max_gauge_pressure_pa
        ends = [float(branch.length(p)) for branch in (self.model.increasing,
                                                       self.model.decreasing)
                for p in (0.0, p_max)]
        bias = self._bias_m if self.settings.mode != 'ff' else 0.0
        return min(ends) + bias, max(ends) + bias

    def set_target(self, length_m: float) -> str:
        """Aim for `length_m`; say why it cannot be ('' when it can)."""
        if isinstance(length_m, bool) or not isinstance(length_m, (int, float)) \
                or not math.isfinite(length_m):
            return f'target length must be a finite number of metres, got {length_m!r}'
        low, high = self.reachable_range_m()
        if not low <= length_m <= high:
            return (f'target {length_m:.4f} m is not reachable: reachable '
                    f'[{low:.4f}, {high:.4f}] m with 0..'
                    f'{self.settings.max_gauge_pressure_pa:.0f} Pa')
        self.target_m = float(length_m)
        return ''

    def clear_target(self) -> None:
        """Stop steering; later updates repeat the last command (the muscle stays put)."""
        self.target_m = None
        self._setpoint_m = None
        self._ramping = False
        self._integral = 0.0

    # -- the loop ----------------------------------------------------------------------

    def update(self, t_s: float, gauge_pressure_pa: float, measured_length_m: float
               ) -> ControlOutput:
        """One sample in, one command out, explained. A NaN length (no echo) leaves the bias
        as it is."""
        return self.explain(self.command(t_s, gauge_pressure_pa, measured_length_m))

    def command(self, t_s: float, gauge_pressure_pa: float, measured_length_m: float
                ) -> ControlOutput:
        """`update` without its explanation: in 'ff_fb' the output's feedforward_pa is NaN
        and its feedback_pa the whole command until `explain`. The pure feedforward costs an
        inverse of its own, which a loop makes after sending the command."""
        self._unexplained = None
        s = self.settings
        dt = 0.0 if self._last_t is None else max(0.0, t_s - self._last_t)
        self._last_t, self._dt = t_s, dt
        model_m = math.nan
        if s.mode == 'fb':
            estimate = self._filter_measurement(measured_length_m, dt)
        else:
            # 'ff' learns nothing: the model predicts from pressure alone.
            learn_from = measured_length_m if s.mode == 'ff_fb' else math.nan
            model_m = self.model.step(gauge_pressure_pa, learn_from, t_s).length_m
            if s.mode == 'ff_fb':
                self._observe_bias(model_m, measured_length_m, dt)
            estimate = model_m + self._bias_m
        if self._command_pa is None:     # bumpless start: from the pressure the muscle has
            self._command_pa = min(max(gauge_pressure_pa, 0.0), s.max_gauge_pressure_pa) \
                if math.isfinite(gauge_pressure_pa) else 0.0
        if self.target_m is None:
            return self._output(self._command_pa, math.nan, 0.0, setpoint=math.nan,
                                estimate=estimate, model_m=model_m)
        setpoint = self._advance_setpoint(estimate, dt)
        error = setpoint - estimate if math.isfinite(estimate) else 0.0
        if s.mode == 'fb':
            return self._feedback_only(setpoint, estimate, error, dt)
        return self._with_feedforward(setpoint, estimate, model_m, error, dt)

    def _observe_bias(self, model_m: float, measured_m: float, dt: float) -> None:
        s = self.settings
        self._bias_var += s.bias_process_noise_m ** 2 * dt
        if not (math.isfinite(measured_m) and math.isfinite(model_m)):
            return
        gain = self._bias_var / (self._bias_var + s.length_noise_m ** 2)
        self._bias_m += gain * (measured_m - model_m - self._bias_m)
        self._bias_var *= 1.0 - gain

    def _filter_measurement(self, measured_m: float, dt: float) -> float:
        """Feedback only: a first-order filter trades the sensor's noise for lag."""
        if math.isfinite(measured_m):
            if not math.isfinite(self._filtered_m):
                self._filtered_m = measured_m
            else:
                tau = self.settings.fb_filter_time_constant_s
                self._filtered_m += (measured_m - self._filtered_m) * dt / (tau + dt)
        return self._filtered_m

    def _advance_setpoint(self, estimate: float, dt: float) -> float:
        if self._setpoint_m is None:
            self._setpoint_m = estimate if math.isfinite(estimate) else self.target_m
        step = self.settings.max_setpoint_rate_m_s * dt
        remaining = self.target_m - self._setpoint_m
        self._ramping = abs(remaining) > step
        self._setpoint_m = self._setpoint_m + math.copysign(step, remaining) \
            if self._ramping else self.target_m
        return self._setpoint_m

    def _with_feedforward(self, setpoint: float, estimate: float, model_m: float, error: float,
                          dt: float) -> ControlOutput:
        s = self.settings
        bias = self._bias_m if s.mode == 'ff_fb' else 0.0
        # The model must make this much now: through creep, aimed ahead of the setpoint.
        aim = self.model.settled_aim_m(setpoint - bias, s.creep_lead_max_share)
        if s.mode == 'ff':
            feedforward, _, _ = self._inverse(aim)
            return self._limited(feedforward, feedforward, setpoint=setpoint,
                                 estimate=estimate, model_m=model_m, low=False, high=False)
        integrate = abs(error) > s.error_deadband_m and not self._ramping
        step = s.ki_per_s * error * dt if integrate else 0.0
        self._integral += step
        wanted, low, high = self._inverse(aim + s.kp * error + self._integral)
        if (low and error > 0) or (high and error < 0):
            self._integral -= step            # anti-windup: the inverse is at an end already
        self._unexplained = (aim, wanted, self._command_pa)
        return self._limited(wanted, math.nan, setpoint=setpoint, estimate=estimate,
                             model_m=model_m, low=low, high=high)

    def explain(self, output: ControlOutput) -> ControlOutput:
        """The last `command`'s output with its feedforward and feedback parts (the model has
        not moved since, so its inverse is the one the command was made with)."""
        if self._unexplained is None:
            return output
        aim, wanted, command_before = self._unexplained
        self._unexplained = None
        feedforward, _, _ = self._inverse(aim, command_before)
        return dataclasses.replace(output, feedforward_pa=feedforward,
                                   feedback_pa=_feedback_part(wanted, feedforward))

    def _feedback_only(self, setpoint: float, estimate: float, error: float,
                       dt: float) -> ControlOutput:
        s = self.settings
        if self._setpoint_m is not None and self._integral == 0.0:
            self._integral = self._command_pa        # bumpless: from the current command
        # Length falls as pressure rises: a muscle too long (error < 0) needs more pressure.
        if abs(error) > s.error_deadband_m:
            self._integral -= s.fb_ki_pa_per_m_s * error * dt
        self._integral = min(max(self._integral, 0.0), s.max_gauge_pressure_pa)  # anti-windup
        wanted = self._integral - s.fb_kp_pa_per_m * error
        return self._limited(wanted, math.nan, setpoint=setpoint, estimate=estimate,
                             model_m=math.nan, low=wanted <= 0.0,
                             high=wanted >= s.max_gauge_pressure_pa)

    def _inverse(self, model_length_m: float, command_pa: float | None = None
                 ) -> tuple[float, bool, bool]:
        """(pressure, at 0 Pa end, at max end) that makes the model this long from here; a
        model without an answer keeps the command (`command_pa`, else the last one)."""
        result = self.model.pressure_for_length(model_length_m, BRANCH_AUTO)
        if result.success:
            return result.gauge_pressure_pa, False, False
        if not math.isfinite(result.min_length_m):
            return (self._command_pa if command_pa is None else command_pa), False, False
        if model_length_m < result.min_length_m:     # shorter than possible: full pressure
            return self.settings.max_gauge_pressure_pa, False, True
        return 0.0, True, False

    def _limited(self, wanted: float, feedforward: float, *, setpoint: float, estimate: float,
                 model_m: float, low: bool, high: bool) -> ControlOutput:
        s = self.settings
        clamped = min(max(wanted, 0.0), s.max_gauge_pressure_pa)
        step = s.max_pressure_rate_pa_s * self._dt
        command = min(max(clamped, self._command_pa - step), self._command_pa + step)
        return self._output(command, feedforward, _feedback_part(wanted, feedforward),
                            setpoint=setpoint, estimate=estimate, model_m=model_m,
                            low=low or wanted < 0.0,
                            high=high or wanted > s.max_gauge_pressure_pa,
                            rate_limited=command != clamped)

    def _output(self, command: float, feedforward: float, feedback: float, *,
                setpoint: float, estimate: float, model_m: float, low: bool = False,
                high: bool = False, rate_limited: bool = False) -> ControlOutput:
        self._command_pa = command
        return ControlOutput(command, feedforward, feedback, setpoint, estimate, model_m,
                             self._bias_m, low, high, rate_limited)


def _feedback_part(wanted: float, feedforward: float) -> float:
    """What the feedback adds to the feedforward (all of `wanted` without a feedforward)."""
    return wanted - feedforward if math.isfinite(feedforward) else wanted


class RecentMean:
    """The mean of the valid readings of the last `window_s`: the sensor's length, filtered.

    The HC-SR04 reads in 3 mm steps with ~1.5 mm noise, so one reading says little; a goal's
    result reports the mean over its settle window, as its action file promises.
    """

    def __init__(self, window_s: float):
        self.window_s = window_s
        self._readings: collections.deque[tuple[float, float]] = collections.deque()

    def add(self, t_s: float, value: float) -> None:
        """A reading at `t_s` (monotonic seconds); a NaN (no echo) is left out."""
        if math.isfinite(value):
            self._readings.append((t_s, value))
        self._forget_before(t_s - self.window_s)

    def mean(self, now_s: float) -> float:
        """NaN when no valid reading came within the window."""
        self._forget_before(now_s - self.window_s)
        if not self._readings:
            return math.nan
        return math.fsum(value for _, value in self._readings) / len(self._readings)

    def _forget_before(self, t_s: float) -> None:
        while self._readings and self._readings[0][0] < t_s:
            self._readings.popleft()
