"""Bounded multi-start least squares with Jacobian-based parameter uncertainty.

The paper fits each branch with MATLAB lsqcurvefit from one start; a sigmoid with a free
exponent has long, flat valleys, so a single start can stop anywhere along them. Here every
fit runs scipy's trust-region reflective solver from several deterministic starts and keeps
the lowest cost, then reports what the data say about each parameter: standard errors and
95 % t-intervals from s^2 (J^T J)^-1, the correlation matrix, and cond(J^T J). Conditioning is
computed on the Jacobian with respect to log|parameter| (columns scaled by |x|), so it does not
depend on the unit a parameter is expressed in (b per Pa vs per kPa).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from pma_model.branches import Branch

# Above this cond(J^T J) the parameters are not separately identifiable from the data.
IDENTIFIABILITY_COND_LIMIT = 1e8
DEFAULT_STARTS = 12


class FitError(RuntimeError):
    """No start ended at a finite solution."""


@dataclass
class LeastSquaresFit:
    """The best start's optimum, its residuals and the local uncertainty around it.

    `converged_starts` counts the starts that met the tolerances; when the best did not,
    `warnings` says the optimum is where the evaluation budget ran out.
    """

    names: tuple[str, ...]
    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    starts: int
    converged_starts: int
    stderr: np.ndarray = field(init=False)
    ci95_low: np.ndarray = field(init=False)
    ci95_high: np.ndarray = field(init=False)
    correlation: np.ndarray = field(init=False)
    cond_jtj: float = field(init=False)
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self):
        n, k = self.jacobian.shape
        dof = n - k
        sse = float(self.residuals @ self.residuals)
        scale = np.where(self.x != 0, np.abs(self.x), 1.0)
        scaled = self.jacobian * scale
        singular = np.linalg.svd(scaled, compute_uv=False)
        self.cond_jtj = float((singular[0] / singular[-1]) ** 2) if singular[-1] > 0 \
            else math.inf
        nan = np.full(k, np.nan)
        self.stderr, self.ci95_low, self.ci95_high = nan.copy(), nan.copy(), nan.copy()
        self.correlation = np.full((k, k), np.nan)
        if dof > 0 and math.isfinite(self.cond_jtj):
            scaled_cov = np.linalg.pinv(scaled.T @ scaled) * (sse / dof)
            cov = scaled_cov * np.outer(scale, scale)
            self.stderr = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            half = stats.t.ppf(0.975, dof) * self.stderr
            self.ci95_low, self.ci95_high = self.x - half, self.x + half
            with np.errstate(invalid='ignore', divide='ignore'):
                self.correlation = cov / np.outer(self.stderr, self.stderr)
        if self.cond_jtj > IDENTIFIABILITY_COND_LIMIT:
            self.warnings.append(
                f'cond(J^T J) = {self.cond_jtj:.3g} > {IDENTIFIABILITY_COND_LIMIT:.0e}: '
                f'parameters {", ".join(self.names)} are not identifiable from these data')

    @property
    def sse(self) -> float:
        return float(self.residuals @ self.residuals)

    def value(self, name: str) -> float:
        return float(self.x[self.names.index(name)])

    def stderr_of(self, name: str) -> float:
        return float(self.stderr[self.names.index(name)])


def start_points(lower, upper, count: int, first=None, seed: int = 0) -> np.ndarray:
    """`count` starts spread over the box (Latin hypercube, fixed seed), `first` included.

    Finite boxes only: callers narrow the solver's bounds to a plausible start region.
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        raise ValueError('start boxes must be finite')
    sampler = stats.qmc.LatinHypercube(d=lower.size, seed=seed)
    points = stats.qmc.scale(sampler.random(count), lower, upper) if np.all(upper > lower) \
        else np.tile(lower, (count, 1))
    if first is not None:
        points[0] = np.clip(np.asarray(first, float), lower, upper)
    return points


def multistart_least_squares(residuals: Callable[[np.ndarray], np.ndarray],
                             names: Sequence[str], bounds, starts: np.ndarray, *,
                             jac: Callable | str = '2-point',
                             max_nfev: int | None = None) -> LeastSquaresFit:
    """Run least_squares (trf, x_scale='jac') from each start and keep the lowest cost.

    A start stopped by `max_nfev` competes too: on a flat valley (a poorly identified model)
    it may have crept further down than any start that met the tolerances elsewhere, and
    which of them meets the tolerances within the budget turns on the last bits of the
    arithmetic (Table 1's sigmoid Bouc-Wen, docs/refit.md). When the best stopped at the
    budget, `warnings` says so.
    """
    lower, upper = (np.asarray(b, float) for b in bounds)
    starts = np.atleast_2d(starts)
    converged, unfinished = [], []
    for start in starts:
        x0 = np.clip(start, lower, upper)
        try:
            result = least_squares(residuals, x0, jac=jac, bounds=(lower, upper),
                                   method='trf', x_scale='jac', xtol=1e-12, ftol=1e-12,
                                   gtol=1e-12, max_nfev=max_nfev)
        except (ValueError, FloatingPointError):
            continue
        if not np.all(np.isfinite(result.fun)) or result.status < 0:
            continue
        (converged if result.status > 0 else unfinished).append(result)
    if not converged and not unfinished:
        raise FitError(f'the fit of ({", ".join(names)}) did not converge from any of '
                       f'{len(starts)} starts')
    best = min(converged + unfinished, key=lambda result: result.cost)
    warnings = []
    if best.status == 0:
        costs = [result.cost for result in unfinished]
        spread = (max(costs) - min(costs)) / min(costs) if min(costs) > 0 else 0.0
        met = (f'{len(converged)} that met them ended at a higher cost' if converged
               else 'none met them')
        warnings.append(f'the best start did not meet the tolerances within {best.nfev} '
                        f'evaluations and is reported; {met} (the {len(unfinished)} stopped '
                        f'at the budget differ in cost by up to {100 * spread:.2g} %)')
    return LeastSquaresFit(tuple(names), best.x, best.fun, best.jac, starts=len(starts),
                           converged_starts=len(converged), warnings=warnings)


@dataclass
class BranchFit:
    """A fitted branch, the free parameters' statistics and the values held fixed."""

    branch: Branch
    fit: LeastSquaresFit
    fixed: dict[str, float]

    @property
    def k(self) -> int:
        return len(self.fit.names)


def _start_box(cls: type[Branch], p_pa: np.ndarray, length_m: np.ndarray):
    """A plausible region for starts, from the data's rest length, stroke and pressure span."""
    rest = float(np.max(length_m))
    stroke = max(float(np.ptp(length_m)), 1e-6)
    p_max = max(float(np.max(p_pa)), 1.0)
    if cls.form == 'sigmoid':
        low = [rest, 0.5 * stroke / rest, 1.0 / p_max, 1.0]
        high = [rest + 0.5 * stroke, min(2.0 * stroke / rest, 0.99), 30.0 / p_max, 15.0]
    else:
        low = [rest - 0.1 * stroke, 0.7 * stroke, 0.1 * p_max, 1.0]
        high = [rest + 0.1 * stroke, 1.5 * stroke, 0.9 * p_max, 5.0]
    return np.array(low), np.array(high)


def fit_branch_multistart(cls: type[Branch], p_pa, length_m,
                          fixed: dict[str, float] | None = None, *, starts: int = DEFAULT_STARTS,
                          initial: Branch | None = None) -> BranchFit:
    """Fit one branch (SI units) with some parameters held at given values.

    The paper's form is `fit_branch_multistart(SigmoidBranch, p, L, {'l0_m': L[0], 'c': 6.214})`.
    """
    fixed = dict(fixed or {})
    pressures = np.asarray(p_pa, dtype=float)
    lengths = np.asarray(length_m, dtype=float)
    keep = np.isfinite(pressures) & np.isfinite(lengths)
    pressures, lengths = pressures[keep], lengths[keep]
    names = cls.names()
    unknown = set(fixed) - set(names)
    if unknown:
        raise ValueError(f'cannot fix unknown {cls.form} parameters {sorted(unknown)}')
    free = [i for i, name in enumerate(names) if name not in fixed]
    if len(pressures) <= len(free):
        raise ValueError(f'a {cls.form} branch with {len(free)} free parameters needs more than '
                         f'{len(free)} samples, got {len(pressures)}')
    lower, upper = cls.bounds()
    box_low, box_high = _start_box(cls, pressures, lengths)
    template = box_low.copy()
    for name, value in fixed.items():
        template[names.index(name)] = value

    def full(free_values):
        vector = template.copy()
        vector[free] = free_values
        return vector

    def residuals(free_values):
        return cls.from_vector(full(free_values)).length(pressures) - lengths

    first = initial.vector()[free] if initial is not None else None
    box_low_free = np.maximum(box_low[free], lower[free])
    box_high_free = np.minimum(box_high[free], upper[free])
    points = start_points(box_low_free, box_high_free, starts, first)
    fit = multistart_least_squares(residuals, [names[i] for i in free],
                                   (lower[free], upper[free]), points)
    return BranchFit(cls.from_vector(full(fit.x)), fit, fixed)
