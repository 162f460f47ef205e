"""`pma sweep`'s flags become the Sweep goal the driver checks (pma_common.sweep.plan_goal);
the experiment's flags of `pma sweep` and `pma move` need a bag to go into."""

import pytest

from pma_cli.goals import checked_sweep_goal, describe, move_metadata, sweep_goal
from pma_cli.main import main, parser
from pma_cli.session import USAGE, CliError
from pma_common.sweep import SweepError, SweepGoal, plan_goal
from pma_interfaces.action import MoveToLength

pytestmark = pytest.mark.in_process

CEILING_PA = 500_000.0


def goal_of(*argv: str):
    return sweep_goal(parser().parse_args(['sweep', *argv]))


def planned(goal):
    """What the driver makes of it (the same checks its action server runs)."""
    return plan_goal(SweepGoal.of(goal), ceiling_pa=CEILING_PA)


@pytest.mark.parametrize('argv', [
    ('--max', '100kPa', '--step', '50kPa'),
    ('--profile', 'forc', '--max', '400kPa', '--step', '100kPa', '--forc-count', '3',
     '--forc-family', 'both', '--hold', '1s'),
    ('--profile', 'ramp', '--max', '300kPa', '--rate', '50kPa/s', '--reversals', '200kPa,100kPa'),
    ('--profile', 'sine', '--amplitude', '100kPa', '--offset', '150kPa', '--frequency', '0.5Hz',
     '--cycles', '2', '--rest', '1s'),
])
def test_every_profile_from_its_flags_is_a_goal_the_driver_plans(argv):
    goal = goal_of(*argv)
    plan = planned(goal)
    assert plan is not None
    assert describe(goal)


def test_a_staircase_holds_5_s_by_default_and_a_ramp_does_not_hold():
    assert goal_of('--max', '100kPa', '--step', '50kPa').hold_s == 5.0
    assert goal_of('--profile', 'ramp', '--max', '1e5', '--rate', '1e4').hold_s == 0.0


def test_the_csv_profile_sends_the_files_points(tmp_path):
    profile = tmp_path / 'p.csv'
    profile.write_text('time_s,gauge_pressure_pa\n0,0\n1.5,100000\n3,0\n')
    goal = goal_of('--profile', 'csv', '--csv', str(profile))
    assert list(goal.profile_time_s) == [0.0, 1.5, 3.0]
    assert list(goal.profile_pressure_pa) == [0.0, 100_000.0, 0.0]
    assert 'profile of 3 points over 3.0 s' in describe(goal)
    planned(goal)


def test_an_unreadable_csv_is_a_usage_error_before_anything_is_sent(tmp_path):
    bad = tmp_path / 'bad.csv'
    bad.write_text('t,p\n0,0\n')
    with pytest.raises(CliError, match='lacks time_s and gauge_pressure_pa') as error:
        goal_of('--profile', 'csv', '--csv', str(bad))
    assert error.value.code == 2


@pytest.mark.parametrize(('argv', 'words'), [
    (('--profile', 'sine', '--amplitude', '100kPa', '--offset', '150kPa', '--frequency', '1Hz',
      '--step', '50kPa'), 'step_pa'),                        # a staircase flag on a sine
    (('--profile', 'ramp', '--max', '300kPa'), 'ramp_rate_pa_s'),
    (('--rate', '50kPa/s', '--max', '300kPa', '--step', '50kPa'), 'ramp_rate_pa_s'),
])
def test_a_flag_the_profile_does_not_use_is_refused_by_the_driver_with_its_name(argv, words):
    with pytest.raises(SweepError, match=words):
        planned(goal_of(*argv))


@pytest.mark.parametrize(('argv', 'flag'), [
    ((), '--max'),                                           # `pma sweep` alone
    (('--max', '300kPa'), '--step'),
    (('--profile', 'ramp', '--max', '300kPa'), '--rate'),
    (('--profile', 'sine', '--amplitude', '100kPa', '--offset', '150kPa'), '--frequency'),
    (('--rate', '50kPa/s', '--max', '300kPa', '--step', '50kPa'), '--rate'),
])
def test_pma_refuses_what_the_driver_would_before_sending_and_names_the_flag(argv, flag):
    args = parser().parse_args(['sweep', *argv])
    with pytest.raises(CliError, match=f'\\({flag}\\); nothing was sent') as error:
        checked_sweep_goal(args)
    assert error.value.code == 2
    with pytest.raises(SweepError):                          # what the driver would say
        planned(sweep_goal(args))


def test_only_the_driver_knows_its_ceiling():
    # Above the default 500 kPa ceiling: pma sends it, the driver (its parameter) decides.
    goal = checked_sweep_goal(parser().parse_args(['sweep', '--max', '600kPa', '--step',
                                                   '100kPa']))
    with pytest.raises(SweepError, match='above the driver ceiling'):
        planned(goal)


@pytest.mark.parametrize('verb', [['sweep', '--max', '200kPa', '--step', '100kPa'],
                                  ['move', '27cm']])
def test_the_experiments_facts_without_a_bag_are_refused_before_anything_is_sent(verb, capsys):
    assert main([*verb, '--muscle', 'm2', '--load-kg', '1.5']) == USAGE
    assert '--muscle, --load-kg: ' in capsys.readouterr().err
    assert main([*verb, '--record', 'x', '--load-kg', '-1']) == USAGE
    assert '--load-kg: must be a finite number >= 0' in capsys.readouterr().err


def test_a_recorded_moves_custom_data_holds_the_goal_as_sent():
    goal = MoveToLength.Goal(length_m=0.27, tolerance_m=0.001)
    assert move_metadata(goal, 'n', {'experiment.muscle': 'm2'}) == {
        'experiment.muscle': 'm2', 'note': 'n', 'move.length_m': '0.27',
        'move.tolerance_m': '0.001', 'move.settle_s': '0.0', 'move.timeout_s': '0.0'}
