"""Bouc-Wen hysteresis driven by pressure, for comparison with the paper's Table 2.

    L(P) = B(P) + k_h * z,    dz = A du - beta |du| |z|^(n-1) z - gamma du |z|^n,  u = P / p_ref

B is the backbone: the classical linear one (L0 + slope * u), which is what the paper's
Bouc-Wen row uses, or a nonlinear branch from pma_model.branches (Hill or sigmoid). A = 1
(its scale is k_h's). Only the bounded variant beta >= |gamma| is offered, parameterised as
gamma = tau * beta with tau in [-1, 1]: then the loop is dissipative and z stays bounded.

The data are quasi-static, so the model is simulated in the pressure domain (rate
independent): 0 -> p_ref -> 0 repeated, z starting at 0, and the last cycle is the steady loop
compared with the data (PRECONDITIONING_CYCLES cycles before it). The z update is
semi-implicit, z' = (z + s*A*h) / (1 + h*c(z)) with c >= 0, so it is stable for any
parameters the fitter tries. Bouc-Wen has no return-point memory: repeated minor loops drift
(`minor_loop_drift`), and one major loop does not identify beta, gamma and n separately.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pma_model.branches import Branch, branch_class
from pma_model.fitting import LeastSquaresFit, multistart_least_squares, start_points

PRECONDITIONING_CYCLES = 2
STEPS_PER_SWEEP = 100
HYSTERESIS_NAMES = ('k_h_m', 'beta', 'tau', 'n')
# Start region and solver bounds of (k_h_m as a fraction of the stroke, beta, tau, n).
_BETA_MAX = 50.0
_N_RANGE = (1.0, 3.0)
SCREENING_CANDIDATES = 256
POLISHED_STARTS = 4
LOOPLESS_FRACTION = 0.01   # a fitted loop narrower than this share of the stroke is none


@dataclass(frozen=True)
class LinearBackbone:
    """The classical Bouc-Wen backbone: L0 + slope * P / p_ref (slope < 0 for a contractor)."""

    l0_m: float
    slope_m: float
    p_ref_pa: float

    form = 'linear'

    @staticmethod
    def names() -> tuple[str, ...]:
        return ('l0_m', 'slope_m')

    def length(self, p_pa):
        return self.l0_m + self.slope_m * np.asarray(p_pa, dtype=float) / self.p_ref_pa

    def to_dict(self) -> dict[str, float]:
        return {'l0_m': self.l0_m, 'slope_m': self.slope_m}


@dataclass(frozen=True)
class BoucWenModel:
    """A backbone plus the Bouc-Wen state term, over pressures 0..p_ref_pa."""

    backbone: object  # LinearBackbone or a pma_model.branches.Branch
    k_h_m: float
    beta: float
    tau: float
    n: float
    p_ref_pa: float
    steps_per_sweep: int = STEPS_PER_SWEEP

    @property
    def gamma(self) -> float:
        return self.tau * self.beta

    def hysteresis_vector(self) -> np.ndarray:
        return np.array([self.k_h_m, self.beta, self.tau, self.n])

    def steady_loop(self):
        """(u grid, z on the rising sweep, z on the falling sweep) of the preconditioned loop."""
        grid, z_up, z_down = _steady_loop_batch(self.hysteresis_vector()[None, 1:],
                                                self.steps_per_sweep)
        return grid, z_up[0], z_down[0]

    @property
    def loop_width_m(self) -> float:
        """Widest gap between the steady loop's sweeps: 0 when the fit has no hysteresis."""
        _, z_up, z_down = self.steady_loop()
        return float(abs(self.k_h_m) * np.max(np.abs(z_up - z_down)))

    def loop_lengths(self, p_pa, rising) -> np.ndarray:
        """Length on the steady loop at each pressure; `rising` picks the sweep per sample."""
        grid, z_up, z_down = self.steady_loop()
        return _loop_lengths(self.backbone, self.k_h_m, self.p_ref_pa, (grid, z_up, z_down),
                             np.asarray(p_pa, float), rising=np.asarray(rising, bool))

    def simulate_path(self, p_pa, z0: float = 0.0) -> np.ndarray:
        """Lengths along an arbitrary pressure path (sub-stepped like the loop), from z0."""
        p_pa = np.asarray(p_pa, dtype=float)
        zs = np.empty(p_pa.size)
        zs[0] = z0
        for i in range(1, p_pa.size):
            zs[i] = self.advance_state(zs[i - 1], p_pa[i - 1], p_pa[i])
        return self.length_m(p_pa, zs)

    def advance_state(self, z: float, from_pa: float, to_pa: float) -> float:
        """The state z after pressure moves from `from_pa` to `to_pa` (steps of the loop's size).

        One step at a time is what a simulated muscle needs: it sees its pressure per sample.
        """
        du = (float(to_pa) - float(from_pa)) / self.p_ref_pa
        steps = max(1, int(np.ceil(abs(du) * self.steps_per_sweep - 1e-9)))
        state = np.array([z], dtype=float)
        if du != 0.0:
            params = self.hysteresis_vector()[None, 1:]
            for _ in range(steps):
                state = _step(state, du / steps, params)
        return float(state[0])

    def length_m(self, p_pa, z):
        """Backbone plus the hysteresis term."""
        return self.backbone.length(p_pa) + self.k_h_m * np.asarray(z)

    def params_dict(self) -> dict[str, float]:
        values = {f'backbone_{k}': float(v) for k, v in self.backbone.to_dict().items()}
        values.update(k_h_m=self.k_h_m, A=1.0, beta=self.beta, gamma=self.gamma, n=self.n,
                      p_ref_pa=self.p_ref_pa)
        return values


def _step(z: np.ndarray, du: float, params: np.ndarray) -> np.ndarray:
    """One semi-implicit step for a batch: params rows are (beta, tau, n)."""
    h = abs(du)
    s = 1.0 if du > 0 else -1.0
    beta_h, gamma_h, n_minus_1 = _step_constants(params, h, s)
    return _step_with(z, s * h, beta_h, gamma_h, n_minus_1)


def _step_constants(params: np.ndarray, h: float, s: float):
    """Per-row constants of a sweep: h*beta, s*h*gamma and n-1."""
    return h * params[:, 0], s * h * params[:, 0] * params[:, 1], params[:, 2] - 1.0


def _step_with(z, signed_h, beta_h, gamma_h, n_minus_1):
    # dz = h*(s*A - c*z), c = (beta + s*gamma*sign(z)) |z|^(n-1) >= 0 because beta >= |gamma|.
    return (z + signed_h) / (1.0 + (beta_h + gamma_h * np.sign(z)) * np.abs(z) ** n_minus_1)


def _steady_loop_batch(params: np.ndarray, steps: int):
    """Simulate every parameter row at once; return grid and (rows x grid) z per sweep."""
    rows = params.shape[0]
    h = 1.0 / steps
    z = np.zeros(rows)
    z_up = np.empty((rows, steps + 1))
    z_down = np.empty((rows, steps + 1))
    rising = _step_constants(params, h, 1.0)
    falling = _step_constants(params, h, -1.0)
    for _ in range(PRECONDITIONING_CYCLES + 1):
        z_up[:, 0] = z
        for i in range(steps):
            z = _step_with(z, h, *rising)
            z_up[:, i + 1] = z
        z_down[:, steps] = z
        for i in range(steps, 0, -1):
            z = _step_with(z, -h, *falling)
            z_down[:, i - 1] = z
    return np.linspace(0.0, 1.0, steps + 1), z_up, z_down


def _loop_lengths(backbone, k_h_m, p_ref_pa, loop, p_pa, *, rising):
    grid, z_up, z_down = loop
    u = np.clip(p_pa / p_ref_pa, 0.0, 1.0)
    z = np.where(rising, np.interp(u, grid, z_up), np.interp(u, grid, z_down))
    return backbone.length(p_pa) + k_h_m * z


@dataclass
class BoucWenFit:
    model: BoucWenModel
    fit: LeastSquaresFit

    @property
    def k(self) -> int:
        return len(self.fit.names)


def _backbone_from(form: str, vector: np.ndarray, p_ref_pa: float):
    if form == 'linear':
        return LinearBackbone(float(vector[0]), float(vector[1]), p_ref_pa)
    return branch_class(form).from_vector(vector)


def _backbone_box(form: str, p_pa, length_m):
    """(solver bounds, start box) of the backbone parameters, from the data."""
    rest = float(np.max(length_m))
    stroke = max(float(np.ptp(length_m)), 1e-6)
    p_max = float(np.max(p_pa))
    if form == 'linear':
        bounds = (np.array([rest - 2 * stroke, -3 * stroke]), np.array([rest + 2 * stroke, 0.0]))
        box = (np.array([rest - 0.5 * stroke, -1.5 * stroke]), np.array([rest, -0.5 * stroke]))
        return bounds, box
    cls: type[Branch] = branch_class(form)
    bounds = cls.bounds()
    if form == 'hill':
        box = (np.array([rest - 0.1 * stroke, 0.7 * stroke, 0.2 * p_max, 1.0]),
               np.array([rest + 0.1 * stroke, 1.5 * stroke, 0.8 * p_max, 4.0]))
    else:
        box = (np.array([rest, 0.5 * stroke / rest, 2.0 / p_max, 2.0]),
               np.array([rest + 0.3 * stroke, 1.5 * stroke / rest, 20.0 / p_max, 12.0]))
    return bounds, box


def fit_bouc_wen(p_pa, length_m, rising, backbone: str = 'linear', *,
                 steps_per_sweep: int = STEPS_PER_SWEEP, seed: int = 0,
                 warm_start: np.ndarray | None = None) -> BoucWenFit:
    """Fit backbone + (k_h, beta, tau, n) to loop samples; `rising` marks the increasing branch.

    Multi-start: SCREENING_CANDIDATES Latin-hypercube points are simulated in one batch and
    the POLISHED_STARTS best are refined with least_squares. `warm_start` (a previous fit's
    parameter vector, e.g. on the full data for a hold-out refit) is refined on its own.
    """
    p_pa = np.asarray(p_pa, float)
    length_m = np.asarray(length_m, float)
    rising = np.asarray(rising, bool)
    keep = np.isfinite(p_pa) & np.isfinite(length_m)
    p_pa, length_m, rising = p_pa[keep], length_m[keep], rising[keep]
    p_ref = float(np.max(p_pa))
    if p_ref <= 0:
        raise ValueError('Bouc-Wen needs pressures above 0 Pa')
    stroke = max(float(np.ptp(length_m)), 1e-6)
    (b_low, b_high), (box_low, box_high) = _backbone_box(backbone, p_pa, length_m)
    nb = b_low.size
    h_low = np.array([-3 * stroke, 0.0, -1.0, _N_RANGE[0]])
    h_high = np.array([3 * stroke, _BETA_MAX, 1.0, _N_RANGE[1]])
    h_box_low = np.array([-stroke, 0.1, -1.0, _N_RANGE[0]])
    h_box_high = np.array([stroke, 20.0, 1.0, _N_RANGE[1]])
    lower, upper = np.concatenate([b_low, h_low]), np.concatenate([b_high, h_high])
    if len(p_pa) <= lower.size:
        raise ValueError(f'Bouc-Wen ({backbone} backbone) has {lower.size} parameters and needs '
                         f'more samples than that, got {len(p_pa)}')

    def model_of(x):
        return BoucWenModel(_backbone_from(backbone, x[:nb], p_ref), float(x[nb]),
                            float(x[nb + 1]), float(x[nb + 2]), float(x[nb + 3]), p_ref,
                            steps_per_sweep)

    def batch_predictions(xs):
        grid, z_up, z_down = _steady_loop_batch(xs[:, nb + 1:], steps_per_sweep)
        out = np.empty((xs.shape[0], p_pa.size))
        for row, x in enumerate(xs):
            out[row] = _loop_lengths(_backbone_from(backbone, x[:nb], p_ref), x[nb], p_ref,
                                     (grid, z_up[row], z_down[row]), p_pa, rising=rising)
        return out

    # The batch costs about the same for 1 row as for 1 + k, so every residual evaluation
    # also computes the forward-difference Jacobian at that point; least_squares asks for
    # the Jacobian only at points whose residuals it has just evaluated.
    cache: dict[bytes, np.ndarray] = {}

    def residuals(x):
        steps = 1e-6 * np.maximum(np.abs(x), 1e-3 * (upper - lower))
        steps = np.where(x + steps > upper, -steps, steps)
        rows = batch_predictions(np.vstack([x[None, :], x + np.diag(steps)]))
        cache.clear()
        cache[x.tobytes()] = ((rows[1:] - rows[0]) / steps[:, None]).T
        return rows[0] - length_m

    def jacobian(x):
        if x.tobytes() not in cache:
            residuals(x)
        return cache[x.tobytes()]

    if warm_start is not None:
        best = np.clip(np.asarray(warm_start, float), lower, upper)[None, :]
    else:
        candidates = start_points(np.concatenate([box_low, h_box_low]),
                                  np.concatenate([box_high, h_box_high]), SCREENING_CANDIDATES,
                                  seed=seed)
        sse = np.sum((batch_predictions(candidates) - length_m) ** 2, axis=1)
        best = candidates[np.argsort(sse)[:POLISHED_STARTS]]
    names = (*_backbone_names(backbone), *HYSTERESIS_NAMES)
    fit = multistart_least_squares(residuals, names, (lower, upper), best, jac=jacobian,
                                   max_nfev=400)
    model = model_of(fit.x)
    # Least squares may prefer the backbone alone (beta or k_h at 0): then nothing of the
    # fit is Bouc-Wen, and whoever compares models or simulates it as a muscle must know.
    if model.loop_width_m < LOOPLESS_FRACTION * stroke:
        fit.warnings.append(
            f'the fitted loop is {1000 * model.loop_width_m:.2g} mm wide (the data\'s stroke '
            f'{1000 * stroke:.3g} mm): with this backbone Bouc-Wen fits best without '
            'hysteresis, and its hysteresis parameters mean nothing')
    return BoucWenFit(model, fit)


def _backbone_names(form: str) -> Sequence[str]:
    names = LinearBackbone.names() if form == 'linear' else branch_class(form).names()
    return tuple(f'backbone_{name}' for name in names)


def minor_loop_drift(model: BoucWenModel, low_pa: float, high_pa: float, cycles: int = 30):
    """Length at low_pa after each of `cycles` low<->high cycles, after the major loop.

    A model with return-point memory gives the same length every cycle; Bouc-Wen drifts.
    """
    rise = np.linspace(0, model.p_ref_pa, 51)
    major = np.concatenate([rise, rise[::-1]])
    path = np.concatenate([major, major, np.linspace(0, low_pa, 21)]
                          + [np.concatenate([np.linspace(low_pa, high_pa, 21)[1:],
                                             np.linspace(high_pa, low_pa, 21)[1:]])
                             for _ in range(cycles)])
    lengths = model.simulate_path(path)
    first = 2 * major.size + 20
    return lengths[first::40][: cycles + 1]
