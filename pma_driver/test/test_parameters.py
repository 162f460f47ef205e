"""driver_node's parameter table: every number has a physical range, and values that make every
reading nonsense are refused with the reason (the node's on-set callback runs these checks)."""

from __future__ import annotations

import math

import pytest
import yaml

from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.driver_parameters import PARAMETERS, check_parameters, defaults
from pma_common.protocol import Hello

pytestmark = pytest.mark.in_process

CONFIG = __import__('pathlib').Path(__file__).resolve().parents[1] / 'config' / 'driver_node.yaml'
HELLO = Hello(1, 'fake_arduino', '0.1.0', 20, 1000, 500_000, 500_000, 1000)


def with_(**changes) -> dict:
    values = defaults()
    values.update({name.replace('__', '.'): value for name, value in changes.items()})
    return values


def test_the_defaults_are_the_config_file_and_pass_their_own_checks():
    listed = yaml.safe_load(CONFIG.read_text())['/**']['ros__parameters']
    assert listed == defaults()
    assert check_parameters(defaults(), None) == ''
    assert check_parameters(defaults(), HELLO) == ''


@pytest.mark.parametrize('name', [n for n, (default, _, _) in PARAMETERS.items()
                                  if isinstance(default, int | float)
                                  and not isinstance(default, bool)])
def test_every_number_has_a_range_that_holds_its_default(name):
    default, description, extra = PARAMETERS[name]
    ranges = extra.get('floating_point_range') or extra.get('integer_range')
    assert ranges, f'{name} has no range (ros2 param describe shows none)'
    assert ranges[0].from_value <= default <= ranges[0].to_value
    assert '[' in description or name in ('baud', 'qos_depth', 'calibration.range_sign'), \
        f'{name}: the description names no unit'


@pytest.mark.parametrize(('changes', 'words'), [
    ({'calibration__volts_at_full': 40.0}, 'calibration.volts_at_full 40.0 is outside 0..5.5'),
    ({'calibration__volts_at_full': 5.2}, 'within the ADC reference'),
    ({'calibration__adc_reference_v': 3.3}, 'within the ADC reference'),
    ({'calibration__volts_at_zero': -0.5}, 'outside 0..5.5'),
    ({'calibration__volts_at_full': 0.6}, 'ADC counts'),
    ({'calibration__volts_at_zero': 4.6}, 'volts_at_full must be above volts_at_zero'),
    ({'calibration__tare_offset_pa': 1e12}, 'tare_offset_pa 1000000000000.0 is outside'),
    ({'calibration__tare_offset_pa': -60_000.0}, '10 % of full_scale_pa'),
    ({'calibration__full_scale_pa': 300_000.0}, 'cannot read max_gauge_pressure_pa'),
    ({'calibration__range_sign': 0.5}, 'range_sign must be -1 or +1'),
    ({'calibration__length_offset_m': 0.01}, 'no muscle length'),
    ({'calibration__speed_of_sound_m_s': 30.0}, 'speed_of_sound_m_s'),
    ({'calibration__adc_reference_v': math.nan}, 'finite'),
    ({'sweep__recorder': 'no spaces allowed'}, 'sweep.recorder'),
    ({'sweep__recorder': ''}, 'sweep.recorder'),
    ({'qos_reliability': 'foo'}, "qos_reliability must be 'reliable' or 'best_effort', got 'foo'"),
    ({'sample_rate_hz': 25.5}, 'sample_rate_hz must be a whole number of Hz'),
    ({'sweep__rest_pa': 0.0}, 'sweep.rest_pa 0.0 is outside 500..100000'),
    ({'sample_rate_hz': 2.0}, 'sweep.rest_time_s 1.0 s holds fewer than 4 samples at '
                              'sample_rate_hz 2.0 Hz'),
    ({'sweep__rest_timeout_s': 1.0}, 'sweep.rest_timeout_s (1.0 s) must be longer than '
                                     'sweep.rest_time_s'),
])
def test_nonsense_calibrations_are_refused_with_the_reason(changes, words):
    reason = check_parameters(with_(**changes), None)
    assert words in reason, reason


def test_a_sensor_for_a_lower_pressure_is_fine_once_the_maximum_is_lowered():
    values = with_(calibration__full_scale_pa=300_000.0, max_gauge_pressure_pa=300_000.0)
    assert check_parameters(values, HELLO) == ''


def test_a_recorder_in_another_namespace_is_a_valid_name():
    assert check_parameters(with_(sweep__recorder='/rig1/recorder'), None) == ''


def test_the_calibrations_refuse_what_the_parameters_refuse():
    with pytest.raises(ValueError, match='within the ADC reference'):
        PressureCalibration(volts_at_full=40.0)
    with pytest.raises(ValueError, match='tare_offset_pa'):
        PressureCalibration(tare_offset_pa=1e12)
    with pytest.raises(ValueError, match='no muscle length'):
        LengthCalibration(length_offset_m=-1.0)
    assert LengthCalibration(length_offset_m=-1.0, range_sign=1.0).range_to_length_m(1.3) == \
        pytest.approx(0.3)
