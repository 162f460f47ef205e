"""pma calibrate's arithmetic: a sensor with a known span error and a known mounting is found
back from what it reads, through the driver's own transfer functions; bad results are refused."""

import math

import pytest
import yaml

from pma_cli import calibration_arithmetic as cal
from pma_common.calibration import ADC_FULL_SCALE, LengthCalibration, PressureCalibration
from pma_common.driver_parameters import PARAMETERS, calibrations, check_parameters, defaults

pytestmark = pytest.mark.in_process


def values(**changes):
    merged = defaults()
    merged.update({f'calibration.{k}': v for k, v in changes.items()})
    return merged


def true_adc(true_sensor: PressureCalibration, gauge_pa: float) -> float:
    """The (unrounded) count a sensor with this real transfer function gives."""
    volts = true_sensor.volts_at_zero + gauge_pa / true_sensor.pa_per_volt
    return volts * ADC_FULL_SCALE / true_sensor.adc_reference_v


@pytest.mark.parametrize('true_volts_at_full', [4.3, 4.5, 4.62])
@pytest.mark.parametrize('zero_offset_pa', [0.0, 4_000.0, -6_000.0])
def test_span_from_a_reference_recovers_the_true_sensor(true_volts_at_full, zero_offset_pa):
    # The real sensor: span 0.5..true_volts_at_full V, and a zero off by zero_offset_pa.
    true_sensor = PressureCalibration(volts_at_full=true_volts_at_full)
    zero_count = true_adc(true_sensor, zero_offset_pa)
    # The driver believes the default span, and tared at rest (as `pma calibrate` does first).
    believed = values()
    pressure, _ = calibrations(believed)
    believed['calibration.tare_offset_pa'] = pressure.with_tare(zero_count).tare_offset_pa
    reference_pa = 300_000.0
    adc = cal.Measurement(true_adc(true_sensor, zero_offset_pa + reference_pa), 1.0, 40)
    result = cal.span_from_reference(believed, adc, reference_pa)

    fixed = calibrations({**believed, 'calibration.volts_at_full': result.volts_at_full,
                          'calibration.tare_offset_pa': result.tare_offset_pa})[0]
    # The corrected calibration reads the reference there, 0 at rest, and right in between.
    assert math.isclose(fixed.adc_to_pa(adc.mean), reference_pa, rel_tol=1e-9)
    assert math.isclose(fixed.adc_to_pa(zero_count), 0.0, abs_tol=1e-6)
    mid = true_adc(true_sensor, zero_offset_pa + 150_000.0)
    assert math.isclose(fixed.adc_to_pa(mid), 150_000.0, rel_tol=1e-9)
    assert math.isclose(result.factor, reference_pa / pressure.with_tare(zero_count).adc_to_pa(
        adc.mean), rel_tol=1e-12)
    assert not check_parameters({**believed, 'calibration.volts_at_full': result.volts_at_full,
                                 'calibration.tare_offset_pa': result.tare_offset_pa}, None)


def test_span_from_the_averaged_zero_is_right_whatever_count_the_tare_caught():
    # The device tares on one conversion: here two counts below the sensor's true zero.
    true_sensor = PressureCalibration(volts_at_full=4.4)
    zero_count = true_adc(true_sensor, 0.0)
    believed = values()
    pressure, _ = calibrations(believed)
    believed['calibration.tare_offset_pa'] = pressure.with_tare(zero_count - 2).tare_offset_pa
    adc = cal.Measurement(true_adc(true_sensor, 300_000.0), 1.0, 40)
    averaged = cal.span_from_reference(believed, adc, 300_000.0, zero_adc=zero_count)
    assert math.isclose(averaged.volts_at_full, 4.4, rel_tol=1e-9)
    from_the_tare = cal.span_from_reference(believed, adc, 300_000.0)
    assert abs(from_the_tare.volts_at_full - 4.4) > 0.01          # what the zero step fixes
    # The tare stays on the device's count: the device and the driver keep one zero.
    assert math.isclose(averaged.tare_offset_pa, calibrations(
        {**believed, 'calibration.volts_at_full': averaged.volts_at_full})[0].with_tare(
            zero_count - 2).tare_offset_pa, rel_tol=1e-9)


def test_span_refusals_say_why():
    believed = values()
    pressure, _ = calibrations(believed)
    at_300 = cal.Measurement(pressure.pa_to_adc(300_000.0), 1.0, 40)
    with pytest.raises(cal.CalibrationError, match='too close to zero'):
        cal.span_from_reference(believed, cal.Measurement(pressure.pa_to_adc(50_000), 1, 40),
                                50_000.0)
    with pytest.raises(cal.CalibrationError, match='misread gauge'):
        cal.span_from_reference(believed, at_300, 400_000.0)      # +33 %
    with pytest.raises(cal.CalibrationError, match='misread gauge'):
        cal.span_from_reference(believed, at_300, 200_000.0)      # -33 %
    with pytest.raises(cal.CalibrationError, match='moved only'):
        cal.span_from_reference(believed, cal.Measurement(pressure.pa_to_adc(0.0) + 3, 1, 40),
                                300_000.0)
    with pytest.raises(cal.CalibrationError, match='too close to zero'):
        cal.span_from_reference(believed, at_300, math.nan)


def test_a_check_pressure_the_span_cannot_use_is_refused_before_anything_is_done():
    # Checked against the driver's parameters before the tare: `--check-pressure 10kPa` used
    # to tare and inflate, then refuse the 10.7 kPa reference.
    believed = values(full_scale_pa=500_000.0)
    cal.check_span_pressure(believed, 100_000.0)                  # 20 % of full scale
    with pytest.raises(cal.CalibrationError, match=r'10\.0 kPa is too close to zero.*check at '
                       r'100 kPa or more \(20 % of full_scale_pa 500 kPa\)'):
        cal.check_span_pressure(believed, 10_000.0)
    with pytest.raises(cal.CalibrationError, match='above max_gauge_pressure_pa'):
        cal.check_span_pressure(believed, believed['max_gauge_pressure_pa'] + 1.0)
    with pytest.raises(cal.CalibrationError, match='too close to zero'):
        cal.check_span_pressure(believed, math.nan)


def test_a_span_that_leaves_the_adc_reference_is_refused_by_the_drivers_rule():
    # Near the top of the allowed error, on a sensor already at the reference: over 5.0 V.
    believed = values(volts_at_full=4.9)
    pressure, _ = calibrations(believed)
    adc = cal.Measurement(pressure.pa_to_adc(300_000.0), 1.0, 40)
    result = cal.span_from_reference(believed, adc, 300_000.0 / 1.15)
    with pytest.raises(cal.CalibrationError, match='driver would refuse it: calibration'):
        cal.check_result(believed, {'calibration.volts_at_full': result.volts_at_full})


@pytest.mark.parametrize(('true_offset', 'sign'), [(0.40, -1.0), (0.383, -1.0), (0.05, 1.0)])
def test_length_offset_from_a_tape_recovers_the_mounting(true_offset, sign):
    rest_m = 0.30
    mounting = LengthCalibration(length_offset_m=true_offset, range_sign=sign)
    echoes = [mounting.length_to_echo_us(rest_m + noise) for noise in
              (-0.0015, 0.0, 0.0015) * 10]
    believed = values(length_offset_m=0.40 if sign < 0 else 0.0, range_sign=sign)
    result = cal.length_offset_from_tape(believed, echoes, rest_m)
    # One microsecond of echo is 0.17 mm: the quantisation of the raw counts.
    assert math.isclose(result.length_offset_m, true_offset, abs_tol=3e-4)
    fixed = LengthCalibration(length_offset_m=result.length_offset_m, range_sign=sign)
    mean = sum(fixed.echo_to_length_m(e) for e in echoes) / len(echoes)
    assert math.isclose(mean, rest_m, abs_tol=1e-9)


def test_length_refusals_say_why():
    believed = values()
    mounting = LengthCalibration()
    echoes = [mounting.length_to_echo_us(0.30)] * 20
    with pytest.raises(cal.CalibrationError, match='not a muscle at rest'):
        cal.length_offset_from_tape(believed, echoes, 3.0)      # 300 cm: typed m for cm?
    with pytest.raises(cal.CalibrationError, match='not a muscle at rest'):
        cal.length_offset_from_tape(believed, echoes, 0.003)
    with pytest.raises(cal.CalibrationError, match='had an echo'):
        cal.length_offset_from_tape(believed, [0] * 10 + echoes[:10], 0.30)
    with pytest.raises(cal.CalibrationError, match='only 5 readings'):
        cal.length_offset_from_tape(believed, echoes[:5], 0.30)


def test_the_params_file_is_what_the_driver_loads():
    merged = values(volts_at_full=4.45, length_offset_m=0.395)
    text = cal.params_file_text(merged, ['span: factor 1.011', 'length: tape 0.300 m'])
    loaded = yaml.safe_load(text)
    parameters = loaded['/**']['ros__parameters']
    assert set(parameters) == set(cal.FILE_PARAMETERS) <= set(PARAMETERS)
    assert parameters['calibration.volts_at_full'] == 4.45
    assert parameters['calibration.length_offset_m'] == 0.395
    assert all(isinstance(v, float) for v in parameters.values())   # doubles stay doubles
    assert 'calibration.tare_offset_pa' not in parameters           # per session, see docstring
    assert '# span: factor 1.011' in text and '--params-file' in text
