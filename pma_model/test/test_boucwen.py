"""Bouc-Wen on the Table-1 loop: the paper's row, a nonlinear backbone, and minor-loop drift."""

import numpy as np
import pytest

from pma_model import units
from pma_model.boucwen import BoucWenModel, LinearBackbone, fit_bouc_wen, minor_loop_drift
from pma_model.branches import HillBranch
from pma_model.metrics import fit_metrics
from pma_model.params import paper_table1

pytestmark = pytest.mark.in_process


@pytest.fixture(scope='module')
def loop():
    table = paper_table1()
    p = np.concatenate([table.pressure_pa, table.pressure_pa])
    lengths = np.concatenate([table.increasing_length_m, table.decreasing_length_m])
    rising = np.arange(p.size) < table.pressure_pa.size
    return p, lengths, rising


@pytest.fixture(scope='module')
def linear_fit(loop):
    return fit_bouc_wen(*loop, backbone='linear')


def loop_metrics(fitted, loop):
    p, lengths, rising = loop
    predicted = fitted.model.loop_lengths(p, rising)
    return fit_metrics(units.m_to_cm(lengths), units.m_to_cm(predicted), k=fitted.k)


def test_linear_backbone_reproduces_the_papers_bouc_wen_row(linear_fit, loop):
    metrics = loop_metrics(linear_fit, loop)
    assert linear_fit.k == 6
    assert metrics.mae == pytest.approx(0.427, abs=0.01)
    assert metrics.r2 == pytest.approx(0.939, abs=0.003)
    assert metrics.mse == pytest.approx(0.269, abs=0.01)
    model = linear_fit.model
    assert model.beta >= abs(model.gamma) - 1e-12  # the bounded variant


def test_hill_backbone_fits_far_better(linear_fit, loop):
    fitted = fit_bouc_wen(*loop, backbone='hill')
    metrics = loop_metrics(fitted, loop)
    assert fitted.k == 8
    assert metrics.mse < 0.025
    assert metrics.mse < 0.1 * loop_metrics(linear_fit, loop).mse
    assert metrics.r2 > 0.995


def test_a_fit_without_hysteresis_says_so(loop, linear_fit):
    # With the sigmoid backbone, Table 1's least-squares optimum has beta at 0: the
    # backbone alone, no loop (RMSE 0.18 cm against the hysteretic Hill fit's 0.14 cm).
    loopless = fit_bouc_wen(*loop, backbone='sigmoid')
    assert loopless.model.loop_width_m < 1e-4
    assert any('without hysteresis' in text for text in loopless.fit.warnings)
    for fitted in (linear_fit, fit_bouc_wen(*loop, backbone='hill')):
        assert fitted.model.loop_width_m > 0.003   # Table 1's loop: up to 5.9 mm wide
        assert not any('without hysteresis' in text for text in fitted.fit.warnings)


def test_preconditioned_loop_is_steady():
    model = BoucWenModel(LinearBackbone(0.30, -0.06, 5e5), 0.01, 5.0, 0.5, 1.5, 5e5)
    _, z_up, z_down = model.steady_loop()
    # Preconditioned: another cycle starts where this one ended (the loop closes).
    assert z_up[0] == pytest.approx(z_down[0], abs=1e-4 * np.ptp(z_up))
    assert z_up[-1] == z_down[-1]  # the reversal at p_ref
    assert np.all(np.diff(z_up) > 0) and np.all(np.diff(z_down) > 0)
    assert np.all(z_down[1:-1] < z_up[1:-1])  # a loop with area: z lags the pressure


def test_minor_loops_drift():
    backbone = HillBranch(0.3069, 0.0792, 203_000.0, 2.08)
    model = BoucWenModel(backbone, 0.014, 10.4, 1.0, 3.0, 5e5)
    lengths = minor_loop_drift(model, 200_000.0, 350_000.0, cycles=30)
    assert lengths.size == 31
    drift_cm = float(units.m_to_cm(lengths[-1] - lengths[0]))
    assert abs(drift_cm) > 0.1  # no return-point memory: L at 200 kPa moves
    assert abs(lengths[-1] - lengths[-2]) < abs(lengths[1] - lengths[0])  # and settles


def test_simulate_path_matches_the_steady_loop():
    model = BoucWenModel(LinearBackbone(0.30, -0.06, 5e5), 0.01, 5.0, 0.5, 1.5, 5e5)
    rise = np.linspace(0, 5e5, 101)
    path = np.concatenate([rise, rise[::-1]] * 3)
    simulated = model.simulate_path(path)[-rise.size:][::-1]
    assert simulated == pytest.approx(model.loop_lengths(rise, np.zeros(rise.size, bool)),
                                      abs=1e-9)
