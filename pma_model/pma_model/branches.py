"""Static length-pressure branches of the muscle: the paper's sigmoid and a Hill curve.

Each hysteresis branch (increasing or decreasing pressure) is a monotone map from gauge
pressure to length. Both forms share one interface so the memory model, the fitter and the
node never care which one is in use. Everything is SI: pressure in Pa, length in m, and the
sigmoid's b in 1/Pa (the paper's 0.011333 per kPa is 1.1333e-5 per Pa, see units.py).

Pressures below 0 Pa gauge are treated as 0 Pa: there is no data below ambient and the
muscle does not lengthen under a slight vacuum, so the forward map holds its rest value.
"""

from __future__ import annotations

import abc
import functools
import math
from dataclasses import asdict, dataclass, fields
from typing import ClassVar

import numpy as np
from scipy.optimize import least_squares

from pma_model import kernel

DEFAULT_MAX_GAUGE_PRESSURE_PA = 500_000.0

# Sanity limits that catch unit mix-ups (cm for m, b per kPa for per Pa, K in kPa). The
# fitter's bounds stay inside them, so a refit never writes parameters the node refuses.
MAX_L0_M = 2.0
MAX_B_PER_PA = 1e-3
MIN_K_PA = 1_000.0

# Towards saturation dP/dL grows without bound, so a sensor-sized length error maps to an
# arbitrarily large pressure. The inverse refuses lengths beyond the pressure where 0.1 mm
# of length moves the answer by 100 kPa (1e9 Pa/m): for the paper's sigmoids that is
# 650-750 kPa, so it only bites when max_gauge_pressure_pa is raised beyond the muscle's
# range (at 500 kPa the figure is 7-15 kPa per 0.1 mm).
MAX_INVERSE_SENSITIVITY_PA_PER_M = 1e9


class UnreachableLengthError(ValueError):
    """The requested length cannot be produced with gauge pressures 0..max on this branch."""

    def __init__(self, message: str, min_length_m: float, max_length_m: float):
        super().__init__(message)
        self.min_length_m = min_length_m
        self.max_length_m = max_length_m


def _require(condition: bool, name: str, value, rule: str) -> None:
    if not condition:
        raise ValueError(f'{name} must be {rule}, got {value!r}')


def _finite_positive(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@dataclass(frozen=True)
class Branch(abc.ABC):
    """One monotone length(pressure) branch with a closed-form inverse.

    Subclasses are frozen dataclasses whose fields are the parameters, in the order of
    `names`; that order is also the parameter vector a least-squares fitter works on.
    """

    form: ClassVar[str]
    # The compiled formula of this form (kernel.SIGMOID, kernel.HILL): the one home of its
    # length and inverse, which `length` and `inverse_unchecked` call for floats and arrays.
    kernel_formula: ClassVar[float]

    @functools.cached_property
    def kernel_row(self) -> np.ndarray:
        """This branch as the compiled formulas read it (kernel.py's branch row, without a
        correction); computed once, as branches are frozen."""
        row = np.zeros(kernel.ROW_HEAD)
        row[kernel.ROW_FORMULA] = self.kernel_formula
        row[kernel.ROW_PARAMETERS:kernel.ROW_KNOTS] = self.vector()
        return row

    def length(self, p_pa):
        """Length [m] at gauge pressure(s) [Pa]; vectorised, float in -> float out."""
        if isinstance(p_pa, float):   # one sample (online, the inverse's searches): no numpy
            return kernel.branch_length(self.kernel_row, p_pa)
        return kernel.elementwise(kernel.branch_lengths, p_pa, self.kernel_row)

    def inverse_unchecked(self, length_m):
        """The closed-form inverse with no range check: NaN where it has no real answer.

        For callers that have already checked the range (the memory model's scanning
        curves); everyone else should call `pressure`.
        """
        if isinstance(length_m, float):   # one length (the controller's inverse): no numpy
            return kernel.branch_pressure(self.kernel_row, length_m)
        return kernel.elementwise(kernel.branch_pressures, length_m, self.kernel_row)

    @abc.abstractmethod
    def stroke_m(self) -> float:
        """Distance from the rest length to the saturation asymptote [m]."""

    @abc.abstractmethod
    def saturation_length_m(self) -> float:
        """The length approached as pressure grows without bound [m]."""

    # --- derived behaviour, shared by all forms -----------------------------------------

    def length_range(self, p_max_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA):
        """(min_length_m, max_length_m) reachable with gauge pressures 0..p_max_pa."""
        return float(self.length(p_max_pa)), float(self.length(0.0))

    def invertible_pressure_limit(self, p_max_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA):
        """Highest pressure the inverse may answer: p_max_pa or the conditioning limit."""
        return min(float(p_max_pa), self._well_conditioned_limit_pa)

    def slope_m_per_pa(self, p_pa: float) -> float:
        """|dL/dP| at p_pa (central difference; the forms are smooth)."""
        step = max(1.0, 1e-6 * p_pa)
        low = max(0.0, p_pa - step)
        return abs(float(self.length(p_pa + step)) - float(self.length(low))) / (p_pa + step - low)

    @functools.cached_property
    def _well_conditioned_limit_pa(self) -> float:
        """Pressure past the steepest point where |dP/dL| reaches the sensitivity limit."""
        threshold = 1.0 / MAX_INVERSE_SENSITIVITY_PA_PER_M
        grid = np.geomspace(1e3, 1e8, 200)
        slopes = np.array([self.slope_m_per_pa(p) for p in grid])
        steepest = int(np.argmax(slopes))
        beyond = np.nonzero(slopes[steepest:] < threshold)[0]
        if slopes[steepest] < threshold or beyond.size == 0:
            return math.inf  # no well-conditioned part to cut off (or not a muscle at all)
        low, high = grid[steepest + beyond[0] - 1], grid[steepest + beyond[0]]
        for _ in range(60):  # bisection on the falling side of the slope
            middle = 0.5 * (low + high)
            low, high = (middle, high) if self.slope_m_per_pa(middle) >= threshold \
                else (low, middle)
        return float(low)

    def invertible_range(self, p_max_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA):
        """(min_length_m, max_length_m) the inverse answers for: 0..invertible_pressure_limit."""
        return self.length_range(self.invertible_pressure_limit(p_max_pa))

    def pressure(self, length_m, p_max_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA):
        """Gauge pressure [Pa] that gives length_m on this branch; never extrapolates.

        Raises UnreachableLengthError (with the reachable range) when any requested length
        is not finite or needs a pressure outside 0..p_max_pa.
        """
        lengths = np.asarray(length_m, dtype=float)
        low, high = self.invertible_range(p_max_pa)
        bad = ~(np.isfinite(lengths) & (lengths >= low) & (lengths <= high))
        if np.any(bad):
            first = float(lengths[bad].flat[0])
            raise UnreachableLengthError(
                f'length {first:.6g} m is outside the {self.form} branch range '
                f'[{low:.6g}, {high:.6g}] m reachable with 0..{p_max_pa:.6g} Pa '
                '(and where 0.1 mm moves the answer by less than 100 kPa)',
                low, high)
        limit_pa = self.invertible_pressure_limit(p_max_pa)
        pressures = np.clip(self.inverse_unchecked(lengths), 0.0, limit_pa)
        return float(pressures) if pressures.ndim == 0 else pressures

    # --- parameter vector for fitters ---------------------------------------------------

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    def vector(self) -> np.ndarray:
        return np.array([getattr(self, name) for name in self.names()], dtype=float)

    @classmethod
    def from_vector(cls, vector) -> Branch:
        values = [float(v) for v in vector]
        if len(values) != len(cls.names()):
            raise ValueError(f'{cls.form} branch needs {len(cls.names())} parameters '
                             f'{cls.names()}, got {len(values)}')
        return cls(**dict(zip(cls.names(), values, strict=True)))

    @classmethod
    @abc.abstractmethod
    def bounds(cls) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) for each entry of the parameter vector, for least_squares."""

    def to_dict(self) -> dict[str, float]:
        return {name: float(value) for name, value in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> Branch:
        missing = set(cls.names()) - set(values)
        extra = set(values) - set(cls.names())
        if missing or extra:
            raise ValueError(f'{cls.form} branch parameters must be exactly {cls.names()}; '
                             f'missing {sorted(missing)}, unknown {sorted(extra)}')
        return cls(**{name: float(values[name]) for name in cls.names()})


@dataclass(frozen=True)
class SigmoidBranch(Branch):
    """The paper's branch: L = L0 - a*L0 / (1 + exp(-b*P))**c."""

    form: ClassVar[str] = 'sigmoid'
    kernel_formula: ClassVar[float] = kernel.SIGMOID

    l0_m: float
    a: float
    b_per_pa: float
    c: float

    def __post_init__(self):
        _require(_finite_positive(self.l0_m), 'l0_m', self.l0_m, 'finite and > 0')
        _require(_finite_positive(self.a) and self.a < 1, 'a', self.a, 'in (0, 1)')
        _require(_finite_positive(self.b_per_pa), 'b_per_pa', self.b_per_pa, 'finite and > 0')
        _require(_finite_positive(self.c), 'c', self.c, 'finite and > 0')

    def stroke_m(self) -> float:
        return self.a * self.l0_m

    def saturation_length_m(self) -> float:
        return self.l0_m * (1.0 - self.a)

    @classmethod
    def bounds(cls):
        return (np.array([1e-3, 1e-6, 1e-9, 1e-2]),
                np.array([MAX_L0_M, 1.0 - 1e-9, MAX_B_PER_PA, 100.0]))


@dataclass(frozen=True)
class HillBranch(Branch):
    """A Hill curve: L = L0 - dL * P**n / (P**n + K**n).

    Unlike the sigmoid it is flat at P = 0 (n > 1), so it follows the rig's 0-50 kPa
    dead zone, and it saturates at L0 - dL rather than at a fixed exponent's limit.
    """

    form: ClassVar[str] = 'hill'
    kernel_formula: ClassVar[float] = kernel.HILL

    l0_m: float
    dl_m: float
    k_pa: float
    n: float

    def __post_init__(self):
        _require(_finite_positive(self.l0_m), 'l0_m', self.l0_m, 'finite and > 0')
        _require(_finite_positive(self.dl_m) and self.dl_m < self.l0_m, 'dl_m', self.dl_m,
                 'in (0, l0_m)')
        _require(_finite_positive(self.k_pa), 'k_pa', self.k_pa, 'finite and > 0')
        _require(_finite_positive(self.n), 'n', self.n, 'finite and > 0')

    def stroke_m(self) -> float:
        return self.dl_m

    def saturation_length_m(self) -> float:
        return self.l0_m - self.dl_m

    @classmethod
    def bounds(cls):
        return (np.array([1e-3, 1e-6, MIN_K_PA, 0.1]), np.array([MAX_L0_M, MAX_L0_M, 1e7, 20.0]))


@dataclass(frozen=True)
class BranchForm:
    """A registered branch form: its class and what the node, the refit and the figures say
    of it. Adding a form is one Branch subclass and one `register_branch_form` call."""

    cls: type[Branch]
    label: str      # in legends and messages ('Hill branches')
    colour: str     # in figures (plots.py): the colour of the report model fitting it freely
    formula: str    # in model_node's parameter description
    seed: Branch    # placeholder numbers (params.py merges the data file into them)

    @property
    def name(self) -> str:
        return self.cls.form


# The one registry of branch forms, by name (the `branch_form` setting), in menu order.
BRANCH_FORMS: dict[str, BranchForm] = {}


def register_branch_form(form: BranchForm) -> BranchForm:
    BRANCH_FORMS[form.name] = form
    return form


register_branch_form(BranchForm(
    SigmoidBranch, "paper's sigmoid", '#0072B2', "the paper's L0 - a*L0/(1+exp(-b*P))^c",
    SigmoidBranch(0.3, 0.2, 1e-5, 6.0)))
register_branch_form(BranchForm(
    HillBranch, 'Hill branches', '#117733', 'L0 - dL*P^n/(P^n+K^n)',
    HillBranch(0.3, 0.06, 2e5, 2.0)))


def branch_class(form: str) -> type[Branch]:
    try:
        return BRANCH_FORMS[form].cls
    except KeyError:
        raise ValueError(f'branch form must be one of {sorted(BRANCH_FORMS)}, got {form!r}') \
            from None


def fit_branch(initial: Branch, p_pa, length_m, fixed: tuple[str, ...] = ()) -> Branch:
    """Least-squares fit of a branch to (pressure, length) samples, from `initial`.

    Parameters named in `fixed` keep their initial value (the paper fixes c and L0).
    NaN samples are ignored. Residuals are in metres, so the fit minimises the MSE.
    """
    cls = type(initial)
    pressures = np.asarray(p_pa, dtype=float)
    lengths = np.asarray(length_m, dtype=float)
    keep = np.isfinite(pressures) & np.isfinite(lengths)
    pressures, lengths = pressures[keep], lengths[keep]
    unknown = set(fixed) - set(cls.names())
    if unknown:
        raise ValueError(f'cannot fix unknown {cls.form} parameters {sorted(unknown)}')
    free = [i for i, name in enumerate(cls.names()) if name not in fixed]
    if len(pressures) < len(free):
        raise ValueError(f'need at least {len(free)} finite samples, got {len(pressures)}')
    start = initial.vector()
    lower, upper = cls.bounds()

    # Parameters differ by ~10 orders of magnitude (b per Pa vs L0 in m), so the solver
    # works on them divided by their starting values: every unknown is then about 1.
    scale = np.where(start[free] != 0, np.abs(start[free]), 1.0)

    def model_with(normalised):
        vector = start.copy()
        vector[free] = normalised * scale
        return cls.from_vector(vector)

    def residuals(normalised):
        return model_with(normalised).length(pressures) - lengths

    result = least_squares(residuals, start[free] / scale,
                           bounds=(lower[free] / scale, upper[free] / scale), method='trf',
                           x_scale='jac', xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=10_000)
    return model_with(result.x)
