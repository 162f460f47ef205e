"""Validation set: a muscle whose loops do not close, ratcheting longer by a little every cycle.

Rubber and braid take a set: every deflation leaves the muscle a little longer than the
inflation found it, less and less as the set approaches its limit (the Mullins-like
softening and the braid's slack settling of a new McKibben muscle). Here a play muscle (the
`wide` family's plays on a warped pressure, families.PlayMuscle) carries a slow ratchet
state r added to its length: falling pressure lengthens it, rising pressure leaves it,
dr = (RATCHET_LIMIT_M - r) |dp| / RATCHET_SCALE_PA while the pressure falls. So each cycle
leaves a permanent offset proportional to its fall, and the offsets accumulate toward
RATCHET_LIMIT_M (2 mm, under the HC-SR04's 3 mm resolution; about 0.16 mm for Table 1's
0 -> 500 -> 0 kPa cycle, on a fresh muscle): the drift is monotonic and bounded, and no loop
closes until the ratchet has saturated. Rate-independent, no return-point memory.

Fitted to Table 1 as the `wide` family is (fit_families.fit_plays: warp and play weights),
on a fresh muscle's first cycle: the plays make Table 1 less the ratchet that cycle adds on
its falling branch. The two constants are a design choice (a small ratchet), not fitted,
and were not chosen on the model's results (pma_sim.splits: validation set). ROS-free.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from pma_sim import families, fit_families
from pma_sim.muscle import TABLE1_PRESSURE_PA

RATCHET_LIMIT_M = 0.002          # the set the muscle takes, at most
RATCHET_SCALE_PA = 6_000_000.0   # falling pressure that takes 63 % of what is left of it


@dataclass(frozen=True)
class RatchetParams:
    plays: families.PlayParams
    limit_m: float = RATCHET_LIMIT_M
    scale_pa: float = RATCHET_SCALE_PA

    def ratchet_after_fall_m(self, ratchet_m, fall_pa):
        """The ratchet after a fall of `fall_pa` from `ratchet_m` (exact for dr/dfall)."""
        return self.limit_m - (self.limit_m - ratchet_m) * np.exp(-np.asarray(fall_pa)
                                                                  / self.scale_pa)


class RatchetMuscle:
    """A `families.Muscle`: the plays' length plus the ratchet (see the module docstring)."""

    def __init__(self, params: RatchetParams):
        self.params = params
        self._plays = families.PlayMuscle(params.plays)
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return self.params.plays.rest_length_m

    @property
    def ratchet_m(self) -> float:
        return self._ratchet_m

    def reset(self) -> None:
        self._plays.reset()
        self._pressure = 0.0
        self._ratchet_m = 0.0
        self.length_m = self.rest_length_m

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        pressure = max(0.0, float(pressure_pa))
        if pressure < self._pressure:
            self._ratchet_m = float(self.params.ratchet_after_fall_m(
                self._ratchet_m, self._pressure - pressure))
        self._pressure = pressure
        self.length_m = self._plays.update(pressure) + self._ratchet_m
        return self.length_m


def major_loop_m(params: RatchetParams) -> tuple[np.ndarray, np.ndarray]:
    """(increasing, decreasing) lengths of a fresh muscle's 0 -> 500 -> 0 kPa cycle at Table
    1's pressures."""
    up, down = families.play_major_loop_m(params.plays, TABLE1_PRESSURE_PA)
    return up, down + _falling_ratchet_m(params.limit_m, params.scale_pa)


def _falling_ratchet_m(limit_m: float, scale_pa: float) -> np.ndarray:
    top = float(np.max(TABLE1_PRESSURE_PA))
    return limit_m * (1.0 - np.exp(-(top - TABLE1_PRESSURE_PA) / scale_pa))


def loop_errors_m(params: RatchetParams) -> np.ndarray:
    """A fresh muscle's first cycle minus Table 1 (22 values)."""
    return np.concatenate(major_loop_m(params)) - fit_families.TARGET


@functools.lru_cache(maxsize=2)
def fit(starts: int = 6, seed: int = 0) -> RatchetParams:
    """The plays fitted so that plays plus the first cycle's ratchet make Table 1."""
    n = TABLE1_PRESSURE_PA.size
    target = fit_families.TARGET.copy()
    target[n:] -= _falling_ratchet_m(RATCHET_LIMIT_M, RATCHET_SCALE_PA)
    plays = fit_families.fit_plays(fit_families.classic_plays, starts, seed, target)
    return RatchetParams(plays)


def cycle_offsets_m(params: RatchetParams, top_pa: float, cycles: int) -> np.ndarray:
    """The length at 0 Pa after each of `cycles` identical 0 -> top -> 0 cycles, less the rest
    length (a fresh muscle, stepped by 5 kPa)."""
    muscle = RatchetMuscle(params)
    ramp = np.linspace(0.0, top_pa, max(2, math.ceil(top_pa / 5e3)) + 1)
    offsets = []
    for _ in range(cycles):
        for pressure in (*ramp, *ramp[::-1]):
            muscle.update(pressure)
        offsets.append(muscle.length_m - muscle.rest_length_m)
    return np.array(offsets)
