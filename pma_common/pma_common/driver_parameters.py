"""driver_node's parameters: names, defaults, descriptions, ranges and the checks across them.

The node declares this table and runs `check_parameters` in its on-set callback (no side
effects there), so what is refused, and why, is tested here without ROS running. Defaults
equal config/driver_node.yaml (test_parameters.py compares them); docs/driver.md explains
each one.
"""

from __future__ import annotations

import math
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidNodeNameException, InvalidTopicNameException
from rclpy.validate_node_name import validate_node_name
from rclpy.validate_topic_name import validate_topic_name

from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.lease import MIN_COMMANDER_TIMEOUT_S
from pma_common.protocol import Command, Hello

# What driver_node does when a commander's lease runs out (commander_lost_action).
COMMANDER_LOST_ACTIONS = ('vent', 'hold')


def _floats(low: float, high: float, step: float = 0.0) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=low, to_value=high, step=step)]


def _ints(low: int, high: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=low, to_value=high, step=1)]


# name: (default, description, extra descriptor fields). Ranges are physical: what the part
# can be, not what is sensible today (the cross-checks in check_parameters do that).
PARAMETERS: dict[str, tuple[Any, str, dict]] = {
    'port': ('/dev/ttyACM0', 'Serial port; a /dev/serial/by-id/... path survives replugging',
             {'read_only': True}),
    'baud': (115200, 'Serial baud rate (the firmware uses 115200)',
             {'read_only': True, 'integer_range': _ints(1200, 4_000_000)}),
    'frame_id': ('pma_link', 'frame_id of every published header', {'read_only': True}),
    'sample_rate_hz': (20.0, 'Sample rate asked of the device (RATE, whole Hz) [Hz]',
                       {'floating_point_range': _floats(1.0, 5000.0)}),
    'max_gauge_pressure_pa': (500_000.0, 'Highest gauge pressure ever commanded (MAX) [Pa]; '
                              'never above the device limit nor the sensor full scale',
                              {'floating_point_range': _floats(1000.0, 1_000_000.0)}),
    'ambient_pressure_pa': (101_325.0, 'Ambient pressure added to gauge for pma/pressure [Pa]',
                            {'floating_point_range': _floats(50_000.0, 120_000.0)}),
    # The ATmega2560 takes an ADC reference of 1.0 V up to its supply (5.5 V at most).
    'calibration.adc_reference_v': (5.0, 'ADC reference voltage [V]',
                                    {'floating_point_range': _floats(1.0, 5.5)}),
    'calibration.volts_at_zero': (0.5, 'Sensor output at 0 Pa gauge [V]; within the ADC '
                                  'reference', {'floating_point_range': _floats(0.0, 5.5)}),
    'calibration.volts_at_full': (4.5, 'Sensor output at full_scale_pa [V]; within the ADC '
                                  'reference', {'floating_point_range': _floats(0.0, 5.5)}),
    'calibration.full_scale_pa': (500_000.0, 'Sensor full scale [Pa, gauge]; at least '
                                  'max_gauge_pressure_pa',
                                  {'floating_point_range': _floats(1000.0, 10_000_000.0)}),
    'calibration.tare_offset_pa': (0.0, 'Subtracted from every pressure reading [Pa]; at most '
                                   '10 % of full_scale_pa (set by ~/tare)',
                                   {'floating_point_range': _floats(-100_000.0, 100_000.0)}),
    'calibration.speed_of_sound_m_s': (343.0, 'Speed of sound for the echo time [m/s]',
                                       {'floating_point_range': _floats(300.0, 400.0)}),
    # The HC-SR04 reaches 4 m, so no mounting puts its zero further away than that.
    'calibration.length_offset_m': (0.40, 'length_m = length_offset_m + range_sign * range [m]',
                                    {'floating_point_range': _floats(-4.0, 4.0)}),
    'calibration.range_sign': (-1.0, '+1 or -1: direction of the range along the muscle',
                               {'floating_point_range': _floats(-1.0, 1.0, step=2.0)}),
    'heartbeat_period_s': (0.2, 'Host heartbeat (HB) period [s]',
                           {'floating_point_range': _floats(0.01, 5.0)}),
    'heartbeat_timeout_ms': (1000, 'Device vents after this long without a command (HBTO) [ms]',
                             {'integer_range': _ints(100, 10_000)}),
    # A remote commander (length controller, `pma sweep`) renews its lease on
    # pma/commander_lease every 0.1 s: 0.8 s is eight missed renewals, and with the check
    # every tenth of it the muscle is vented within 0.9 s of the network dropping.
    'commander_timeout_s': (0.8, 'A commander holding a lease on pma/commander_lease that '
                            'renews none for this long is lost: the muscle goes to '
                            'commander_lost_action [s]',
                            {'floating_point_range': _floats(MIN_COMMANDER_TIMEOUT_S, 30.0)}),
    'commander_lost_action': ('vent', "'vent' (default) or 'hold' (keep the pressure, for a "
                              'load that must not drop) when a commander is lost; a running '
                              'sweep aborts and vents either way', {}),
    'reconnect_period_s': (1.0, 'Retry period when the port is missing or lost [s]',
                           {'floating_point_range': _floats(0.1, 60.0)}),
    'handshake_timeout_s': (2.0, 'Wait this long for the firmware HELLO after opening [s]',
                            {'floating_point_range': _floats(0.1, 30.0)}),
    'autostart': (True, 'Configure and activate without a lifecycle manager',
                  {'read_only': True}),
    'qos_reliability': ('reliable', "'reliable' (REP-2003 system default) or 'best_effort'",
                        {'read_only': True}),
    'qos_depth': (1000, 'History depth of the data topics: what a reliable reader that '
                  'stalls (a busy recorder) can still get; 1000 = 1 s at 1 kHz',
                  {'read_only': True, 'integer_range': _ints(1, 10_000)}),
    'sweep.tolerance_pa': (10_000.0, 'A sweep step is reached within this of its setpoint [Pa]',
                           {'floating_point_range': _floats(100.0, 100_000.0)}),
    'sweep.step_timeout_s': (10.0, 'Hold starts anyway after this long (logged) [s]',
                             {'floating_point_range': _floats(0.1, 600.0)}),
    # At rest (before a sweep's first level): the mean over sweep.rest_time_s below
    # sweep.rest_pa and flat (halves within 1 kPa). 5 kPa is 1 % of the 500 kPa sensor's
    # span, twice its noise (0.5 % FS a reading; a 1 s mean at 20 Hz is within 0.6 kPa),
    # far below the muscle's ~50 kPa dead zone; 1 s is two exhaust time constants of the
    # simulated rig; 30 s lets a slow exhaust vent from the ceiling (2.3 s simulated).
    'sweep.rest_pa': (5_000.0, "A sweep's wait for rest before its first level ends once the "
                      'mean pressure over sweep.rest_time_s is below this and flat [Pa]',
                      {'floating_point_range': _floats(500.0, 100_000.0)}),
    'sweep.rest_time_s': (1.0, 'The window over which the pressure must be at rest (mean below '
                          'sweep.rest_pa, its halves within 1 kPa) [s]',
                          {'floating_point_range': _floats(0.1, 60.0)}),
    'sweep.rest_timeout_s': (30.0, 'A sweep whose muscle is not at rest this long after venting '
                             'aborts (and vents) [s]',
                             {'floating_point_range': _floats(1.0, 600.0)}),
    'sweep.recorder': ('recorder', 'Node name of the recorder a Sweep goal with record asks '
                       '(its ~/start and ~/stop); relative names resolve in this namespace',
                       {'read_only': True}),
    'sweep.recorder_timeout_s': (5.0, 'A recording sweep aborts when the recorder is not found '
                                 'or does not answer within this [s]',
                                 {'floating_point_range': _floats(0.1, 60.0)}),
}


def defaults() -> dict[str, Any]:
    return {name: default for name, (default, _, _) in PARAMETERS.items()}


def descriptor(name: str) -> ParameterDescriptor:
    _, description, extra = PARAMETERS[name]
    return ParameterDescriptor(description=description, **extra)


def _out_of_range(name: str, value: Any) -> str:
    extra = PARAMETERS[name][2]
    for key in ('floating_point_range', 'integer_range'):
        for allowed in extra.get(key, ()):
            if not allowed.from_value <= value <= allowed.to_value:
                return (f'{name} {value} is outside {allowed.from_value:g}..'
                        f'{allowed.to_value:g}')
    return ''


def calibrations(values: dict) -> tuple[PressureCalibration, LengthCalibration]:
    """Calibration dataclasses from parameter values (they validate; ValueError says why)."""
    pressure = PressureCalibration(
        adc_reference_v=values['calibration.adc_reference_v'],
        volts_at_zero=values['calibration.volts_at_zero'],
        volts_at_full=values['calibration.volts_at_full'],
        full_scale_pa=values['calibration.full_scale_pa'],
        tare_offset_pa=values['calibration.tare_offset_pa'])
    length = LengthCalibration(
        speed_of_sound_m_s=values['calibration.speed_of_sound_m_s'],
        length_offset_m=values['calibration.length_offset_m'],
        range_sign=values['calibration.range_sign'])
    return pressure, length


def recorder_name_error(name: str) -> str:
    """Why `name` cannot name the recorder node ('' when it can)."""
    node = name.rsplit('/', 1)[-1]
    try:
        validate_node_name(node)
        validate_topic_name(f'{name}/start')
    except (InvalidNodeNameException, InvalidTopicNameException) as error:
        return f'sweep.recorder {name!r} is not a node name: {str(error).splitlines()[0]}'
    return ''


def check_parameters(values: dict, hello: Hello | None) -> str:
    """Why these parameter values cannot be used ('' when they can)."""
    for name, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            return f'{name} must be finite, got {value}'
        reason = _out_of_range(name, value)
        if reason:
            return reason
    if values['qos_reliability'] not in ('reliable', 'best_effort'):
        return ("qos_reliability must be 'reliable' or 'best_effort', got "
                f"{values['qos_reliability']!r}")
    if values['commander_lost_action'] not in COMMANDER_LOST_ACTIONS:
        return (f'commander_lost_action must be one of {COMMANDER_LOST_ACTIONS}, got '
                f"{values['commander_lost_action']!r}")
    if values['sample_rate_hz'] != round(values['sample_rate_hz']):
        return (f'sample_rate_hz must be a whole number of Hz (the device takes RATE in whole '
                f'Hz), got {values["sample_rate_hz"]}')
    if values['heartbeat_period_s'] * 1000.0 > values['heartbeat_timeout_ms'] / 2:
        return (f'heartbeat_period_s ({values["heartbeat_period_s"]} s) must be at most half '
                f'of heartbeat_timeout_ms ({values["heartbeat_timeout_ms"]} ms)')
    if values['sweep.rest_time_s'] * values['sample_rate_hz'] < 4:
        return (f'sweep.rest_time_s {values["sweep.rest_time_s"]} s holds fewer than 4 samples '
                f'at sample_rate_hz {values["sample_rate_hz"]} Hz: the wait for rest compares '
                'the means of its two halves; raise either')
    if values['sweep.rest_timeout_s'] <= values['sweep.rest_time_s']:
        return (f'sweep.rest_timeout_s ({values["sweep.rest_timeout_s"]} s) must be longer than '
                f'sweep.rest_time_s ({values["sweep.rest_time_s"]} s)')
    reason = recorder_name_error(values['sweep.recorder'])
    if reason:
        return reason
    try:
        calibrations(values)
    except ValueError as error:
        return f'calibration: {error}'
    if values['max_gauge_pressure_pa'] > values['calibration.full_scale_pa']:
        return (f'the sensor (calibration.full_scale_pa {values["calibration.full_scale_pa"]:.0f}'
                f' Pa) cannot read max_gauge_pressure_pa {values["max_gauge_pressure_pa"]:.0f} '
                'Pa: lower max_gauge_pressure_pa or fit a sensor with a larger range')
    if hello is not None:
        if values['sample_rate_hz'] > hello.max_rate_hz:
            return (f'sample_rate_hz {values["sample_rate_hz"]} Hz is above the device maximum '
                    f'{hello.max_rate_hz} Hz')
        # limit_pa is the firmware's compiled hard limit; its current ceiling_pa is only what
        # the last MAX set, which this parameter is about to set again.
        if values['max_gauge_pressure_pa'] > hello.limit_pa:
            return (f'max_gauge_pressure_pa {values["max_gauge_pressure_pa"]:.0f} Pa is above '
                    f'the device limit {hello.limit_pa} Pa')
    return ''


def device_ceiling_pa(max_gauge_pressure_pa: float, hello: Hello | None) -> int:
    """The most any command may ask for: the parameter, never above the device's limit."""
    limit = max_gauge_pressure_pa
    if hello is not None:
        limit = min(limit, hello.limit_pa)
    return math.floor(limit)


def stall_timeout_s(sample_rate_hz: float) -> float:
    """No data for this long is a stall: five samples, but never under a second."""
    return max(1.0, 5.0 / sample_rate_hz)


def startup_commands(values: dict, hello: Hello) -> tuple[list[tuple[Command, tuple[int, ...]]],
                                                          list[str]]:
    """What to send after a handshake (HBTO, MAX, RATE), and warnings about what was clipped."""
    warnings = []
    if values['max_gauge_pressure_pa'] > hello.limit_pa:
        warnings.append(f'max_gauge_pressure_pa {values["max_gauge_pressure_pa"]:.0f} Pa is '
                        f'above the device limit {hello.limit_pa} Pa: using the device limit')
    rate = round(values['sample_rate_hz'])
    if rate > hello.max_rate_hz:
        warnings.append(f'sample_rate_hz {rate} is above the device maximum '
                        f'{hello.max_rate_hz}: using {hello.max_rate_hz}')
        rate = hello.max_rate_hz
    commands = [
        (Command.HEARTBEAT_TIMEOUT, (values['heartbeat_timeout_ms'],)),
        (Command.MAX, (device_ceiling_pa(values['max_gauge_pressure_pa'], hello),)),
        (Command.RATE, (max(1, rate),))]
    return commands, warnings
