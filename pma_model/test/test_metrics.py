"""Metrics: the paper's Table 2 recomputed from Table 1, and the formulas on their own."""

import math

import numpy as np
import pytest
from scipy import stats

from pma_model import units
from pma_model.metrics import fit_metrics
from pma_model.params import default_params, paper_table1

pytestmark = pytest.mark.in_process


@pytest.fixture(scope='module')
def table():
    return paper_table1()


def branch_metrics_cm(table, direction, form='sigmoid', k=2):
    branch = getattr(default_params(), direction).of_form(form)
    measured = units.m_to_cm(getattr(table, f'{direction}_length_m'))
    predicted = units.m_to_cm(branch.length(table.pressure_pa))
    return fit_metrics(measured, predicted, k=k)


def test_increasing_sigmoid_reproduces_paper_table2(table):
    result = branch_metrics_cm(table, 'increasing')
    assert result.n == 11
    assert round(result.mae, 4) == 0.1664
    assert round(result.r2, 4) == 0.9912
    assert round(result.pearson_r, 4) == 0.9960
    assert round(result.aic, 3) == -31.563
    assert round(result.bic, 3) == -30.767
    assert round(result.mse, 4) == 0.0394


def test_paper_printed_mse_is_four_times_the_true_value(table):
    result = branch_metrics_cm(table, 'increasing')
    assert 0.1578 / result.mse == pytest.approx(4.0, rel=1e-3)


def test_decreasing_fit_and_hill_rank_as_documented(table):
    sigmoid = branch_metrics_cm(table, 'decreasing')
    assert sigmoid.mse == pytest.approx(0.0423, abs=5e-5)
    assert sigmoid.r2 == pytest.approx(0.9903, abs=5e-5)
    for direction, expected_mse in (('increasing', 0.0169), ('decreasing', 0.0162)):
        hill = branch_metrics_cm(table, direction, form='hill', k=4)
        assert hill.mse == pytest.approx(expected_mse, abs=1e-4)
        assert hill.mse < 0.5 * branch_metrics_cm(table, direction).mse


def test_formulas_against_independent_computation():
    rng = np.random.default_rng(7)
    measured = rng.normal(25.0, 2.0, 40)
    predicted = measured + rng.normal(0.0, 0.3, 40)
    result = fit_metrics(measured, predicted, k=3, stroke=6.0)
    errors = predicted - measured
    sse = float(np.sum(errors ** 2))
    assert result.mse == pytest.approx(sse / 40)
    assert result.rmse == pytest.approx(math.sqrt(sse / 40))
    assert result.mae == pytest.approx(np.mean(np.abs(errors)))
    assert result.max_abs_error == pytest.approx(np.max(np.abs(errors)))
    assert result.r2 == pytest.approx(1 - sse / np.sum((measured - measured.mean()) ** 2))
    assert result.pearson_r == pytest.approx(stats.pearsonr(measured, predicted)[0])
    assert result.rmse_pct_stroke == pytest.approx(100 * result.rmse / 6.0)
    assert result.max_pct_stroke == pytest.approx(100 * result.max_abs_error / 6.0)
    assert result.aic == pytest.approx(40 * math.log(sse / 40) + 6)
    assert result.aicc == pytest.approx(result.aic + 24 / 36)
    assert result.bic == pytest.approx(40 * math.log(sse / 40) + 3 * math.log(40))


def test_unit_agnostic_scaling():
    measured = np.array([30.0, 28.0, 26.5, 25.0, 24.2])
    predicted = np.array([29.9, 28.2, 26.4, 25.1, 24.3])
    in_cm = fit_metrics(measured, predicted, k=2)
    in_m = fit_metrics(measured / 100, predicted / 100, k=2)
    assert in_m.mae == pytest.approx(in_cm.mae / 100)
    assert in_m.r2 == pytest.approx(in_cm.r2)
    assert in_m.rmse_pct_stroke == pytest.approx(in_cm.rmse_pct_stroke)


def test_nan_pairs_are_dropped_and_counted_out():
    result = fit_metrics([1.0, 2.0, np.nan, 4.0], [1.1, np.nan, 3.0, 3.9], k=1)
    assert result.n == 2
    assert result.mae == pytest.approx(0.1)
    assert math.isnan(result.aicc)  # n - k - 1 = 0


def test_bad_input_is_refused_with_a_message():
    with pytest.raises(ValueError, match='differ in size'):
        fit_metrics([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match='at least 2'):
        fit_metrics([1.0, np.nan], [1.0, 2.0])
