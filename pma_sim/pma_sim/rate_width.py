"""Validation set: a muscle whose hysteresis widens with the pressure's rate of change.

The rubber's viscosity and the braid's velocity-dependent friction make a pneumatic muscle's
loop wider the faster it is cycled (beyond the `creep` family's lag, which only delays the
length: here the band itself grows). Play operators (the `wide` family's plays on a warped
pressure, families.PlayMuscle) whose half-widths scale with a filtered pressure rate:
r_j(t) = r_j (1 + WIDTH_GAIN q / (q + HALF_RATE_PA_S)), q the |dp/dt| low-passed with
RATE_TIME_CONSTANT_S. At 250 kPa/s, the paths' fastest ramp, the band is 1.44x its static
width; at 10 kPa/s 1.04x; never over 1.8x. When the pressure holds, q decays and the band
narrows back: a play left outside it is pulled in, so the length relaxes onto the static
loop within a second or so (bounded, like a creep, but only after a fast move).

Table 1's points are the ends of holds, where the width has relaxed: the static plays are
fitted to it as the `wide` family's are (fit_families.fit_plays), and its Table 1 fit is
measured on the paper's protocol (a 1 s ramp to each level, a 10 s hold, the end of the
hold; `table1_loop_m`). The three rate constants are a design choice, not fitted, and were
not chosen on the model's results (pma_sim.splits: validation set). Rate-dependent: no
oracle. ROS-free.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import numpy as np

from pma_sim import families, fit_families
from pma_sim.muscle import TABLE1_PRESSURE_PA

WIDTH_GAIN = 0.8                 # the band grows by up to 80 %
HALF_RATE_PA_S = 200_000.0       # ... half of that at 200 kPa/s
RATE_TIME_CONSTANT_S = 0.3       # the pressure rate's low-pass


@dataclass(frozen=True)
class RateWidthParams:
    plays: families.PlayParams
    width_gain: float = WIDTH_GAIN
    half_rate_pa_s: float = HALF_RATE_PA_S
    rate_time_constant_s: float = RATE_TIME_CONSTANT_S

    def width_scale(self, rate_pa_s: float) -> float:
        """The bands' half-widths at a filtered pressure rate, as a multiple of the static."""
        rate = abs(rate_pa_s)
        return 1.0 + self.width_gain * rate / (rate + self.half_rate_pa_s)


class RateWidthMuscle(families.PlayMuscle):
    """A `families.Muscle`: plays whose bands widen with the filtered pressure rate."""

    def __init__(self, params: RateWidthParams):
        self.rate_params = params
        super().__init__(params.plays)

    def reset(self) -> None:
        super().reset()
        self._pressure = 0.0
        self._time_s: float | None = None
        self.rate_pa_s = 0.0      # |dp/dt| low-passed
        self._scale = 1.0

    @property
    def width_scale(self) -> float:
        return self._scale

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        pressure = max(0.0, float(pressure_pa))
        if self._time_s is not None and t_s > self._time_s:
            dt = t_s - self._time_s
            raw = abs(pressure - self._pressure) / dt
            share = 1.0 - math.exp(-dt / self.rate_params.rate_time_constant_s)
            self.rate_pa_s += share * (raw - self.rate_pa_s)
        if self._time_s is None or t_s > self._time_s:
            self._time_s = t_s
        self._pressure = pressure
        self._scale = self.rate_params.width_scale(self.rate_pa_s)
        return super().update(pressure, t_s)

    def _band(self, v: float) -> tuple[np.ndarray, np.ndarray]:
        radii = self._radii * self._scale
        return v - radii, v + radii


@functools.lru_cache(maxsize=2)
def fit(starts: int = 6, seed: int = 0) -> RateWidthParams:
    """The static plays fitted to Table 1 (the ends of holds, where the width has relaxed)."""
    return RateWidthParams(fit_families.fit_plays(fit_families.classic_plays, starts, seed))


def table1_loop_m(params: RateWidthParams, ramp_s: float = 1.0,
                  hold_s: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(increasing, decreasing) lengths on the paper's protocol: a ramp of `ramp_s` to each of
    Table 1's levels, up then down, and the length at the end of a `hold_s` hold; the second
    of two cycles (sampled at 50 Hz)."""
    muscle = RateWidthMuscle(params)
    t, pressure, lengths = 0.0, 0.0, []
    levels = np.concatenate([TABLE1_PRESSURE_PA, TABLE1_PRESSURE_PA[::-1]])
    for cycle, level in itertools.product(range(2), levels):
        for fraction in np.linspace(0.02, 1.0, 50):   # the ramp
            muscle.update(pressure + fraction * (level - pressure), t + fraction * ramp_s)
        t += ramp_s
        pressure = float(level)
        for _ in range(int(hold_s * 50)):   # the hold
            t += 0.02
            muscle.update(pressure, t)
        if cycle == 1:
            lengths.append(muscle.length_m)
    n = TABLE1_PRESSURE_PA.size
    return np.array(lengths[:n]), np.array(lengths[n:][::-1])


def loop_errors_m(params: RateWidthParams) -> np.ndarray:
    """Its loop on the paper's protocol minus Table 1 (22 values)."""
    return np.concatenate(table1_loop_m(params)) - fit_families.TARGET


def cycle_width_m(params: RateWidthParams, rate_pa_s: float, top_pa: float = 400e3,
                  at_pa: float = 200e3, rate_hz: float = 50.0) -> float:
    """The loop's width (|rising - falling length|) at `at_pa` on
    a 0 -> top -> 0 triangle at `rate_pa_s`, the second of two cycles."""
    muscle = RateWidthMuscle(params)
    period_s = 2.0 * top_pa / rate_pa_s
    times = np.arange(0.0, 2.0 * period_s, 1.0 / rate_hz)
    pressures = top_pa - np.abs(top_pa - (rate_pa_s * times) % (2.0 * top_pa))
    lengths = np.array([muscle.update(p, t) for p, t in zip(pressures, times, strict=True)])
    second = times >= period_s
    rising = second & (times - period_s < period_s / 2)
    falling = second & ~rising
    up = np.interp(at_pa, pressures[rising], lengths[rising])
    down = np.interp(at_pa, pressures[falling][::-1], lengths[falling][::-1])
    return float(abs(up - down))
