"""A hysteretic McKibben muscle for the simulated rig: a Preisach operator model.

Deliberately a different family from the models `pma_model` fits (sigmoid, Hill,
Madelung branches): a simulator that shares the fitted model's structure would
flatter it. Preisach gives minor loops, return-point memory and wiping-out from
first principles (Mayergoyz), and with a smooth density it reproduces the
paper's major loop (Table 1) within the sensors' accuracy.

Structure (every pressure is gauge, in Pa; lengths in m):

* A dead zone: below `dead_zone_pa` the braid is slack and nothing moves, so
  the operators see `p_eff = clip(p - dead_zone_pa, 0, span_pa)`.
* A hysteretic part: relays with up/down thresholds alpha >= beta >= 0 and a
  Gaussian density in (centre, half-width) = ((alpha + beta)/2, (alpha - beta)/2).
  Its output is evaluated exactly through the Everett function and a stack of
  turning points (no relay grid to step, so it is cheap and has no staircase).
* A reversible part: a cumulative Gaussian of `p_eff` (the anhysteretic backbone).

length = rest_length - stroke_hyst * hysteretic - stroke_rev * reversible.

`fit_major_loop` identified the constants in `TABLE1_FIT` from the paper's Table 1
(`python -m pma_sim.muscle` repeats the fit and prints them).
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import astuple, dataclass, fields

import numpy as np

# Paper Table 1 (Al-Qurnawi & Al-Ibadi 2026), converted to SI: gauge pressure [Pa],
# length on the increasing and the decreasing branch [m]. The fit target only.
TABLE1_PRESSURE_PA = np.arange(0.0, 500_001.0, 50_000.0)
TABLE1_LENGTH_INCREASING_M = np.array([
    30.06, 30.06333333, 29.14, 27.94333333, 26.74, 26.00666667, 25.47, 25.32333333, 24.82,
    24.4, 24.2]) / 100.0
TABLE1_LENGTH_DECREASING_M = np.array([
    30.06, 30.05666667, 28.54666667, 27.46333333, 26.38, 25.64333333, 25.22666667, 25.08333333,
    24.59333333, 24.39, 24.2]) / 100.0

SPAN_PA = 700_000.0        # operator domain: above the 600 kPa supply, so never clipped
EVERETT_STEP_PA = 2_000.0  # Everett table resolution (bilinear interpolation between nodes)


@dataclass(frozen=True)
class MuscleParams:
    rest_length_m: float
    stroke_hyst_m: float      # length lost when every relay is on
    centre_pa: float          # density: mean relay centre (alpha + beta) / 2
    centre_sd_pa: float
    half_width_pa: float      # density: mean relay half-width (alpha - beta) / 2
    half_width_sd_pa: float
    stroke_rev_m: float       # length lost by the reversible part at full activation
    rev_centre_pa: float
    rev_sd_pa: float
    dead_zone_pa: float


# Fitted to Table 1 by fit_major_loop (`python -m pma_sim.muscle`): RMSE 0.067 cm over
# the 22 points. The narrow reversible term near 370 kPa reproduces the measured plateau
# at 300-350 kPa followed by the drop to 400 kPa.
TABLE1_FIT = MuscleParams(
    rest_length_m=0.30059903, stroke_hyst_m=0.05132607, centre_pa=9456.627,
    centre_sd_pa=142149.76, half_width_pa=0.0, half_width_sd_pa=14118.860,
    stroke_rev_m=0.00729836, rev_centre_pa=365698.39, rev_sd_pa=38003.917,
    dead_zone_pa=48628.685)


def everett_table(params: MuscleParams, step_pa: float = EVERETT_STEP_PA,
                  span_pa: float = SPAN_PA) -> np.ndarray:
    """E[i, j]: relay mass with both thresholds inside [j*step, i*step] (zero for j > i).

    Integrates the density cell by cell (midpoint rule), normalised so that the whole
    triangle 0 <= beta <= alpha <= span has mass 1.
    """
    n = round(span_pa / step_pa)
    mid = (np.arange(n) + 0.5) * step_pa
    alpha, beta = np.meshgrid(mid, mid, indexing='ij')
    centre = 0.5 * (alpha + beta)
    half_width = 0.5 * (alpha - beta)
    density = np.exp(-0.5 * ((centre - params.centre_pa) / params.centre_sd_pa) ** 2
                     - 0.5 * ((half_width - params.half_width_pa) / params.half_width_sd_pa) ** 2)
    weight = np.tril(np.ones((n, n)), -1) + 0.5 * np.eye(n)  # diagonal cells are half inside
    mass = density * weight
    mass /= mass.sum()
    # E[i, j] = sum over alpha-cells < i and beta-cells >= j.
    table = np.zeros((n + 1, n + 1))
    table[1:, :n] = np.cumsum(mass, axis=0)[:, ::-1].cumsum(axis=1)[:, ::-1]
    return np.tril(table)


def reversible_fraction(p_eff_pa: np.ndarray, params: MuscleParams) -> np.ndarray:
    """Anhysteretic activation, 0 at p_eff = 0 (vectorised twin of PreisachMuscle._length)."""
    scale = params.rev_sd_pa * math.sqrt(2.0)
    erf = np.vectorize(math.erf)
    return 0.5 * (erf((np.asarray(p_eff_pa, dtype=float) - params.rev_centre_pa) / scale)
                  - math.erf(-params.rev_centre_pa / scale))


def effective_pressure(pressure_pa, params: MuscleParams):
    return np.clip(np.asarray(pressure_pa, dtype=float) - params.dead_zone_pa, 0.0, SPAN_PA)


class PreisachMuscle:
    """Length of the muscle as pressure moves; call `update(p)` for each new pressure.

    Rate-independent: only the sequence of pressures matters, not the time step.
    The turning-point stack starts at the relaxed state (all relays off, p = 0).
    """

    def __init__(self, params: MuscleParams = TABLE1_FIT, step_pa: float = EVERETT_STEP_PA):
        self.params = params
        self._step = step_pa
        self._table = everett_table(params, step_pa).tolist()  # lists: fast scalar lookups
        self._last_index = len(self._table) - 1
        self._rev_scale = params.rev_sd_pa * math.sqrt(2.0)
        self._rev_at_zero = 0.5 * math.erf(-params.rev_centre_pa / self._rev_scale)
        self.reset()

    def __deepcopy__(self, memo) -> PreisachMuscle:
        # The state is the turning points and a few floats; the Everett table is read-only
        # and shared. Copying it made a snapshot of the muscle (the return-point oracle of
        # tests/support takes one at every reversal) cost 5.6 s a three-minute path.
        clone = copy.copy(self)
        clone._turns = list(self._turns)
        return clone

    def reset(self) -> None:
        """Back to the relaxed state (as after a long rest at 0 Pa)."""
        self._turns = [0.0]   # alternating extrema of p_eff, oldest first; [0] = permanent anchor
        self._input = 0.0
        self._prefix = 0.0    # hysteretic output of the completed segments
        self.length_m = self._length(0.0, 0.0)

    def _everett(self, high: float, low: float) -> float:
        """Bilinear interpolation of the Everett table at (alpha=high, beta=low)."""
        x = min(high / self._step, self._last_index)
        y = min(low / self._step, self._last_index)
        i = min(int(x), self._last_index - 1)
        j = min(int(y), self._last_index - 1)
        fx, fy = x - i, y - j
        t = self._table
        return ((t[i][j] * (1 - fx) + t[i + 1][j] * fx) * (1 - fy)
                + (t[i][j + 1] * (1 - fx) + t[i + 1][j + 1] * fx) * fy)

    def _segment(self, start: float, end: float) -> float:
        """Change of hysteretic output along a monotone segment from `start` to `end`."""
        if end >= start:
            return self._everett(end, start)
        return -self._everett(start, end)

    def _recompute_prefix(self) -> None:
        turns = self._turns
        self._prefix = sum(self._segment(a, b) for a, b in itertools.pairwise(turns))

    def _length(self, hysteretic: float, p_eff: float) -> float:
        p = self.params
        return (p.rest_length_m - p.stroke_hyst_m * hysteretic
                - p.stroke_rev_m * (0.5 * math.erf((p_eff - p.rev_centre_pa) / self._rev_scale)
                                    - self._rev_at_zero))

    def hysteretic_fraction(self) -> float:
        return self._prefix + self._segment(self._turns[-1], self._input)

    @property
    def rest_length_m(self) -> float:
        """Length at 0 Pa in the relaxed state [m]."""
        return self._length(0.0, 0.0)

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        """Move to a new pressure [Pa gauge]; return the muscle length [m].

        `t_s` is the families' common time argument (sim.families.Muscle); unused here.
        """
        v = min(max(float(pressure_pa) - self.params.dead_zone_pa, 0.0), SPAN_PA)
        turns = self._turns
        changed = False
        u = self._input
        if v != u:
            last = turns[-1]
            if u != last and (u - last) * (v - u) < 0:
                turns.append(u)  # reversal: the previous input becomes a turning point
                changed = True
            # Wiping-out: passing the previous extremum of the same kind closes a minor
            # loop, which is then forgotten (its two turning points go).
            while len(turns) >= 3 and (v - turns[-1]) * (turns[-2] - turns[-1]) > 0 \
                    and abs(v - turns[-1]) >= abs(turns[-2] - turns[-1]):
                del turns[-2:]
                changed = True
            if len(turns) == 2 and v <= 0.0:
                del turns[1:]  # back at the bottom of the domain: every relay is off
                changed = True
            self._input = v
            if changed:
                self._recompute_prefix()
        self.length_m = self._length(self.hysteretic_fraction(), v)
        return self.length_m

    def turning_points_pa(self) -> list[float]:
        """The remembered reversals (effective pressure, Pa); for tests and diagnostics."""
        return list(self._turns[1:])


def major_loop_m(params: MuscleParams, pressures_pa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Increasing and decreasing branch lengths of the relaxed 0 -> max -> 0 loop, in closed form.

    After any excursion back to 0 Pa every relay is off, so a preconditioning cycle
    leaves the Preisach state where it started: the loop is steady from the first cycle.
    """
    table = everett_table(params)
    n = table.shape[0] - 1
    p_eff = effective_pressure(pressures_pa, params)
    top = effective_pressure(np.max(pressures_pa), params)

    def everett(high, low):
        # Bilinear interpolation, vectorised (same scheme as PreisachMuscle._everett).
        x = np.clip(np.asarray(high) / EVERETT_STEP_PA, 0, n)
        y = np.clip(np.asarray(low) / EVERETT_STEP_PA, 0, n)
        i = np.minimum(x.astype(int), n - 1)
        j = np.minimum(y.astype(int), n - 1)
        fx, fy = x - i, y - j
        return ((table[i, j] * (1 - fx) + table[i + 1, j] * fx) * (1 - fy)
                + (table[i, j + 1] * (1 - fx) + table[i + 1, j + 1] * fx) * fy)

    rev = reversible_fraction(p_eff, params)
    up = params.rest_length_m - params.stroke_hyst_m * everett(p_eff, 0.0 * p_eff) \
        - params.stroke_rev_m * rev
    hyst_down = everett(top + 0.0 * p_eff, 0.0 * p_eff) - everett(top + 0.0 * p_eff, p_eff)
    down = params.rest_length_m - params.stroke_hyst_m * hyst_down - params.stroke_rev_m * rev
    return up, down


def fit_major_loop(pressures_pa=TABLE1_PRESSURE_PA, increasing_m=TABLE1_LENGTH_INCREASING_M,
                   decreasing_m=TABLE1_LENGTH_DECREASING_M, starts: int = 12, seed: int = 0):
    """Least-squares fit of MuscleParams to a measured major loop (multi-start TRF).

    Offline only (scipy is imported here, not at run time). Returns (params, rmse_m).
    """
    from scipy.optimize import least_squares

    names = [f.name for f in fields(MuscleParams)]
    lower = np.array([0.29, 0.0, 0.0, 10e3, 0.0, 5e3, 0.0, 0.0, 10e3, 0.0])
    upper = np.array([0.31, 0.1, 500e3, 400e3, 300e3, 300e3, 0.1, 600e3, 400e3, 100e3])
    scale = np.array([0.01, 0.01, 1e5, 1e5, 1e5, 1e5, 0.01, 1e5, 1e5, 1e5])
    target = np.concatenate([increasing_m, decreasing_m])

    def residuals(z):
        up, down = major_loop_m(MuscleParams(*(z * scale)), pressures_pa)
        return np.concatenate([up, down]) - target

    rng = np.random.default_rng(seed)
    best = None
    for k in range(starts):
        x0 = np.array(astuple(TABLE1_FIT)) if k == 0 else rng.uniform(lower, upper)
        result = least_squares(residuals, x0 / scale, bounds=(lower / scale, upper / scale),
                               x_scale='jac')
        if best is None or result.cost < best.cost:
            best = result
    params = MuscleParams(**dict(zip(names, best.x * scale, strict=True)))
    rmse = float(np.sqrt(np.mean(best.fun ** 2)))
    return params, rmse


def main() -> None:
    params, rmse = fit_major_loop()
    print(f'# RMSE {rmse * 100:.4f} cm over {2 * len(TABLE1_PRESSURE_PA)} points')
    print('TABLE1_FIT = MuscleParams(')
    for name, value in zip([f.name for f in fields(MuscleParams)], astuple(params), strict=True):
        print(f'    {name}={float(value)!r},')
    print(')')


if __name__ == '__main__':
    main()
