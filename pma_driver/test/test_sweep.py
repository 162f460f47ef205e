"""The Sweep staircase plan and its validation."""

import itertools
import math
import tracemalloc

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pma_driver.sweep import SweepError, plan_sweep, staircase, staircase_length

CEILING = 500_000.0


def test_plain_staircase_up_and_down():
    plan = plan_sweep(200_000.0, 100_000.0, 0.5, 1, ceiling_pa=CEILING)
    assert plan.setpoints_pa == (0.0, 100_000.0, 200_000.0, 100_000.0, 0.0)
    assert plan.step_count == 5
    assert plan.hold_time_s == pytest.approx(2.5)


def test_top_off_the_grid_is_its_own_step():
    plan = plan_sweep(250_000.0, 100_000.0, 0.0, 1, ceiling_pa=CEILING)
    assert plan.setpoints_pa == (0.0, 100_000.0, 200_000.0, 250_000.0, 200_000.0, 100_000.0, 0.0)


def test_cycles_repeat_without_doubling_zero():
    plan = plan_sweep(100_000.0, 50_000.0, 0.0, 3, ceiling_pa=CEILING)
    one = [50_000.0, 100_000.0, 50_000.0, 0.0]
    assert list(plan.setpoints_pa) == [0.0, *one * 3]


def test_reversals_make_a_minor_loop():
    plan = plan_sweep(500_000.0, 100_000.0, 1.0, 1, [300_000.0, 150_000.0], ceiling_pa=CEILING)
    assert list(plan.setpoints_pa) == [
        0.0, 100e3, 200e3, 300e3,            # up to the first reversal
        200e3, 150e3,                         # down to the second
        200e3, 300e3, 400e3, 500e3,           # on up to max
        400e3, 300e3, 200e3, 100e3, 0.0]      # and back down


def test_listing_max_puts_later_reversals_on_the_falling_branch():
    plan = plan_sweep(500_000.0, 100_000.0, 1.0, 1, [500_000.0, 100_000.0, 250_000.0],
                      ceiling_pa=CEILING)
    assert list(plan.setpoints_pa) == [
        0.0, 100e3, 200e3, 300e3, 400e3, 500e3,   # up to max
        400e3, 300e3, 200e3, 100e3,                # down to the trough
        200e3, 250e3,                              # a minor loop up
        200e3, 100e3, 0.0]                         # and down to 0


def test_progress_runs_from_zero_to_one():
    plan = plan_sweep(200_000.0, 100_000.0, 1.0, 1, ceiling_pa=CEILING)
    assert plan.progress(0) == 0.0
    assert plan.progress(2, 0.5) == pytest.approx(2.5 / 5)
    assert plan.progress(4, 1.0) == 1.0


@pytest.mark.parametrize(('kwargs', 'words'), [
    ({'max_gauge_pressure_pa': 600_000.0}, 'above the driver ceiling'),
    ({'max_gauge_pressure_pa': -1.0}, 'max_gauge_pressure_pa must be > 0'),
    ({'max_gauge_pressure_pa': math.nan}, 'finite'),
    ({'step_pa': 0.0}, 'step_pa must be > 0'),
    ({'step_pa': -5.0}, 'step_pa must be > 0'),
    ({'step_pa': math.inf}, 'finite'),
    ({'hold_s': -1.0}, 'hold_s must be >= 0'),
    ({'hold_s': math.nan}, 'finite'),
    ({'cycles': 0}, 'cycles must be >= 1'),
    ({'reversal_pressures_pa': [300_000.0]}, 'alternate'),
    ({'reversal_pressures_pa': [400_000.0, 100_000.0]}, 'alternate'),
    ({'reversal_pressures_pa': [150_000.0, 300_000.0]}, 'alternate'),
    ({'reversal_pressures_pa': [300_000.0, math.nan]}, 'finite'),
    ({'reversal_pressures_pa': [450_000.0, 100_000.0]}, 'within'),
    ({'reversal_pressures_pa': [-1.0, 100_000.0]}, 'within'),
    ({'step_pa': 1.0}, 'too small'),
])
def test_bad_goals_are_refused_with_the_reason(kwargs, words):
    goal = {'max_gauge_pressure_pa': 400_000.0, 'step_pa': 100_000.0, 'hold_s': 1.0,
            'cycles': 1, 'reversal_pressures_pa': ()}
    goal.update(kwargs)
    with pytest.raises(SweepError, match=words):
        plan_sweep(**goal, ceiling_pa=CEILING)


@given(top=st.floats(1_000.0, CEILING), step=st.floats(500.0, 200_000.0),
       cycles=st.integers(1, 3))
def test_any_valid_plan_stays_within_bounds_and_moves_by_at_most_a_step(top, step, cycles):
    plan = plan_sweep(top, step, 0.0, cycles, ceiling_pa=CEILING)
    values = plan.setpoints_pa
    assert values[0] == 0.0 and values[-1] == 0.0
    assert max(values) == top
    assert all(0.0 <= v <= top for v in values)
    assert all(0 < abs(b - a) <= step * (1 + 1e-9) for a, b in itertools.pairwise(values))


def test_staircase_edges():
    assert staircase(0.0, 0.0, 1.0) == []
    assert staircase(100.0, 0.0, 100.0) == [0.0]
    assert staircase(50.0, 250.0, 100.0) == [100.0, 200.0, 250.0]


@pytest.mark.parametrize('step_pa', [1.0, 0.1, 0.01, 1e-9])
def test_a_plan_over_the_step_cap_is_refused_before_it_is_built(step_pa):
    # step_pa 0.1 used to build a 10-million-step staircase (450 MB, 2 s) before counting it.
    tracemalloc.start()
    try:
        with pytest.raises(SweepError, match='too small'):
            plan_sweep(500_000.0, step_pa, 1.0, 1, [300_000.0, 100_000.0], ceiling_pa=CEILING)
        with pytest.raises(SweepError, match='more than 10000'):
            plan_sweep(500_000.0, 100_000.0, 1.0, 2**32 - 1, ceiling_pa=CEILING)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 100_000, f'{peak} bytes allocated to refuse the plan'


def test_too_many_reversals_are_refused_before_planning():
    reversals = [300_000.0, 100_000.0] * 6_000
    with pytest.raises(SweepError, match='more than 10000'):
        plan_sweep(400_000.0, 100_000.0, 1.0, 1, reversals, ceiling_pa=CEILING)


@given(start=st.floats(0.0, CEILING), stop=st.floats(0.0, CEILING),
       step=st.floats(1.0, 200_000.0))
def test_the_step_count_is_the_length_of_the_staircase(start, stop, step):
    assert staircase_length(start, stop, step) == len(staircase(start, stop, step))


@pytest.mark.parametrize(('start', 'stop', 'step'), [
    (0.0, 50_000.0, 0.1), (0.0, 0.3, 0.1), (0.3, 0.0, 0.1), (0.7, 0.1, 0.2),
    (100_000.0, 100_000.0, 7.0), (1e-9, 1e-6, 1e-9 / 3)])
def test_the_step_count_matches_on_float_grid_edges(start, stop, step):
    assert staircase_length(start, stop, step) == len(staircase(start, stop, step))
