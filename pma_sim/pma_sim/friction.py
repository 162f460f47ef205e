"""Tuning set: braid friction that grows with the pressure, and a late, sharp onset.

In a McKibben muscle the braid's fibres rub on the tube and on each other with a contact
force that grows with the pressure, so the friction each fibre must overcome is a fixed
share of the pressure (Tondu and Lopez, IEEE Control Systems 20(2), 2000). Fibre j sticks
while the warped pressure v stays within a band proportional to v around its state y_j:
y_j = clip(y_j, v (1 - k_j), v (1 + k_j)), zero at 0 Pa (every loop closes there).
length = rest - sum_j w_j y_j. Like any play it wipes out, so the muscle keeps return-point
memory; unlike the `wide` family its loops narrow toward 0 Pa.

It is a generalized play (pma_sim.generalized_play) with half-width k_j and envelopes
v (1 - k_j) + 2 k_j (rising) and v (1 + k_j) (falling): shifted by k_j, so that the relaxed
state is y_j = k_j as families.PlayParams has it. So the simulator's play muscle runs it
and fit_families.fit_plays fits it to Table 1 (warp: dead zone, K, n; weights by
non-negative least squares), its bands spread over 0..widest. With bands up to 0.9 (the
default) it stays at rest to about 70 kPa and then contracts at once, between Table 1's
points at 50 and 100 kPa; the simulator's families leave their dead zone at about 50 kPa.
ROS-free.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pma_sim import families, fit_families
from pma_sim.generalized_play import GeneralizedPlayMuscle
from pma_sim.muscle import TABLE1_PRESSURE_PA

DEFAULT_WIDEST_BAND = 0.9   # k of the widest fibre: its band is v (1 -/+ 0.9)


@dataclass(frozen=True)
class FrictionParams(families.PlayParams):
    """PlayParams whose radii are the fibres' bands k_j (shares of the warped pressure)."""

    def envelopes(self, v) -> tuple[np.ndarray, np.ndarray]:
        v = np.asarray(v, dtype=float)[..., None]
        bands = np.array(self.radii)
        return v * (1.0 - bands) + 2.0 * bands, v * (1.0 + bands)


class FrictionMuscle(GeneralizedPlayMuscle):
    """A `families.Muscle`: rate-independent, with return-point memory."""


def loop_errors_m(params: FrictionParams) -> np.ndarray:
    """The muscle's major loop minus Table 1 (22 values)."""
    return np.concatenate(families.play_major_loop_m(params, TABLE1_PRESSURE_PA)) - \
        fit_families.TARGET


@functools.lru_cache(maxsize=4)
def fit(widest_band: float = DEFAULT_WIDEST_BAND, starts: int = 6,
        seed: int = 0) -> FrictionParams:
    """Warp and fibre weights fitted to Table 1, bands evenly spread over 0..widest_band."""
    def params_for(rest_length_m, warp, radii, weights_m):
        classic = fit_families.classic_plays(rest_length_m, warp, radii, weights_m)
        bands = tuple(float(r) * widest_band / fit_families.MAX_RADIUS for r in radii)
        return FrictionParams(**{**vars(classic), 'radii': bands})

    return fit_families.fit_plays(params_for, starts, seed)
