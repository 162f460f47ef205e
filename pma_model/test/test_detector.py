"""Branch detector: deadband reversals, noise immunity, online == array form."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_model.detector import (
    BRANCH_DECREASING,
    BRANCH_INCREASING,
    BranchDetector,
    detect_branches,
)

pytestmark = pytest.mark.in_process


def online(pressures, deadband_pa):
    detector = BranchDetector(deadband_pa)
    return np.array([detector.update(p) for p in pressures], dtype=np.uint8)


def test_reversal_counts_only_after_the_deadband():
    detector = BranchDetector(20_000.0)
    for p in (0.0, 100e3, 300e3):
        assert detector.update(p) == BRANCH_INCREASING
    assert detector.update(281e3) == BRANCH_INCREASING  # moved 19 kPa back: not yet
    assert detector.update(290e3) == BRANCH_INCREASING
    assert detector.update(280e3) == BRANCH_DECREASING  # 20 kPa below the 300 kPa peak
    assert detector.update(295e3) == BRANCH_DECREASING  # 15 kPa above the 280 kPa low
    assert detector.update(300e3) == BRANCH_INCREASING


def test_plus_minus_10_kpa_noise_does_not_chatter_with_the_default_deadband():
    rng = np.random.default_rng(3)
    hold = 250e3 + rng.uniform(-9_990.0, 9_990.0, 20_000)  # +/-2 % of 500 kPa
    ramp_up = np.linspace(0.0, 250e3, 200)
    labels = detect_branches(np.concatenate((ramp_up, hold)))
    assert np.all(labels == BRANCH_INCREASING)
    ramp_down = np.linspace(250e3, 100e3, 200) + rng.uniform(-9_990.0, 9_990.0, 200)
    labels = detect_branches(np.concatenate((ramp_up, ramp_down, hold[:5000] - 150e3)))
    assert np.count_nonzero(np.diff(labels.astype(int)) != 0) == 1


def test_an_hour_of_gaussian_sensor_noise_does_not_chatter_with_the_default_deadband():
    # One hour at 100 Hz on a 250 kPa hold, noise like the simulated rig's (sigma 2.5 kPa,
    # then 10-bit steps of 611 Pa): the tails reach further than +/-10 kPa.
    rng = np.random.default_rng(11)
    hold = 611.0 * np.round((250e3 + rng.normal(0.0, 2_500.0, 360_000)) / 611.0)
    ramp_up = np.linspace(0.0, 250e3, 200)
    pressures = np.concatenate((ramp_up, hold))
    assert np.all(detect_branches(pressures) == BRANCH_INCREASING)
    flips_at_20_kpa = np.count_nonzero(np.diff(detect_branches(pressures, 20_000.0)
                                               .astype(int)))
    assert flips_at_20_kpa > 0, 'the old 20 kPa default would chatter here'


@settings(max_examples=60, deadline=None)
@given(deadband=st.floats(1_000.0, 50_000.0), seed=st.integers(0, 2 ** 32 - 1))
def test_noise_narrower_than_the_deadband_never_flips(deadband, seed):
    rng = np.random.default_rng(seed)
    noise = rng.uniform(-0.499 * deadband, 0.499 * deadband, 2_000)
    labels = detect_branches(200e3 + noise, deadband)
    assert np.all(labels == BRANCH_INCREASING)


@settings(max_examples=200, deadline=None)
@given(steps=st.lists(st.floats(-60e3, 60e3), min_size=1, max_size=400),
       deadband=st.sampled_from([0.0, 611.0, 10_000.0, 20_000.0]),
       holes=st.lists(st.integers(0, 399), max_size=5))
def test_array_form_equals_online_form(steps, deadband, holes):
    pressures = np.cumsum(steps)
    expected = online(pressures, deadband)
    assert np.array_equal(detect_branches(pressures, deadband), expected)
    # NaN samples are skipped: they carry the branch in force, the rest is unchanged.
    with_holes = pressures.copy()
    holes = [h for h in holes if h < len(pressures)]
    with_holes[holes] = math.nan
    finite = np.isfinite(with_holes)
    labels = detect_branches(with_holes, deadband)
    assert np.array_equal(labels[finite], online(with_holes[finite], deadband))


def test_array_form_continues_from_the_online_state_in_chunks():
    rng = np.random.default_rng(11)
    pressures = np.cumsum(rng.normal(0, 8e3, 5_000))
    whole = detect_branches(pressures, 10_000.0)
    detector = BranchDetector(10_000.0)
    pieces = [detector.detect(chunk) for chunk in np.array_split(pressures, 7)]
    assert np.array_equal(np.concatenate(pieces), whole)


def test_zero_deadband_flips_on_any_strict_reversal_but_not_on_a_hold():
    labels = detect_branches([0.0, 1.0, 1.0, 0.5, 0.5, 0.7], 0.0)
    assert labels.tolist() == [1, 1, 1, 2, 2, 1]


def test_bad_input_is_refused_and_state_kept():
    detector = BranchDetector(10_000.0)
    detector.update(100e3)
    with pytest.raises(ValueError, match='finite'):
        detector.update(math.nan)
    assert detector.update(85e3) == BRANCH_DECREASING  # the 100 kPa peak is still known
    with pytest.raises(ValueError, match='deadband_pa'):
        BranchDetector(-1.0)
    with pytest.raises(ValueError, match='initial_branch'):
        BranchDetector(1.0, initial_branch=0)
    assert detect_branches([math.nan, math.nan]).tolist() == [1, 1]
