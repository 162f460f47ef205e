"""docs/bags.md's table of custom_data keys is exactly what the code writes.

The keys a sweep's bag gets come from `recording_metadata`, run here on a goal of every
profile, and a recorded move's from `move_metadata`; the recorder's own keys, the
experiment's and the demo's are read from where the code keeps them. A key written but not
documented fails, and so does a documented key that nothing writes (the table once named
`rig`, `muscle` and `sweep_plan`, which nothing wrote).
tests/test_user_guide_order.py checks the experiment's keys in a bag a real sweep recorded.
"""

from __future__ import annotations

import re

import pytest

from pma_bag.info import LOSS_KEYS
from pma_bag.record import RIG_DIAGNOSTIC_KEYS
from pma_cli.goals import move_metadata
from pma_common import experiment
from pma_common.driver_parameters import PARAMETERS
from pma_common.protocol import Hello
from pma_common.sweep import PROFILE_FIELDS, SweepGoal, plan_goal
from pma_driver.sweep_runner import recording_metadata
from pma_interfaces.action import MoveToLength
from support.procs import ROOT

pytestmark = pytest.mark.in_process

GOALS = {
    'staircase': SweepGoal(max_gauge_pressure_pa=200e3, step_pa=100e3, hold_s=1.0,
                           reversal_pressures_pa=(150e3, 50e3)),
    'forc': SweepGoal(profile='forc', max_gauge_pressure_pa=200e3, step_pa=100e3, hold_s=1.0,
                      forc_count=2, forc_family='both'),
    'ramp': SweepGoal(profile='ramp', max_gauge_pressure_pa=200e3, ramp_rate_pa_s=50e3),
    'sine': SweepGoal(profile='sine', sine_amplitude_pa=50e3, sine_offset_pa=100e3,
                      sine_frequency_hz=0.5),
    'csv': SweepGoal(profile='csv', profile_time_s=(0.0, 1.0), profile_pressure_pa=(0.0, 5e4)),
}


def documented_keys() -> list[str]:
    """The first column of the table under 'custom_data and loss accounting'."""
    text = (ROOT / 'docs' / 'bags.md').read_text(encoding='utf-8')
    section = text.split('### custom_data and loss accounting', 1)[1].split('\n## ', 1)[0]
    keys = []
    for line in section.splitlines():
        if line.startswith('| any'):
            keys.append('*')
        elif line.startswith('| `'):
            keys += re.findall(r'`([^`]+)`', line.split('|')[1])
    return keys


def written_keys() -> set[str]:
    hello = Hello(1, 'pma_firmware', '1.0', 50, 50, 500_000, 500_000, 1000)
    calibration = {name: 1.0 for name in PARAMETERS if name.startswith('calibration.')}
    keys = set()
    assert set(PROFILE_FIELDS) == set(GOALS)
    for goal in GOALS.values():
        keys |= set(recording_metadata(goal, plan_goal(goal, ceiling_pa=500e3), hello,
                                       calibration))
    keys |= set(experiment.KEYS) | set(RIG_DIAGNOSTIC_KEYS) | set(LOSS_KEYS)
    keys |= set(move_metadata(MoveToLength.Goal(length_m=0.27), 'a note', {}))
    keys |= {'run_id'} if "'run_id'" in (ROOT / 'pma_bringup' / 'pma_bringup' /
                                         'demo.py').read_text() else set()
    return keys


def pattern(key: str) -> re.Pattern:
    """`sweep.<field>` matches any one name there; `*` (the 'any KEY' row) nothing."""
    if key == '*':
        return re.compile(r'(?!)')
    return re.compile(re.sub(r'<[^>]+>', r'[A-Za-z0-9_]+', re.escape(key).replace(
        r'\<', '<').replace(r'\>', '>')) + '$')


def test_every_key_written_is_documented_and_every_documented_key_written():
    documented = documented_keys()
    assert len(documented) > 20, documented
    written = written_keys()
    patterns = {key: pattern(key) for key in documented}
    undocumented = sorted(k for k in written if not any(p.match(k) for p in patterns.values()))
    assert not undocumented, f'written but not in docs/bags.md: {undocumented}'
    unwritten = sorted(key for key, p in patterns.items()
                       if key != '*' and not any(p.match(k) for k in written))
    assert not unwritten, f'in docs/bags.md but written by nothing: {unwritten}'


def test_the_experiments_flags_store_si_values_and_refuse_nonsense():
    data = experiment.custom_data({'muscle': ' m2 ', 'load_kg': '1.5', 'supply_kpa': '600',
                                   'operator': 'ada'})
    assert data == {'experiment.muscle': 'm2', 'experiment.load_kg': '1.5',
                    'experiment.supply_gauge_pressure_pa': '600000.0',
                    'experiment.operator': 'ada'}
    assert experiment.summary(data) == 'muscle m2, load 1.5 kg, supply 600 kPa, operator ada'
    assert experiment.custom_data({'load_kg': ''}) == {}
    for name, bad in (('load_kg', '-1'), ('supply_kpa', 'nan'), ('load_kg', '٣'),
                      ('muscle', '  ')):
        with pytest.raises(experiment.ExperimentError, match=f"--{name.replace('_', '-')}"):
            experiment.custom_data({name: bad})


def test_a_goals_entries_go_into_the_bag_and_the_drivers_own_keys_win():
    from diagnostic_msgs.msg import KeyValue

    from pma_interfaces.action import Sweep

    message = Sweep.Goal(max_gauge_pressure_pa=200e3, step_pa=100e3, hold_s=1.0, cycles=1,
                         note='real',
                         custom_data=[KeyValue(key='experiment.muscle', value='m2'),
                                      KeyValue(key='sweep.profile', value='bogus'),
                                      KeyValue(key='note', value='not this')])
    goal = SweepGoal.of(message)
    assert goal.custom_data == {'experiment.muscle': 'm2', 'sweep.profile': 'bogus',
                                'note': 'not this'}
    data = recording_metadata(goal, plan_goal(goal, ceiling_pa=500e3), None, {})
    assert (data['experiment.muscle'], data['sweep.profile'], data['note']) == (
        'm2', 'staircase', 'real')
