"""Tuning set: generalized Prandtl-Ishlinskii, asymmetric, with return-point memory.

A model the literature fits to pneumatic muscles whose length/pressure loops are asymmetric
(the generalized play operator of Al Janaideh, Rakheja and Su, IEEE/ASME Trans. Mechatronics
16(4), 2011; on a PAM's length, with two operators for the ascending and descending branches:
Liu, Zang, Lin, Liu and Zhao, Strojniski vestnik 63(1), 2017): plays whose band is bounded by
two different envelopes, one for rising input and one for falling, so that rising and falling
scanning curves differ, while every play keeps wiping-out, and so the muscle keeps
return-point memory. The `asymmetric` family of the
simulator is asymmetric too but has no return-point memory (a Duhem muscle); this one separates
the two: whatever the model misses here is asymmetry, not loops that do not close.

The input is warped as the `wide` family's (families.PlayParams.warp: dead zone, then a Hill
curve, 0..1 up to SPAN_PA). Play j with half-width r_j has output y_j within
[rising(v) - r_j, falling(v) + r_j], with rising(v) = v and falling(v) = v + bulge v (1 - v)
for every play but the reversible one (width 0): the falling envelope lies above the rising
one (bulge >= 0), so the band never closes, and falling curves are steeper than rising ones
at low pressure and flatter at high. length = rest - sum_j w_j (y_j - r_j); relaxed at 0 Pa,
y_j = r_j.

The simulator's play muscle runs it (families.PlayMuscle, with this band) and
fit_families.fit_plays fits it to Table 1, as it fits the `wide` family (about 3 s a bulge).
ROS-free.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pma_sim import families, fit_families
from pma_sim.muscle import TABLE1_PRESSURE_PA

DEFAULT_BULGE = 1.0  # the falling envelope up to 0.25 of the warped range above the rising one


@dataclass(frozen=True)
class GeneralizedPlayParams(families.PlayParams):
    bulge: float = 0.0

    def envelopes(self, v) -> tuple[np.ndarray, np.ndarray]:
        """(rising, falling) envelopes at warped input v, one per play: the play of width 0
        is reversible, so it has one."""
        rising, _ = super().envelopes(v)
        bulge = np.where(np.array(self.radii) > 0.0, self.bulge, 0.0)
        return rising, rising + bulge * rising * (1.0 - rising)


class GeneralizedPlayMuscle(families.PlayMuscle):
    """A `families.Muscle`: rate-independent, asymmetric, with return-point memory."""

    def _band(self, v: float) -> tuple[np.ndarray, np.ndarray]:
        rising, falling = self.params.envelopes(v)
        return rising - self._radii, falling + self._radii


def loop_errors_m(params: GeneralizedPlayParams) -> np.ndarray:
    """The model's major loop minus Table 1 (22 values)."""
    return np.concatenate(families.play_major_loop_m(params, TABLE1_PRESSURE_PA)) - \
        fit_families.TARGET


@functools.lru_cache(maxsize=8)
def fit(bulge: float = DEFAULT_BULGE, starts: int = 6, seed: int = 0) -> GeneralizedPlayParams:
    """Warp (dead zone, K, n) and play weights fitted to Table 1 for a given bulge."""
    def params_for(rest_length_m, warp, radii, weights_m):
        classic = fit_families.classic_plays(rest_length_m, warp, radii, weights_m)
        return GeneralizedPlayParams(**vars(classic), bulge=float(bulge))

    return fit_families.fit_plays(params_for, starts, seed)
