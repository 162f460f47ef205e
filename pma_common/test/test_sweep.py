"""The Sweep profiles' plans and their validation."""

import itertools
import math
import tracemalloc
from dataclasses import MISSING, fields

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pma_common.sweep import (
    MAX_RATE_PA_S,
    STREAM_RATE_HZ,
    StreamPlan,
    SweepError,
    SweepGoal,
    _is_default,
    forc_turning_points,
    plan_forc,
    plan_goal,
    plan_points,
    plan_ramp,
    plan_sine,
    plan_sweep,
    read_profile_csv,
    reversal_examples,
    staircase,
    staircase_length,
)

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


@pytest.mark.parametrize('top_pa', [500_000.0, 300_000.0, 120_000.0, 333_333.3])
def test_the_refusals_examples_are_plans_for_that_top(top_pa):
    with pytest.raises(SweepError, match='alternate') as refused:
        plan_sweep(top_pa, 10_000.0, 0.0, 1, [0.9 * top_pa], ceiling_pa=CEILING)
    before, after = reversal_examples(top_pa)
    assert f'e.g. {before} before the top, or {after} after it' in str(refused.value)
    for reversals in (before, after):
        plan = plan_sweep(top_pa, 10_000.0, 0.0, 1, reversals, ceiling_pa=CEILING)
        assert max(plan.setpoints_pa) == top_pa


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


# -- every profile through plan_goal -------------------------------------------------------


def test_a_goal_without_a_profile_is_the_staircase_it_always_was():
    plan = plan_goal(SweepGoal(200_000.0, 100_000.0, 0.5, 1), ceiling_pa=CEILING)
    assert plan == plan_sweep(200_000.0, 100_000.0, 0.5, 1, ceiling_pa=CEILING)
    assert plan_goal(SweepGoal(200_000.0, 100_000.0, 0.5, 1, profile='staircase'),
                     ceiling_pa=CEILING) == plan


def test_the_goal_mirrors_the_action_field_by_field():
    from pma_interfaces.action import Sweep
    assert {f.name for f in fields(SweepGoal)} == set(Sweep.Goal.get_fields_and_field_types())
    # Defaults of the new fields are the action's: an old goal keeps its meaning.
    defaults = Sweep.Goal()
    for f in fields(SweepGoal):
        if f.name not in ('max_gauge_pressure_pa', 'step_pa', 'hold_s', 'cycles'):
            default = f.default_factory() if f.default is MISSING else f.default
            assert _is_default(getattr(defaults, f.name)) and _is_default(default), f.name


def test_rest_is_held_at_0_pa_between_cycles_only():
    plan = plan_sweep(100_000.0, 50_000.0, 1.0, 3, ceiling_pa=CEILING, rest_s=30.0)
    one = [50_000.0, 100_000.0, 50_000.0, 0.0]
    assert list(plan.setpoints_pa) == [0.0, *one * 3]
    assert [plan.hold_at(i) for i in range(plan.step_count)] == \
        [1.0, 1.0, 1.0, 1.0, 31.0, 1.0, 1.0, 1.0, 31.0, 1.0, 1.0, 1.0, 1.0]
    assert plan.hold_time_s == pytest.approx(13 + 60)


def test_ascending_forcs_turn_on_the_falling_major_branch_and_rise_back_to_the_top():
    assert forc_turning_points(400e3, 4, 'ascending') == [
        0.0, 400e3, 300e3, 400e3, 200e3, 400e3, 100e3, 400e3, 0.0, 400e3, 0.0]
    assert forc_turning_points(400e3, 4, 'descending') == [
        0.0, 100e3, 0.0, 200e3, 0.0, 300e3, 0.0, 400e3, 0.0]
    assert forc_turning_points(400e3, 2, 'both') == [
        0.0, 400e3, 200e3, 400e3, 0.0, 400e3, 0.0, 200e3, 0.0, 400e3, 0.0]


def test_a_forc_goal_is_a_staircase_through_its_reversals():
    plan = plan_goal(SweepGoal(200e3, 100e3, 0.5, 1, profile='forc', forc_count=2),
                     ceiling_pa=CEILING)
    assert plan.profile == 'forc' and plan.hold_s == 0.5
    assert list(plan.setpoints_pa) == [0.0, 100e3, 200e3,      # up the major branch
                                       100e3, 200e3,            # curve from 100 kPa
                                       100e3, 0.0, 100e3, 200e3,  # curve from 0 (major loop)
                                       100e3, 0.0]
    descending = plan_goal(SweepGoal(200e3, 100e3, 0.5, 2, profile='forc', forc_count=2,
                                     forc_family='descending', rest_s=5.0), ceiling_pa=CEILING)
    assert list(descending.setpoints_pa) == [0.0, *[100e3, 0.0, 100e3, 200e3, 100e3, 0.0] * 2]
    assert descending.hold_at(6) == 5.5 and descending.hold_at(12) == 0.5


def test_a_ramp_joins_the_turning_points_at_its_rate_and_holds_at_each():
    plan = plan_goal(SweepGoal(400e3, hold_s=1.0, cycles=2, profile='ramp',
                               ramp_rate_pa_s=100e3, reversal_pressures_pa=[200e3, 100e3],
                               rest_s=3.0), ceiling_pa=CEILING)
    assert isinstance(plan, StreamPlan) and plan.profile == 'ramp'
    assert plan.knots_time_s == (0.0, 2.0, 3.0, 4.0, 5.0, 8.0, 9.0, 13.0)
    assert plan.knots_pressure_pa == (0.0, 200e3, 200e3, 100e3, 100e3, 400e3, 400e3, 0.0)
    assert (plan.cycle_s, plan.duration_s, plan.peak_pa) == (13.0, 29.0, 400e3)
    assert plan.setpoint_count == 29 * 20 + 1
    assert [plan.pressure_at(t) for t in (0.5, 2.5, 3.5, 6.5, 11.0, 13.5, 16.0, 17.0, 29.0)] \
        == [50e3, 200e3, 150e3, 250e3, 200e3, 0.0, 0.0, 100e3, 0.0]


def test_a_sine_runs_whole_periods_from_its_trough():
    plan = plan_goal(SweepGoal(profile='sine', sine_amplitude_pa=100e3, sine_offset_pa=200e3,
                               sine_frequency_hz=0.5, cycles=3), ceiling_pa=CEILING)
    assert plan.duration_s == 6.0 and plan.peak_pa == 300e3
    assert plan.setpoint_count == 121
    values = [plan.pressure_at(plan.time_of(i)) for i in range(plan.setpoint_count)]
    assert values[0] == values[-1] == pytest.approx(100e3)
    assert max(values) == pytest.approx(300e3) and min(values) == pytest.approx(100e3)
    assert values[20] == pytest.approx(300e3)          # the peak, half a period in
    assert plan.pressure_at(0.5) == pytest.approx(200e3)


def test_csv_points_are_joined_by_straight_lines_from_the_first_time():
    plan = plan_goal(SweepGoal(profile='csv', profile_time_s=[10.0, 12.0, 13.0],
                               profile_pressure_pa=[0.0, 200e3, 50e3], cycles=2, rest_s=1.0),
                     ceiling_pa=CEILING)
    assert plan.knots_time_s == (0.0, 2.0, 3.0) and plan.duration_s == 7.0
    assert [plan.pressure_at(t) for t in (1.0, 2.5, 3.0, 3.5, 4.0, 5.0, 7.0)] == \
        [100e3, 125e3, 50e3, 0.0, 0.0, 100e3, 50e3]


@given(top=st.floats(1_000.0, CEILING), rate=st.floats(100.0, MAX_RATE_PA_S),
       hold=st.floats(0.0, 5.0), cycles=st.integers(1, 3), rest=st.floats(0.0, 5.0))
def test_a_streamed_ramp_moves_at_most_its_rate_per_setpoint_and_never_leaves_0_to_top(
        top, rate, hold, cycles, rest):
    plan = plan_ramp(top, rate, hold, cycles, ceiling_pa=CEILING, rest_s=rest)
    if plan.setpoint_count > 20_000:
        return
    values = [plan.pressure_at(plan.time_of(i)) for i in range(plan.setpoint_count)]
    assert all(-1e-6 <= v <= top * (1 + 1e-12) for v in values)
    assert values[0] == 0.0 and values[-1] == pytest.approx(0.0, abs=1e-6)
    jumps = [abs(b - a) for a, b in itertools.pairwise(values)]
    # At most one rate-step per setpoint, except the steps into and out of a rest at 0 Pa.
    assert all(j <= rate / STREAM_RATE_HZ * (1 + 1e-9) + 1e-6 for j in jumps)


@given(amplitude=st.floats(1_000.0, 250_000.0), frequency=st.floats(0.001, 2.0),
       cycles=st.integers(1, 3))
def test_any_accepted_sine_stays_within_0_and_the_ceiling(amplitude, frequency, cycles):
    try:
        plan = plan_sine(amplitude, CEILING - amplitude, frequency, cycles, ceiling_pa=CEILING)
    except SweepError as error:
        assert 'faster than' in str(error)
        assert 2 * math.pi * frequency * amplitude > MAX_RATE_PA_S
        return
    times = [plan.duration_s * k / 997 for k in range(998)]
    assert all(0 <= plan.pressure_at(t) <= CEILING * (1 + 1e-12) for t in times)


FORC = {'profile': 'forc', 'max_gauge_pressure_pa': 400e3, 'step_pa': 50e3, 'forc_count': 4}
RAMP = {'profile': 'ramp', 'max_gauge_pressure_pa': 400e3, 'ramp_rate_pa_s': 50e3}
SINE = {'profile': 'sine', 'sine_amplitude_pa': 100e3, 'sine_offset_pa': 200e3,
        'sine_frequency_hz': 0.1}
POINTS = {'profile': 'csv', 'profile_time_s': [0.0, 1.0, 2.0],
          'profile_pressure_pa': [0.0, 100e3, 0.0]}


@pytest.mark.parametrize(('goal', 'words'), [
    ({'profile': 'triangle'}, "profile 'triangle' is not one of staircase, forc, ramp"),
    ({'max_gauge_pressure_pa': 100e3, 'step_pa': 50e3, 'sine_amplitude_pa': 5e4},
     "sine_amplitude_pa is set, but profile 'staircase' does not use it (it is for 'sine'"),
    ({**SINE, 'step_pa': 50e3}, "step_pa is set, but profile 'sine' does not use it"),
    ({**RAMP, 'forc_count': 3}, "forc_count is set, but profile 'ramp'"),
    ({**FORC, 'reversal_pressures_pa': [100e3, 50e3]}, 'reversal_pressures_pa is set'),
    ({**POINTS, 'ramp_rate_pa_s': math.nan}, 'ramp_rate_pa_s is set'),
    ({**FORC, 'rest_s': -1.0}, 'rest_s must be within 0..86400 s'),
    ({**FORC, 'rest_s': math.inf}, 'rest_s must be a finite number'),
    ({**FORC, 'cycles': 0}, 'cycles must be >= 1'),
    # FORC
    ({**FORC, 'forc_count': 0}, 'forc_count must be >= 1'),
    ({**FORC, 'forc_family': 'upward'}, "forc_family 'upward' is not one of ascending"),
    ({**FORC, 'max_gauge_pressure_pa': 600e3}, 'above the driver ceiling 500000 Pa'),
    ({**FORC, 'step_pa': 0.0}, 'step_pa must be > 0'),
    ({**FORC, 'forc_count': 2**32 - 1}, 'forc_count 4294967295 makes more than 10000 steps'),
    ({**FORC, 'forc_count': 2000}, 'steps (more than 10000): is step_pa 50000 Pa too small?'),
    # ramp
    ({**RAMP, 'ramp_rate_pa_s': 0.0}, 'ramp_rate_pa_s must be > 0 Pa/s'),
    ({**RAMP, 'ramp_rate_pa_s': -5.0}, 'ramp_rate_pa_s must be > 0 Pa/s'),
    ({**RAMP, 'ramp_rate_pa_s': math.inf}, 'ramp_rate_pa_s must be a finite number'),
    ({**RAMP, 'ramp_rate_pa_s': 2e6}, 'ramp_rate_pa_s 2000000 Pa/s is faster than 1000000'),
    ({**RAMP, 'ramp_rate_pa_s': 1.0}, 'the ramp lasts 800000 s (more than 86400 s)'),
    ({**RAMP, 'cycles': 2**32 - 1}, 'the ramp lasts'),
    ({**RAMP, 'max_gauge_pressure_pa': 500_001.0}, 'above the driver ceiling'),
    ({**RAMP, 'reversal_pressures_pa': [100e3, 200e3]}, 'alternate'),
    ({**RAMP, 'hold_s': -1.0}, 'hold_s must be >= 0'),
    # sine
    ({**SINE, 'sine_amplitude_pa': 0.0}, 'sine_amplitude_pa must be > 0'),
    ({**SINE, 'sine_offset_pa': 50e3}, 'the sine goes below 0 Pa gauge'),
    ({**SINE, 'sine_offset_pa': 450e3}, 'the sine peaks at 550000 Pa, above the driver ceiling'),
    ({**SINE, 'max_gauge_pressure_pa': 250e3}, 'the sine peaks at 300000 Pa, above '
                                               'max_gauge_pressure_pa 250000 Pa'),
    ({**SINE, 'max_gauge_pressure_pa': 600e3}, 'above the driver ceiling'),
    ({**SINE, 'max_gauge_pressure_pa': -1.0}, 'max_gauge_pressure_pa must be > 0'),
    ({**SINE, 'sine_frequency_hz': 0.0}, 'sine_frequency_hz must be within 0..2 Hz'),
    ({**SINE, 'sine_frequency_hz': 3.0}, 'sine_frequency_hz must be within 0..2 Hz'),
    ({**SINE, 'sine_frequency_hz': math.nan}, 'sine_frequency_hz must be a finite number'),
    ({**SINE, 'sine_frequency_hz': 1.9}, "the sine's steepest slope"),
    ({**SINE, 'sine_frequency_hz': 0.001, 'cycles': 100}, 'the sine lasts 100000 s'),
    ({**SINE, 'cycles': 2**32 - 1}, 'the sine lasts'),
    # csv
    ({**POINTS, 'profile_time_s': [0.0, 1.0]}, 'profile_time_s has 2 points and '
                                               'profile_pressure_pa 3'),
    ({**POINTS, 'profile_time_s': [0.0], 'profile_pressure_pa': [0.0]}, 'at least 2 points'),
    ({**POINTS, 'profile_time_s': [0.0, 1.0, 1.0]}, 'point 2 is at 1 s after 1 s'),
    ({**POINTS, 'profile_time_s': [0.0, 2.0, 1.0]}, 'must increase strictly'),
    ({**POINTS, 'profile_time_s': [0.0, math.nan, 2.0]}, 'profile_time_s[1] must be a finite'),
    ({**POINTS, 'profile_pressure_pa': [0.0, math.inf, 0.0]}, 'profile_pressure_pa[1] must be'),
    ({**POINTS, 'profile_pressure_pa': [0.0, 600e3, 0.0]},
     'profile_pressure_pa[1] = 600000 Pa must be within 0..500000 Pa (the driver ceiling'),
    ({**POINTS, 'profile_pressure_pa': [0.0, -1.0, 0.0]}, 'must be within 0..500000'),
    ({**POINTS, 'max_gauge_pressure_pa': 50e3}, 'within 0..50000 Pa (max_gauge_pressure_pa)'),
    ({**POINTS, 'profile_time_s': [0.0, 0.01, 2.0]}, 'between points 0 and 1: its slope '
                                                     '10000000 Pa/s is faster'),
    ({**POINTS, 'profile_time_s': [0.0, 1.0, 90_000.0]}, 'the csv profile lasts 90000 s'),
])
def test_bad_profile_goals_are_refused_with_the_reason(goal, words):
    with pytest.raises(SweepError) as refused:
        plan_goal(SweepGoal(**{'cycles': 1, **goal}), ceiling_pa=CEILING)
    assert words in str(refused.value)


def test_huge_profiles_are_refused_by_arithmetic_before_anything_is_built():
    huge = range(10**9)            # a sequence of a billion points that takes no memory
    tracemalloc.start()
    try:
        with pytest.raises(SweepError, match='1000000000 points'):
            plan_points(huge, huge, 1, ceiling_pa=CEILING)
        with pytest.raises(SweepError, match='lasts'):
            plan_sine(1e3, 1e3, 1e-3, 2**32 - 1, ceiling_pa=CEILING)
        with pytest.raises(SweepError, match='more than 10000'):
            plan_forc(500e3, 1e3, 1.0, 2**32 - 1, forc_count=10_000, ceiling_pa=CEILING)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 100_000, f'{peak} bytes allocated to refuse the plan'


def test_a_profile_csv_is_read_by_its_column_names(tmp_path):
    path = tmp_path / 'profile.csv'
    path.write_text('time_s,length_m,gauge_pressure_pa\n0,0.3,0\n1.5,0.29,120000\n\n3,0.3,0\n')
    assert read_profile_csv(path) == ([0.0, 1.5, 3.0], [0.0, 120e3, 0.0])


@pytest.mark.parametrize(('text', 'words'), [
    ('', 'empty'),
    ('t,p\n0,0\n', 'the header t,p lacks time_s and gauge_pressure_pa'),
    ('time_s,gauge_pressure_pa\n0,0\n1,lots\n', 'line 3: not two numbers'),
    ('time_s,gauge_pressure_pa\n0\n', 'line 2: not two numbers'),
])
def test_a_bad_profile_csv_says_where(tmp_path, text, words):
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(SweepError, match=words):
        read_profile_csv(path)


def test_a_missing_profile_csv_is_a_sweep_error(tmp_path):
    with pytest.raises(SweepError, match='cannot read the profile'):
        read_profile_csv(tmp_path / 'absent.csv')
