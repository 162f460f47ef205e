"""Branch forms: the paper's formula, the closed-form inverses, range checks, fitting."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_model import units
from pma_model.branches import (
    DEFAULT_MAX_GAUGE_PRESSURE_PA,
    MAX_INVERSE_SENSITIVITY_PA_PER_M,
    HillBranch,
    SigmoidBranch,
    UnreachableLengthError,
    branch_class,
    fit_branch,
)
from pma_model.params import default_params

pytestmark = pytest.mark.in_process

PARAMS = default_params()
ALL_BRANCHES = {f'{direction}-{form}': getattr(PARAMS, direction).of_form(form)
                for direction in ('increasing', 'decreasing') for form in ('sigmoid', 'hill')}


def test_units_round_trip_and_b_conversion():
    assert units.kpa_to_pa(500) == 500_000.0
    assert units.cm_to_m(30.06) == pytest.approx(0.3006)
    assert units.m_to_cm(units.cm_to_m(24.2)) == pytest.approx(24.2)
    assert units.pa_to_kpa(units.kpa_to_pa(123.4)) == pytest.approx(123.4)
    assert units.per_kpa_to_per_pa(0.011333) == pytest.approx(1.1333e-5)
    assert units.per_pa_to_per_kpa(1.1333e-5) == pytest.approx(0.011333)
    # b*P is dimensionless: the same in both unit systems.
    assert units.per_kpa_to_per_pa(0.011333) * units.kpa_to_pa(250) == pytest.approx(
        0.011333 * 250)


def test_sigmoid_matches_the_paper_formula_in_paper_units():
    branch = PARAMS.increasing.sigmoid
    for p_kpa in (0.0, 50.0, 137.0, 300.0, 500.0):
        paper_cm = 30.06 - 0.19073 * 30.06 / (1 + math.exp(-0.011333 * p_kpa)) ** 6.214
        assert units.m_to_cm(branch.length(units.kpa_to_pa(p_kpa))) == pytest.approx(
            paper_cm, abs=1e-12)


def test_hill_matches_its_formula():
    branch = HillBranch(0.30, 0.06, 200_000.0, 2.5)
    p = 123_000.0
    assert branch.length(p) == pytest.approx(0.30 - 0.06 * p ** 2.5 / (p ** 2.5 + 2e5 ** 2.5))
    assert branch.length(0.0) == 0.30


@pytest.mark.parametrize('name', sorted(ALL_BRANCHES))
def test_length_is_vectorised_and_monotone(name):
    branch = ALL_BRANCHES[name]
    pressures = np.linspace(0.0, 600_000.0, 601)
    lengths = branch.length(pressures)
    assert lengths.shape == pressures.shape
    assert np.all(np.diff(lengths) < 0)
    assert isinstance(branch.length(1e5), float)
    assert branch.length_range() == (branch.length(DEFAULT_MAX_GAUGE_PRESSURE_PA),
                                     branch.length(0.0))


@pytest.mark.parametrize('name', sorted(ALL_BRANCHES))
@settings(max_examples=150, deadline=None)
@given(p_pa=st.floats(allow_nan=True, allow_infinity=True))
def test_one_sample_and_an_array_give_the_same_length(name, p_pa):
    # A float takes math's path (online steps, the inverse's searches), an array numpy's.
    assert_one_as_an_array(ALL_BRANCHES[name].length, p_pa, rel=1e-14, abs=1e-15)


def assert_one_as_an_array(function, value: float, **tolerance) -> None:
    """`function` of one float is a float, and what it gives for the one-element array."""
    with np.errstate(invalid='ignore', over='ignore'):
        from_array = function(np.array([value]))[0]
    one = function(value)
    assert isinstance(one, float)
    if math.isnan(from_array):
        assert math.isnan(one)
    else:
        assert one == pytest.approx(from_array, **tolerance)


@pytest.mark.parametrize('name', sorted(ALL_BRANCHES))
@settings(max_examples=150, deadline=None)
@given(p_kpa=st.floats(min_value=20.0, max_value=480.0))
def test_inverse_of_forward_within_one_pascal(name, p_kpa):
    branch = ALL_BRANCHES[name]
    p_pa = float(units.kpa_to_pa(p_kpa))
    assert abs(branch.pressure(branch.length(p_pa)) - p_pa) < 1.0


@pytest.mark.parametrize('name', sorted(ALL_BRANCHES))
def test_inverse_vectorised_matches_scalar(name):
    branch = ALL_BRANCHES[name]
    pressures = np.linspace(20_000.0, 480_000.0, 47)
    recovered = branch.pressure(branch.length(pressures))
    assert recovered.shape == pressures.shape
    assert np.max(np.abs(recovered - pressures)) < 1.0
    # One length takes math's path, an array numpy's: they may differ in the last bit.
    assert recovered[5] == pytest.approx(branch.pressure(branch.length(pressures[5])),
                                         rel=1e-13)


@pytest.mark.parametrize('name', sorted(ALL_BRANCHES))
@settings(max_examples=200, deadline=None)
@given(length_m=st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(min_value=0.2, max_value=0.32)))
def test_one_length_and_an_array_give_the_same_inverse(name, length_m):
    # A float takes math's path (the controller's inverse every sample), an array numpy's.
    assert_one_as_an_array(ALL_BRANCHES[name].inverse_unchecked, length_m, rel=1e-12,
                           abs=1e-9)


def test_inverse_refuses_lengths_outside_the_reachable_range():
    branch = PARAMS.increasing.sigmoid
    low, high = branch.length_range()
    # The rest length measured at 0 kPa (30.06 cm) is above what the sigmoid gives at 0 Pa.
    with pytest.raises(UnreachableLengthError, match=r'\[0\.24\d*, 0\.29\d*\] m') as info:
        branch.pressure(0.3006)
    assert (info.value.min_length_m, info.value.max_length_m) == pytest.approx((low, high))
    # 24.20 cm, measured at 500 kPa, needs more than 500 kPa on this branch: unreachable.
    with pytest.raises(UnreachableLengthError):
        branch.pressure(0.2420)
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(UnreachableLengthError):
            branch.pressure(bad)
    with pytest.raises(UnreachableLengthError):
        branch.pressure(np.array([0.26, 0.2420]))  # one bad element refuses the array


def test_a_length_needing_more_than_the_maximum_pressure_is_unreachable_not_bigger():
    branch = PARAMS.decreasing.sigmoid
    needs_600_kpa = branch.length(600_000.0)
    with pytest.raises(UnreachableLengthError, match=r'0\.\.500000 Pa'):
        branch.pressure(needs_600_kpa)
    assert branch.pressure(needs_600_kpa, p_max_pa=700_000.0) == pytest.approx(600_000.0,
                                                                              abs=1e-3)
    assert branch.pressure(branch.length(500_000.0)) == pytest.approx(500_000.0, abs=1e-3)


@pytest.mark.parametrize('direction', ['increasing', 'decreasing'])
@pytest.mark.parametrize('form', ['sigmoid', 'hill'])
def test_ill_conditioned_end_is_refused_only_beyond_the_default_range(direction, form):
    branch = getattr(PARAMS, direction).of_form(form)
    limit = branch.invertible_pressure_limit(1e8)
    assert branch.invertible_pressure_limit(500_000.0) == 500_000.0
    # at the limit 0.1 mm of length moves the answer by 100 kPa
    assert branch.slope_m_per_pa(limit) * MAX_INVERSE_SENSITIVITY_PA_PER_M == \
        pytest.approx(1.0, rel=1e-3)
    assert branch.slope_m_per_pa(0.999 * limit) > branch.slope_m_per_pa(limit)
    beyond = branch.length(1.2 * limit)
    with pytest.raises(UnreachableLengthError, match='100 kPa'):
        branch.pressure(beyond, p_max_pa=1e8)
    if form == 'sigmoid':
        assert 600e3 < limit < 900e3


def test_ends_of_the_range_invert_exactly():
    hill = PARAMS.increasing.hill
    assert hill.pressure(hill.length(0.0)) == 0.0  # rest length: the least pressure, 0 Pa
    sigmoid = PARAMS.increasing.sigmoid
    assert sigmoid.pressure(sigmoid.length(0.0)) == pytest.approx(0.0, abs=1e-6)


def test_extreme_pressures_stay_finite():
    for branch in ALL_BRANCHES.values():
        lengths = branch.length(np.array([-1e9, -1.0, 0.0, 1e7, 1e12, 1e300, np.inf]))
        assert np.all(np.isfinite(lengths))
        assert lengths[0] == lengths[1] == lengths[2]  # no data below ambient: held at rest
        assert lengths[-1] == pytest.approx(branch.saturation_length_m())
        assert lengths[-3] == pytest.approx(branch.saturation_length_m())
        assert branch.length(1e300) == branch.length(math.inf) == lengths[-1]


def test_parameter_vector_interface_round_trips():
    for branch in ALL_BRANCHES.values():
        cls = type(branch)
        assert cls.from_vector(branch.vector()) == branch
        assert cls.from_dict(branch.to_dict()) == branch
        lower, upper = cls.bounds()
        assert len(lower) == len(upper) == len(cls.names()) == len(branch.vector())
        assert np.all(lower <= branch.vector()) and np.all(branch.vector() <= upper)
    assert SigmoidBranch.names() == ('l0_m', 'a', 'b_per_pa', 'c')
    assert HillBranch.names() == ('l0_m', 'dl_m', 'k_pa', 'n')
    assert branch_class('hill') is HillBranch


def test_invalid_parameters_name_the_field():
    with pytest.raises(ValueError, match=r'^a must be in'):
        SigmoidBranch(0.3, 1.2, 1e-5, 6.0)
    with pytest.raises(ValueError, match=r'^b_per_pa'):
        SigmoidBranch(0.3, 0.2, math.nan, 6.0)
    with pytest.raises(ValueError, match=r'^dl_m'):
        HillBranch(0.3, 0.4, 2e5, 2.0)
    with pytest.raises(ValueError, match='unknown'):
        SigmoidBranch.from_dict({'l0_m': 0.3, 'a': 0.2, 'b_per_pa': 1e-5, 'c': 6.0, 'k': 1})
    with pytest.raises(ValueError, match='4 parameters'):
        SigmoidBranch.from_vector([0.3, 0.2])
    with pytest.raises(ValueError, match='branch form must be one of'):
        branch_class('cubic')


def test_fit_recovers_known_parameters_from_clean_data():
    pressures = np.linspace(0.0, 500_000.0, 21)
    truth = SigmoidBranch(0.31, 0.18, 1.25e-5, 6.214)
    fitted = fit_branch(SigmoidBranch(0.31, 0.25, 0.8e-5, 6.214), pressures,
                        truth.length(pressures), fixed=('l0_m', 'c'))
    assert fitted.a == pytest.approx(truth.a, rel=1e-6)
    assert fitted.b_per_pa == pytest.approx(truth.b_per_pa, rel=1e-6)
    hill_truth = HillBranch(0.302, 0.064, 180_000.0, 2.3)
    with_nan = np.append(hill_truth.length(pressures), math.nan)
    hill = fit_branch(HillBranch(0.30, 0.05, 250_000.0, 1.5), np.append(pressures, 1e5),
                      with_nan)
    assert hill.vector() == pytest.approx(hill_truth.vector(), rel=1e-5)
    with pytest.raises(ValueError, match='unknown'):
        fit_branch(truth, pressures, truth.length(pressures), fixed=('k_pa',))
