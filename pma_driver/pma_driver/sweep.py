"""The pressure staircase of a Sweep goal (pma_interfaces/action/Sweep), checked and planned.

Plain Python, no ROS: the driver's action server runs the plan, tests check it here.
One cycle goes 0 -> max in steps of `step_pa` and back to 0, holding `hold_s` at each
step. Reversal pressures are turning points visited in turn, for minor loops: `[300e3,
150e3]` goes up to 300 kPa, down to 150 kPa, then on up to max and back down. Listing max
itself puts the loops after it on the falling branch: `[500e3, 100e3, 250e3]` goes up to
500 kPa, down to 100 kPa, up to 250 kPa, then down to 0. Steps lie on the grid of
multiples of `step_pa`, plus the turning points themselves.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

MAX_STEPS = 10_000  # a plan longer than this is a typo (step_pa of 1 Pa), not an experiment


class SweepError(ValueError):
    """A goal that cannot be run; the message says which field and why."""


@dataclass(frozen=True)
class SweepPlan:
    setpoints_pa: tuple[float, ...]   # every step, in order, starting with 0 Pa
    hold_s: float
    cycles: int

    @property
    def step_count(self) -> int:
        return len(self.setpoints_pa)

    @property
    def hold_time_s(self) -> float:
        """Total time spent holding (the run takes longer: each step must be reached first)."""
        return self.step_count * self.hold_s

    def progress(self, step_index: int, hold_fraction: float = 0.0) -> float:
        """Fraction done (0..1) at `step_index` with this much of its hold elapsed."""
        fraction = (step_index + min(1.0, max(0.0, hold_fraction))) / self.step_count
        return min(1.0, max(0.0, fraction))


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


def _check_finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise SweepError(f'{name} must be a finite number, got {value}')


def plan_sweep(max_gauge_pressure_pa: float, step_pa: float, hold_s: float, cycles: int,
               reversal_pressures_pa: Sequence[float] = (), *,
               ceiling_pa: float, max_steps: int = MAX_STEPS) -> SweepPlan:
    """Check a Sweep goal against the driver's ceiling and return its plan, or raise SweepError."""
    _check_finite('max_gauge_pressure_pa', max_gauge_pressure_pa)
    _check_finite('step_pa', step_pa)
    _check_finite('hold_s', hold_s)
    if max_gauge_pressure_pa <= 0:
        raise SweepError(f'max_gauge_pressure_pa must be > 0 Pa, got {max_gauge_pressure_pa}')
    if max_gauge_pressure_pa > ceiling_pa:
        raise SweepError(
            f'max_gauge_pressure_pa {max_gauge_pressure_pa:.0f} Pa is above the driver ceiling '
            f'{ceiling_pa:.0f} Pa (parameter max_gauge_pressure_pa)')
    if step_pa <= 0:
        raise SweepError(f'step_pa must be > 0 Pa, got {step_pa}')
    if hold_s < 0:
        raise SweepError(f'hold_s must be >= 0 s, got {hold_s}')
    if cycles < 1:
        raise SweepError(f'cycles must be >= 1, got {cycles}')
    if len(reversal_pressures_pa) >= max_steps:
        raise SweepError(f'{len(reversal_pressures_pa)} reversal pressures make more than '
                         f'{max_steps} steps')
    reversals = [float(r) for r in reversal_pressures_pa]
    for i, value in enumerate(reversals):
        _check_finite(f'reversal_pressures_pa[{i}]', value)
        if not 0 <= value <= max_gauge_pressure_pa:
            raise SweepError(
                f'reversal_pressures_pa[{i}] = {value:.0f} Pa must be within '
                f'0..{max_gauge_pressure_pa:.0f} Pa (max_gauge_pressure_pa)')
    top = float(max_gauge_pressure_pa)
    turning = [0.0, *reversals, *([] if top in reversals else [top]), 0.0]
    for i in range(1, len(turning) - 1):
        rising = turning[i] > turning[i - 1]
        falling_next = turning[i + 1] < turning[i]
        if rising != falling_next or turning[i] == turning[i - 1]:
            raise SweepError(
                'reversal pressures must alternate up and down, starting up from 0 and ending '
                f'with a fall to 0 (turning points {[round(t) for t in turning]} Pa do not); '
                'e.g. [300000, 150000] before the top, or [500000, 100000, 250000] after it')
    # Counted by arithmetic before anything is built: a tiny step_pa must cost nothing.
    per_cycle = sum(staircase_length(a, b, step_pa) for a, b in itertools.pairwise(turning))
    count = 1 + per_cycle * cycles
    if count > max_steps:
        raise SweepError(f'the plan has {count} steps (more than {max_steps}): is step_pa '
                         f'{step_pa:g} Pa too small?')
    one_cycle: list[float] = []
    for start, stop in itertools.pairwise(turning):
        one_cycle += staircase(start, stop, step_pa)
    return SweepPlan(tuple([0.0, *one_cycle * cycles]), float(hold_s), int(cycles))
