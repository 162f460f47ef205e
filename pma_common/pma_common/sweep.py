"""The profile of a Sweep goal (pma_interfaces/action/Sweep), checked and planned.

Plain Python, no ROS: the driver's action server runs the plan, tests check it here. Every
check is arithmetic on the goal's fields before anything is built, so a typo (`step_pa` 1 Pa,
`cycles` 4e9, a ramp at 1 Pa/s) costs nothing and is refused with its reason.

Stepped profiles (a `SweepPlan`: setpoints, each reached and held):
- 'staircase': one cycle goes 0 -> max in steps of `step_pa` and back to 0, holding `hold_s`
  at each step. Reversal pressures are turning points visited in turn, for minor loops:
  `[300e3, 150e3]` goes up to 300 kPa, down to 150 kPa, then on up to max and back down.
  Listing max itself puts the loops after it on the falling branch: `[500e3, 100e3, 250e3]`
  goes up to 500 kPa, down to 100 kPa, up to 250 kPa, then down to 0. Steps lie on the grid
  of multiples of `step_pa`, plus the turning points themselves.
- 'forc': a set of first-order reversal curves (FORCs), as staircases through generated
  turning points (`forc_turning_points`).

Streamed profiles (a `StreamPlan`: a pressure for every instant, sent at STREAM_RATE_HZ):
- 'ramp': the staircase's path (0, reversals..., max, 0) at `ramp_rate_pa_s`, holding
  `hold_s` at each turning point;
- 'sine': offset - amplitude * cos(2 pi f t), whole periods from the trough;
- 'csv': given (time, pressure) points, straight lines between them (`read_profile_csv`
  reads the file on the client; the points travel in the goal).

Every profile runs `cycles` times with `rest_s` at 0 Pa between cycles, and ends at 0 Pa.
"""

from __future__ import annotations

import bisect
import csv
import itertools
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

MAX_STEPS = 10_000  # a plan longer than this is a typo (step_pa of 1 Pa), not an experiment
MAX_PROFILE_POINTS = MAX_STEPS   # points of a 'csv' profile
STREAM_RATE_HZ = 20.0            # setpoints per second of a streamed profile
# Faster than any valve of the rig follows (the simulated one fills 0 -> 500 kPa in 1.4 s):
# a profile asking more is a unit mistake (kPa for Pa), or a step the stream cannot draw.
MAX_RATE_PA_S = 1_000_000.0
MAX_SINE_FREQUENCY_HZ = STREAM_RATE_HZ / 10   # at least 10 setpoints per period
MAX_DURATION_S = 86_400.0        # a streamed profile, or one rest, longer than a day is a typo

PROFILES = ('staircase', 'forc', 'ramp', 'sine', 'csv')
STREAMED_PROFILES = ('ramp', 'sine', 'csv')
FORC_FAMILIES = ('ascending', 'descending', 'both')

# The goal's profile fields each profile uses (besides `cycles` and `rest_s`, which all use);
# any other profile field must stay at its default, so a forgotten `profile: sine` is
# refused instead of running a staircase.
PROFILE_FIELDS = {
    'staircase': ('max_gauge_pressure_pa', 'step_pa', 'hold_s', 'reversal_pressures_pa'),
    'forc': ('max_gauge_pressure_pa', 'step_pa', 'hold_s', 'forc_count', 'forc_family'),
    'ramp': ('max_gauge_pressure_pa', 'ramp_rate_pa_s', 'hold_s', 'reversal_pressures_pa'),
    'sine': ('max_gauge_pressure_pa', 'sine_amplitude_pa', 'sine_offset_pa',
             'sine_frequency_hz'),
    'csv': ('max_gauge_pressure_pa', 'profile_time_s', 'profile_pressure_pa'),
}


class SweepError(ValueError):
    """A goal that cannot be run; the message says which field and why."""


@dataclass(frozen=True)
class SweepGoal:
    """pma_interfaces/action/Sweep's goal, without ROS (the .action documents each field)."""

    max_gauge_pressure_pa: float = 0.0
    step_pa: float = 0.0
    hold_s: float = 0.0
    cycles: int = 1
    reversal_pressures_pa: Sequence[float] = ()
    record: bool = False
    bag_path: str = ''
    note: str = ''
    profile: str = ''
    rest_s: float = 0.0
    ramp_rate_pa_s: float = 0.0
    sine_amplitude_pa: float = 0.0
    sine_offset_pa: float = 0.0
    sine_frequency_hz: float = 0.0
    profile_time_s: Sequence[float] = ()
    profile_pressure_pa: Sequence[float] = ()
    forc_count: int = 0
    forc_family: str = ''
    start_pressurised: bool = False   # no vent and wait for rest before the first level
    custom_data: Mapping[str, str] = field(default_factory=dict)   # more bag metadata

    @property
    def profile_name(self) -> str:
        return self.profile or 'staircase'

    @classmethod
    def of(cls, goal) -> SweepGoal:
        """The fields of any object that has them by name (a `Sweep.Goal` message, whose
        custom_data is a list of KeyValue)."""
        values = {item.name: getattr(goal, item.name) for item in fields(cls)
                  if item.name != 'custom_data'}
        entries = getattr(goal, 'custom_data', ())
        values['custom_data'] = (dict(entries) if isinstance(entries, Mapping)
                                 else {kv.key: kv.value for kv in entries})
        return cls(**values)


@dataclass(frozen=True)
class SweepPlan:
    """A stepped profile: every setpoint is reached, then held."""

    setpoints_pa: tuple[float, ...]   # every step, in order, starting with 0 Pa
    hold_s: float
    cycles: int
    rest_s: float = 0.0
    profile: str = 'staircase'
    turning_points_pa: tuple[float, ...] = ()   # one cycle's, from 0 to 0

    @property
    def step_count(self) -> int:
        return len(self.setpoints_pa)

    @property
    def peak_pa(self) -> float:
        return max(self.setpoints_pa)

    @property
    def hold_time_s(self) -> float:
        """Total time spent holding (the run takes longer: each step must be reached first)."""
        return self.step_count * self.hold_s + (self.cycles - 1) * self.rest_s

    def hold_at(self, step_index: int) -> float:
        """How long step `step_index` is held: `hold_s`, plus `rest_s` at the 0 Pa ending a
        cycle that another follows."""
        per_cycle = (self.step_count - 1) // self.cycles
        if 0 < step_index < self.step_count - 1 and step_index % per_cycle == 0:
            return self.hold_s + self.rest_s
        return self.hold_s

    def progress(self, step_index: int, hold_fraction: float = 0.0) -> float:
        """Fraction done (0..1) at `step_index` with this much of its hold elapsed."""
        fraction = (step_index + min(1.0, max(0.0, hold_fraction))) / self.step_count
        return min(1.0, max(0.0, fraction))


@dataclass(frozen=True)
class StreamPlan:
    """A streamed profile: a pressure for every instant, sent at `rate_hz`.

    One cycle lasts `cycle_s`; cycles follow each other with `rest_s` at 0 Pa in between.
    Knot profiles (ramp, csv) interpolate linearly between (knots_time_s, knots_pressure_pa)
    of one cycle; a sine is (amplitude, offset, frequency).
    """

    profile: str
    cycles: int
    rest_s: float
    cycle_s: float
    peak_pa: float
    knots_time_s: tuple[float, ...] = ()
    knots_pressure_pa: tuple[float, ...] = ()
    sine: tuple[float, float, float] | None = None
    rate_hz: float = STREAM_RATE_HZ

    @property
    def duration_s(self) -> float:
        return self.cycles * self.cycle_s + (self.cycles - 1) * self.rest_s

    @property
    def setpoint_count(self) -> int:
        """Setpoints sent, the first (at t = 0) and the last (at the end) included."""
        return math.ceil(self.duration_s * self.rate_hz - 1e-9) + 1

    def time_of(self, index: int) -> float:
        """When setpoint `index` is due, from the start of the profile [s]."""
        return min(index / self.rate_hz, self.duration_s)

    def index_at(self, elapsed_s: float) -> int:
        """The newest setpoint due `elapsed_s` after the start."""
        return min(self.setpoint_count - 1, math.floor(elapsed_s * self.rate_hz + 1e-9))

    def first_turn(self, first: int, last: int) -> int | None:
        """The first setpoint index in first..last-1 where the profile turns or stops (a
        reversal, a hold's or a rest's start), or None: a late stream skips stale setpoints,
        but not these, since a hysteresis loop is defined by where its pressure turned."""
        def at(index: int) -> float:
            return self.pressure_at(self.time_of(index))

        start = max(first, 1)
        before, here = at(start - 1), at(start)
        for index in range(start, min(last, self.setpoint_count - 1)):
            after = at(index + 1)
            if here != before and (here - before) * (after - here) <= 0.0:
                return index
            before, here = here, after
        return None

    def pressure_at(self, t_s: float) -> float:
        period = self.cycle_s + self.rest_s
        cycle = min(self.cycles - 1, max(0, math.floor(t_s / period)))
        tau = min(max(0.0, t_s - cycle * period), period)
        if tau > self.cycle_s:
            return 0.0                                     # resting between cycles
        if self.sine is not None:
            amplitude, offset, frequency = self.sine
            return offset - amplitude * math.cos(2 * math.pi * frequency * tau)
        times, pressures = self.knots_time_s, self.knots_pressure_pa
        k = bisect.bisect_right(times, tau)
        if k >= len(times):
            return pressures[-1]
        t0, t1 = times[k - 1], times[k]
        return pressures[k - 1] + (pressures[k] - pressures[k - 1]) * (tau - t0) / (t1 - t0)

    def progress(self, t_s: float) -> float:
        return min(1.0, max(0.0, t_s / self.duration_s))


# -- the staircase grid --------------------------------------------------------------------


def _first_step(start_pa: float, step_pa: float, rising: bool) -> int:
    """Grid index of the first step after `start_pa` (excluded) in the direction of travel."""
    if rising:
        return math.floor(start_pa / step_pa + 1e-9) + 1
    return math.ceil(start_pa / step_pa - 1e-9) - 1


def _grid_steps(start_pa: float, stop_pa: float, step_pa: float) -> tuple[int, int]:
    """(first index, count) of the grid points strictly between start and stop, by arithmetic.

    The estimate is corrected against the very comparison `staircase` makes, so both agree
    to the last float rounding.
    """
    eps = 1e-9 * step_pa
    rising = stop_pa > start_pa
    first = _first_step(start_pa, step_pa, rising)
    if rising:
        def inside(k: int) -> bool:
            return k * step_pa < stop_pa - eps
        last = math.ceil((stop_pa - eps) / step_pa) - 1
        while inside(last + 1):
            last += 1
        while last >= first and not inside(last):
            last -= 1
        return first, max(0, last - first + 1)

    def inside(k: int) -> bool:
        return k * step_pa > stop_pa + eps
    last = math.floor((stop_pa + eps) / step_pa) + 1
    while inside(last - 1):
        last -= 1
    while last <= first and not inside(last):
        last += 1
    return first, max(0, first - last + 1)


def staircase_length(start_pa: float, stop_pa: float, step_pa: float) -> int:
    """len(staircase(start_pa, stop_pa, step_pa)), without building it."""
    if stop_pa == start_pa:
        return 0
    return _grid_steps(start_pa, stop_pa, step_pa)[1] + 1


def staircase(start_pa: float, stop_pa: float, step_pa: float) -> list[float]:
    """Steps from `start_pa` (excluded) to `stop_pa` (included) on the grid of `step_pa`."""
    if stop_pa == start_pa:
        return []
    first, count = _grid_steps(start_pa, stop_pa, step_pa)
    direction = 1 if stop_pa > start_pa else -1
    return [(first + direction * i) * step_pa for i in range(count)] + [stop_pa]


# -- checks --------------------------------------------------------------------------------


def _check_finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise SweepError(f'{name} must be a finite number, got {value}')


def _check_top(max_gauge_pressure_pa: float, ceiling_pa: float) -> None:
    _check_finite('max_gauge_pressure_pa', max_gauge_pressure_pa)
    if max_gauge_pressure_pa <= 0:
        raise SweepError(f'max_gauge_pressure_pa must be > 0 Pa, got {max_gauge_pressure_pa}')
    if max_gauge_pressure_pa > ceiling_pa:
        raise SweepError(
            f'max_gauge_pressure_pa {max_gauge_pressure_pa:.0f} Pa is above the driver ceiling '
            f'{ceiling_pa:.0f} Pa (parameter max_gauge_pressure_pa)')


def _check_cycles_and_rest(cycles: int, rest_s: float) -> None:
    if cycles < 1:
        raise SweepError(f'cycles must be >= 1, got {cycles}')
    _check_finite('rest_s', rest_s)
    if not 0 <= rest_s <= MAX_DURATION_S:
        raise SweepError(f'rest_s must be within 0..{MAX_DURATION_S:.0f} s, got {rest_s}')


def _check_hold(hold_s: float) -> None:
    _check_finite('hold_s', hold_s)
    if hold_s < 0:
        raise SweepError(f'hold_s must be >= 0 s, got {hold_s}')


def _check_stepped(max_gauge_pressure_pa: float, step_pa: float, hold_s: float, cycles: int,
                   rest_s: float, *, ceiling_pa: float) -> None:
    """The fields every stepped profile (staircase, forc) shares."""
    _check_top(max_gauge_pressure_pa, ceiling_pa)
    _check_finite('step_pa', step_pa)
    _check_hold(hold_s)
    if step_pa <= 0:
        raise SweepError(f'step_pa must be > 0 Pa, got {step_pa}')
    _check_cycles_and_rest(cycles, rest_s)


def _check_duration(what: str, cycle_s: float, cycles: int, rest_s: float) -> None:
    total = cycles * cycle_s + (cycles - 1) * rest_s
    if total > MAX_DURATION_S:
        raise SweepError(f'the {what} lasts {total:.0f} s (more than {MAX_DURATION_S:.0f} s): '
                         'check its rate, period and cycles')


def _check_rate(name: str, rate_pa_s: float) -> None:
    if rate_pa_s > MAX_RATE_PA_S:
        raise SweepError(f'{name} {rate_pa_s:.0f} Pa/s is faster than {MAX_RATE_PA_S:.0f} Pa/s, '
                         'more than the valves can follow (a unit mistake?)')


def _is_default(value) -> bool:
    if isinstance(value, str):
        return value == ''
    if isinstance(value, (int, float)):
        return value == 0        # NaN is not 0: a NaN in an unused field is refused too
    return len(value) == 0


def _check_unused_fields(goal: SweepGoal, profile: str) -> None:
    uses = PROFILE_FIELDS[profile]
    for item in fields(SweepGoal):
        name = item.name
        if name in uses or not any(name in used for used in PROFILE_FIELDS.values()):
            continue
        if not _is_default(getattr(goal, name)):
            users = [p for p, used in PROFILE_FIELDS.items() if name in used]
            raise SweepError(
                f'{name} is set, but profile {profile!r} does not use it (it is for '
                f'{" and ".join(repr(p) for p in users)}; profile {profile!r} uses '
                f'{", ".join(uses)}, cycles and rest_s)')


def _turning_points(top: float, reversal_pressures_pa: Sequence[float],
                    max_steps: int) -> list[float]:
    """0, the reversals, the top (unless listed) and 0: checked to alternate up and down."""
    if len(reversal_pressures_pa) >= max_steps:
        raise SweepError(f'{len(reversal_pressures_pa)} reversal pressures make more than '
                         f'{max_steps} steps')
    reversals = [float(r) for r in reversal_pressures_pa]
    for i, value in enumerate(reversals):
        _check_finite(f'reversal_pressures_pa[{i}]', value)
        if not 0 <= value <= top:
            raise SweepError(
                f'reversal_pressures_pa[{i}] = {value:.0f} Pa must be within '
                f'0..{top:.0f} Pa (max_gauge_pressure_pa)')
    turning = [0.0, *reversals, *([] if top in reversals else [top]), 0.0]
    for i in range(1, len(turning) - 1):
        rising = turning[i] > turning[i - 1]
        falling_next = turning[i + 1] < turning[i]
        if rising != falling_next or turning[i] == turning[i - 1]:
            before, after = reversal_examples(top)
            raise SweepError(
                'reversal pressures must alternate up and down, starting up from 0 and ending '
                f'with a fall to 0 (turning points {[round(t) for t in turning]} Pa do not); '
                f'e.g. {before} before the top, or {after} after it')
    return turning


def reversal_examples(top: float) -> tuple[list[float], list[float]]:
    """Two valid reversal lists for this top (a minor loop before it, one after it), in the
    refusal's words: an example made for another top would be refused itself."""
    def at(share: float) -> int:
        return round(share * top)
    exact_top = round(top) if top == round(top) else top   # listed as the top, so exact
    return [at(0.6), at(0.3)], [exact_top, at(0.2), at(0.5)]


def _check_step_count(turning: Iterable[float], step_pa: float, cycles: int,
                      max_steps: int) -> None:
    """Count the staircase through `turning` by arithmetic (an iterator costs no memory)."""
    per_cycle = sum(staircase_length(a, b, step_pa) for a, b in itertools.pairwise(turning))
    count = 1 + per_cycle * cycles
    if count > max_steps:
        raise SweepError(f'the plan has {count} steps (more than {max_steps}): is step_pa '
                         f'{step_pa:g} Pa too small?')


def _stepped_plan(turning: list[float], step_pa: float, *, hold_s: float, cycles: int,
                  rest_s: float, max_steps: int, profile: str) -> SweepPlan:
    """The staircase through `turning` (0 ... 0), `cycles` times; counted before it is built."""
    _check_step_count(turning, step_pa, cycles, max_steps)
    one_cycle: list[float] = []
    for start, stop in itertools.pairwise(turning):
        one_cycle += staircase(start, stop, step_pa)
    return SweepPlan(tuple([0.0, *one_cycle * cycles]), float(hold_s), int(cycles),
                     float(rest_s), profile, tuple(turning))


# -- stepped profiles ----------------------------------------------------------------------


def plan_sweep(max_gauge_pressure_pa: float, step_pa: float, hold_s: float, cycles: int,
               reversal_pressures_pa: Sequence[float] = (), *, ceiling_pa: float,
               max_steps: int = MAX_STEPS, rest_s: float = 0.0) -> SweepPlan:
    """Check a staircase goal against the driver's ceiling and return its plan, or raise."""
    _check_stepped(max_gauge_pressure_pa, step_pa, hold_s, cycles, rest_s,
                   ceiling_pa=ceiling_pa)
    turning = _turning_points(float(max_gauge_pressure_pa), reversal_pressures_pa, max_steps)
    return _stepped_plan(turning, step_pa, hold_s=hold_s, cycles=cycles, rest_s=rest_s,
                         max_steps=max_steps, profile='staircase')


def forc_turning_points(top_pa: float, count: int, family: str = 'ascending') -> list[float]:
    """The turning points (0 ... 0) of a set of `count` first-order reversal curves.

    'ascending' is the standard FORC (Mayergoyz; Pike et al. 1999, "saturate, decrease to
    the reversal field, measure while increasing"), with the top pressure as saturation:
    up to the top, down the major decreasing branch to each reversal pressure
    p_k = top (N - k) / N (k = 1..N, the last at 0 Pa: the major loop), and back up to the
    top; then down to 0. Each curve starts on the major branch from a state the top has
    wiped clean, so curve k depends on p_k alone: that is what makes the set identify a
    Preisach-type memory. For pma_model these are the rising scanning curves (the rising
    play share of the 'identify' rule, Madelung's rising curves).
    'descending' is its mirror from rest: up the major increasing branch to p_k = top k / N
    and back down to 0 (the falling scanning curves and share). 'both' runs the ascending
    set, then the descending one: what `refit --memory-check` needs to tell every rule and
    both shares apart.
    """
    return list(_forc_turning(top_pa, count, family))


def _forc_turning(top_pa: float, count: int, family: str) -> Iterator[float]:
    yield 0.0
    if family in ('ascending', 'both'):
        yield top_pa
        for k in range(1, count + 1):
            yield top_pa * (count - k) / count
            yield top_pa
        yield 0.0
    if family in ('descending', 'both'):
        for k in range(1, count + 1):
            yield top_pa * k / count
            yield 0.0


def plan_forc(max_gauge_pressure_pa: float, step_pa: float, hold_s: float, cycles: int, *,
              forc_count: int, forc_family: str = '', ceiling_pa: float,
              max_steps: int = MAX_STEPS, rest_s: float = 0.0) -> SweepPlan:
    """Check a FORC goal and return its plan (staircases between the turning points)."""
    _check_stepped(max_gauge_pressure_pa, step_pa, hold_s, cycles, rest_s,
                   ceiling_pa=ceiling_pa)
    family = forc_family or 'ascending'
    if family not in FORC_FAMILIES:
        raise SweepError(f'forc_family {forc_family!r} is not one of '
                         f'{", ".join(FORC_FAMILIES)} (empty = ascending)')
    if forc_count < 1:
        raise SweepError(f'forc_count must be >= 1, got {forc_count}')
    if forc_count > max_steps:
        raise SweepError(f'forc_count {forc_count} makes more than {max_steps} steps')
    top = float(max_gauge_pressure_pa)
    _check_step_count(_forc_turning(top, forc_count, family), step_pa, cycles, max_steps)
    turning = forc_turning_points(top, forc_count, family)
    return _stepped_plan(turning, step_pa, hold_s=hold_s, cycles=cycles, rest_s=rest_s,
                         max_steps=max_steps, profile='forc')


# -- streamed profiles ---------------------------------------------------------------------


def _bound(max_gauge_pressure_pa: float, ceiling_pa: float) -> float:
    """The most a sine or csv profile may reach: the ceiling, or the goal's own bound."""
    if max_gauge_pressure_pa == 0:
        return ceiling_pa
    _check_top(max_gauge_pressure_pa, ceiling_pa)
    return max_gauge_pressure_pa


def plan_ramp(max_gauge_pressure_pa: float, ramp_rate_pa_s: float, hold_s: float,
              cycles: int, reversal_pressures_pa: Sequence[float] = (), *, ceiling_pa: float,
              max_steps: int = MAX_STEPS, rest_s: float = 0.0) -> StreamPlan:
    """The staircase's turning points joined by straight lines at `ramp_rate_pa_s`."""
    _check_top(max_gauge_pressure_pa, ceiling_pa)
    _check_finite('ramp_rate_pa_s', ramp_rate_pa_s)
    _check_hold(hold_s)
    if ramp_rate_pa_s <= 0:
        raise SweepError(f'ramp_rate_pa_s must be > 0 Pa/s, got {ramp_rate_pa_s}')
    _check_rate('ramp_rate_pa_s', ramp_rate_pa_s)
    _check_cycles_and_rest(cycles, rest_s)
    turning = _turning_points(float(max_gauge_pressure_pa), reversal_pressures_pa, max_steps)
    travel = sum(abs(b - a) for a, b in itertools.pairwise(turning))
    cycle_s = travel / ramp_rate_pa_s + hold_s * (len(turning) - 2)
    _check_duration('ramp', cycle_s, cycles, rest_s)
    times, pressures = [0.0], [0.0]
    for i, target in enumerate(turning[1:], start=1):
        times.append(times[-1] + abs(target - pressures[-1]) / ramp_rate_pa_s)
        pressures.append(target)
        if hold_s > 0 and i < len(turning) - 1:
            times.append(times[-1] + hold_s)
            pressures.append(target)
    return StreamPlan('ramp', int(cycles), float(rest_s), times[-1],
                      float(max_gauge_pressure_pa), tuple(times), tuple(pressures))


def plan_sine(amplitude_pa: float, offset_pa: float, frequency_hz: float, cycles: int, *,
              ceiling_pa: float, max_gauge_pressure_pa: float = 0.0,
              rest_s: float = 0.0) -> StreamPlan:
    """offset - amplitude cos(2 pi f t): `cycles` whole periods, from the trough to the trough."""
    for name, value in (('sine_amplitude_pa', amplitude_pa), ('sine_offset_pa', offset_pa),
                        ('sine_frequency_hz', frequency_hz)):
        _check_finite(name, value)
    bound = _bound(max_gauge_pressure_pa, ceiling_pa)
    if amplitude_pa <= 0:
        raise SweepError(f'sine_amplitude_pa must be > 0 Pa, got {amplitude_pa}')
    if offset_pa - amplitude_pa < 0:
        raise SweepError(f'the sine goes below 0 Pa gauge: sine_offset_pa {offset_pa:.0f} - '
                         f'sine_amplitude_pa {amplitude_pa:.0f} < 0')
    if offset_pa + amplitude_pa > bound:
        raise SweepError(f'the sine peaks at {offset_pa + amplitude_pa:.0f} Pa, above '
                         + (f'max_gauge_pressure_pa {bound:.0f} Pa' if max_gauge_pressure_pa
                            else f'the driver ceiling {bound:.0f} Pa (parameter '
                            'max_gauge_pressure_pa)'))
    if not 0 < frequency_hz <= MAX_SINE_FREQUENCY_HZ:
        raise SweepError(f'sine_frequency_hz must be within 0..{MAX_SINE_FREQUENCY_HZ:g} Hz '
                         f'(> 0; at least 10 setpoints per period at {STREAM_RATE_HZ:g} Hz), '
                         f'got {frequency_hz}')
    _check_rate('the sine\'s steepest slope (2 pi f amplitude)',
                2 * math.pi * frequency_hz * amplitude_pa)
    _check_cycles_and_rest(cycles, rest_s)
    _check_duration('sine', 1.0 / frequency_hz, cycles, rest_s)
    return StreamPlan('sine', int(cycles), float(rest_s), 1.0 / frequency_hz,
                      float(offset_pa + amplitude_pa),
                      sine=(float(amplitude_pa), float(offset_pa), float(frequency_hz)))


def plan_points(time_s: Sequence[float], pressure_pa: Sequence[float], cycles: int, *,
                ceiling_pa: float, max_gauge_pressure_pa: float = 0.0,
                rest_s: float = 0.0) -> StreamPlan:
    """Straight lines between (time, pressure) points; times count from the first point."""
    n = len(time_s)
    if n != len(pressure_pa):
        raise SweepError(f'profile_time_s has {n} points and profile_pressure_pa '
                         f'{len(pressure_pa)}: they must pair up')
    if n < 2:
        raise SweepError(f'a csv profile needs at least 2 points, got {n}')
    if n > MAX_PROFILE_POINTS:
        raise SweepError(f'the csv profile has {n} points (more than {MAX_PROFILE_POINTS})')
    bound = _bound(max_gauge_pressure_pa, ceiling_pa)
    times, pressures = [float(t) for t in time_s], [float(p) for p in pressure_pa]
    for i, (t, p) in enumerate(zip(times, pressures, strict=True)):
        _check_finite(f'profile_time_s[{i}]', t)
        _check_finite(f'profile_pressure_pa[{i}]', p)
        if not 0 <= p <= bound:
            raise SweepError(f'profile_pressure_pa[{i}] = {p:.0f} Pa must be within '
                             f'0..{bound:.0f} Pa ('
                             + ('max_gauge_pressure_pa)' if max_gauge_pressure_pa
                                else 'the driver ceiling, parameter max_gauge_pressure_pa)'))
    for i in range(1, n):
        dt = times[i] - times[i - 1]
        if not dt > 0:
            raise SweepError(f'profile_time_s must increase strictly: point {i} is at '
                             f'{times[i]:g} s after {times[i - 1]:g} s')
        _check_rate(f'the csv profile between points {i - 1} and {i}: its slope',
                    abs(pressures[i] - pressures[i - 1]) / dt)
    _check_cycles_and_rest(cycles, rest_s)
    cycle_s = times[-1] - times[0]
    _check_duration('csv profile', cycle_s, cycles, rest_s)
    return StreamPlan('csv', int(cycles), float(rest_s), cycle_s, max(pressures),
                      tuple(t - times[0] for t in times), tuple(pressures))


def read_profile_csv(path) -> tuple[list[float], list[float]]:
    """(time_s, gauge_pressure_pa) of a CSV with those columns (SI, a header row; other
    columns are ignored, so refit's sample log CSV replays as a profile). For the client:
    the points go into the goal, since the driver may run on another machine."""
    path = Path(path)
    try:
        with path.open(newline='', encoding='utf-8') as stream:
            rows = list(csv.reader(stream))
    except (OSError, UnicodeDecodeError) as error:
        raise SweepError(f'{path}: cannot read the profile: {error}') from None
    if not rows:
        raise SweepError(f'{path}: empty; a profile CSV has a header row time_s,'
                         'gauge_pressure_pa and one row per point')
    header = [name.strip() for name in rows[0]]
    try:
        columns = header.index('time_s'), header.index('gauge_pressure_pa')
    except ValueError:
        raise SweepError(f'{path}: the header {",".join(header)} lacks time_s and '
                         'gauge_pressure_pa (SI: seconds and pascals)') from None
    times, pressures = [], []
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        try:
            times.append(float(row[columns[0]]))
            pressures.append(float(row[columns[1]]))
        except (IndexError, ValueError):
            raise SweepError(f'{path}, line {line}: not two numbers in time_s and '
                             f'gauge_pressure_pa: {",".join(row)}') from None
    return times, pressures


# -- the goal ------------------------------------------------------------------------------


def plan_goal(goal: SweepGoal, *, ceiling_pa: float,
              max_steps: int = MAX_STEPS) -> SweepPlan | StreamPlan:
    """Check any Sweep goal against the driver's ceiling and return its plan, or raise."""
    profile = goal.profile_name
    if profile not in PROFILES:
        raise SweepError(f'profile {goal.profile!r} is not one of {", ".join(PROFILES)} '
                         '(empty = staircase)')
    _check_unused_fields(goal, profile)
    common = {'ceiling_pa': ceiling_pa, 'rest_s': goal.rest_s}
    if profile == 'staircase':
        return plan_sweep(goal.max_gauge_pressure_pa, goal.step_pa, goal.hold_s, goal.cycles,
                          goal.reversal_pressures_pa, max_steps=max_steps, **common)
    if profile == 'forc':
        return plan_forc(goal.max_gauge_pressure_pa, goal.step_pa, goal.hold_s, goal.cycles,
                         forc_count=goal.forc_count, forc_family=goal.forc_family,
                         max_steps=max_steps, **common)
    if profile == 'ramp':
        return plan_ramp(goal.max_gauge_pressure_pa, goal.ramp_rate_pa_s, goal.hold_s,
                         goal.cycles, goal.reversal_pressures_pa, max_steps=max_steps, **common)
    if profile == 'sine':
        return plan_sine(goal.sine_amplitude_pa, goal.sine_offset_pa, goal.sine_frequency_hz,
                         goal.cycles, max_gauge_pressure_pa=goal.max_gauge_pressure_pa,
                         **common)
    return plan_points(goal.profile_time_s, goal.profile_pressure_pa, goal.cycles,
                       max_gauge_pressure_pa=goal.max_gauge_pressure_pa, **common)
