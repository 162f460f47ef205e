"""A held-out muscle: generalized Prandtl-Ishlinskii, asymmetric, with return-point memory.

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

`fit(bulge)` fits the warp and the weights to Table 1 by variable projection, as
fit_families.fit_wide does for the `wide` family (about 20 s). ROS-free.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from pma_driver.sim import families
from pma_driver.sim.muscle import (
    TABLE1_LENGTH_DECREASING_M,
    TABLE1_LENGTH_INCREASING_M,
    TABLE1_PRESSURE_PA,
)

PLAYS = 20
MAX_RADIUS = 0.45
SMOOTHING = 0.03     # the second-difference penalty on the weights, as fit_families uses
DEFAULT_BULGE = 1.0  # the falling envelope up to 0.25 of the warped range above the rising one
TARGET_M = np.concatenate([TABLE1_LENGTH_INCREASING_M, TABLE1_LENGTH_DECREASING_M])


@dataclass(frozen=True)
class GeneralizedPlayParams:
    rest_length_m: float
    dead_zone_pa: float
    warp_k_pa: float
    warp_n: float
    bulge: float
    radii: tuple[float, ...]
    weights_m: tuple[float, ...]

    def warp(self, pressure_pa):
        return families.PlayParams(self.rest_length_m, self.dead_zone_pa, self.warp_k_pa,
                                   self.warp_n, (), ()).warp(pressure_pa)

    def envelopes(self, v):
        """(rising, falling) envelopes at warped input v, one row per play (the band's two
        edges before r): the play of width 0 is reversible, so it has one."""
        v = np.asarray(v, dtype=float)[..., None]
        bulge = np.where(np.array(self.radii) > 0.0, self.bulge, 0.0)
        return np.broadcast_to(v, v.shape[:-1] + bulge.shape), v + bulge * v * (1.0 - v)


class GeneralizedPlayMuscle:
    """A `families.Muscle`: rate-independent, asymmetric, with return-point memory."""

    def __init__(self, params: GeneralizedPlayParams):
        self.params = params
        self._radii = np.array(params.radii, dtype=float)
        self._weights = np.array(params.weights_m, dtype=float)
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return self.params.rest_length_m

    def reset(self) -> None:
        self._outputs = self._radii.copy()
        self.length_m = self.params.rest_length_m

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        rising, falling = self.params.envelopes(float(self.params.warp(float(pressure_pa))))
        np.clip(self._outputs, rising - self._radii, falling + self._radii, out=self._outputs)
        self.length_m = self.params.rest_length_m - float(
            self._weights @ (self._outputs - self._radii))
        return self.length_m


def major_loop_m(params: GeneralizedPlayParams, pressures_pa) -> tuple[np.ndarray, np.ndarray]:
    """(increasing, decreasing) lengths of the 0 -> max(pressures) -> 0 loop from rest."""
    rising, falling = params.envelopes(params.warp(pressures_pa))
    radii, weights = np.array(params.radii), np.array(params.weights_m)
    top = np.maximum(radii, rising.max(axis=0) - radii)
    up = np.maximum(radii[None, :], rising - radii[None, :])
    down = np.minimum(top[None, :], falling + radii[None, :])
    return (params.rest_length_m - (up - radii) @ weights,
            params.rest_length_m - (down - radii) @ weights)


def loop_errors_m(params: GeneralizedPlayParams) -> np.ndarray:
    """The model's major loop minus Table 1 (22 values)."""
    return np.concatenate(major_loop_m(params, TABLE1_PRESSURE_PA)) - TARGET_M


@functools.lru_cache(maxsize=8)
def fit(bulge: float = DEFAULT_BULGE, starts: int = 6, seed: int = 0) -> GeneralizedPlayParams:
    """Warp (dead zone, K, n) and play weights fitted to Table 1 for a given bulge."""
    from scipy.optimize import least_squares, nnls

    rest = float(TABLE1_LENGTH_INCREASING_M[0])
    radii = tuple(float(r) for r in np.linspace(0.0, MAX_RADIUS, PLAYS))
    penalty = np.sqrt(SMOOTHING) * np.diff(np.eye(PLAYS), 2, axis=0)
    scale = np.array([1e5, 1e5, 1.0])

    def params(warp, weights):
        return GeneralizedPlayParams(rest, float(warp[0]), float(warp[1]), float(warp[2]),
                                     float(bulge), radii, tuple(float(w) for w in weights))

    def weights_for(warp):
        columns = [rest - np.concatenate(major_loop_m(params(warp, np.eye(PLAYS)[j]),
                                                      TABLE1_PRESSURE_PA))
                   for j in range(PLAYS)]
        design = np.array(columns).T                     # length lost per unit weight
        weights, _ = nnls(np.vstack([design, penalty]),
                          np.concatenate([rest - TARGET_M, np.zeros(PLAYS - 2)]))
        return weights, rest - design @ weights - TARGET_M

    rng = np.random.default_rng(seed)
    best = None
    for k in range(starts):
        x0 = np.array([0.5, 1.5, 1.5]) if k == 0 else rng.uniform([0.0, 0.5, 0.8],
                                                                 [0.8, 3.0, 4.0])
        result = least_squares(lambda z: weights_for(z * scale)[1], x0,
                               bounds=([0.0, 0.2, 0.5], [1.0, 6.0, 6.0]))
        if best is None or result.cost < best.cost:
            best = result
    warp = best.x * scale
    return params(warp, weights_for(warp)[0])
