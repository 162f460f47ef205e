"""The arithmetic of `pma calibrate`: span from a reference gauge, length offset from a tape.

No ROS. The sensors' transfer functions are pma_common.calibration's and the limits are the
driver's own parameter checks (pma_common.driver_parameters), so a result the driver would
refuse is refused here first, with the reason; on top of them, bounds on what a calibration
may change at all (a 30 % span error is a wrong sensor or a misread gauge, not a calibration).

Geometry (docs/hardware.md, "Length sensor geometry"): the HC-SR04 looks along the muscle at
a plate on its free end and `length_m = length_offset_m + range_sign * range_m`. With the
usual mounting (range_sign -1) the sensor faces the free end from beyond it, and
length_offset_m is the distance from the muscle's fixed end to the sensor's face: a tape
measurement of the muscle at rest gives it as rest length + the range the sensor reads.
"""

from __future__ import annotations

import datetime
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from pma_common.calibration import ADC_FULL_SCALE, LengthCalibration
from pma_common.driver_parameters import PARAMETERS, calibrations, check_parameters

MIN_CHECK_FRACTION = 0.2       # of full scale: below it the span is judged on too few counts
MAX_SPAN_ERROR = 0.2           # |reference / reading - 1| above this: not a calibration
MIN_SAMPLES = 10               # averaged readings behind each measurement
MIN_ECHO_SHARE = 0.8           # of samples with an echo, for a length measurement
REST_LENGTH_BOUNDS_M = (0.05, 2.0)   # a PMA at rest: 5 cm .. 2 m
LARGE_OFFSET_CHANGE_M = 0.05   # asks for a confirmation: a misplaced tape, or a moved sensor?
# The parameters a calibration file sets (the tare is per session: the device forgets it).
FILE_PARAMETERS = ('calibration.adc_reference_v', 'calibration.volts_at_zero',
                   'calibration.volts_at_full', 'calibration.full_scale_pa',
                   'calibration.speed_of_sound_m_s', 'calibration.length_offset_m',
                   'calibration.range_sign')


class CalibrationError(ValueError):
    """A result outside physical bounds, or a measurement too poor to use; says which."""


@dataclass(frozen=True)
class Measurement:
    """The mean of raw readings over a hold, and how much they varied."""

    mean: float
    stdev: float
    count: int

    @classmethod
    def of(cls, values: Sequence[float]) -> Measurement:
        values = [float(v) for v in values]
        if len(values) < MIN_SAMPLES:
            raise CalibrationError(f'only {len(values)} readings (at least {MIN_SAMPLES})')
        return cls(statistics.fmean(values), statistics.pstdev(values), len(values))


@dataclass(frozen=True)
class SpanResult:
    reading_pa: float        # what the sensor read (current calibration, tared)
    reference_pa: float      # what the reference gauge read
    volts_at_full: float     # new calibration.volts_at_full
    tare_offset_pa: float    # the tare, rescaled to the new span (same zero count)

    @property
    def factor(self) -> float:
        return self.reference_pa / self.reading_pa


@dataclass(frozen=True)
class LengthResult:
    range_m: float           # what the sensor measured at rest
    tape_m: float            # the muscle at rest, by tape
    length_offset_m: float   # new calibration.length_offset_m
    previous_length_m: float  # what the driver published before


def check_span_pressure(values: Mapping[str, float], check_pa: float) -> None:
    """Refuse a check pressure the span check cannot use, before the tare and the inflation:
    below MIN_CHECK_FRACTION of full scale its reference would be refused (too close to zero)
    only once both were done, and above max_gauge_pressure_pa the driver refuses it."""
    full_scale = calibrations(values)[0].full_scale_pa
    if not (math.isfinite(check_pa) and check_pa >= MIN_CHECK_FRACTION * full_scale):
        raise CalibrationError(f'a check pressure of {check_pa / 1e3:.1f} kPa is too close to '
                               f'zero to judge the span: {_minimum_check(full_scale)}')
    ceiling = values['max_gauge_pressure_pa']
    if check_pa > ceiling:
        raise CalibrationError(f'check pressure {check_pa / 1e3:.0f} kPa is above '
                               f'max_gauge_pressure_pa {ceiling / 1e3:.0f} kPa')


def _minimum_check(full_scale_pa: float) -> str:
    return (f'check at {MIN_CHECK_FRACTION * full_scale_pa / 1e3:.0f} kPa or more '
            f'({100 * MIN_CHECK_FRACTION:.0f} % of full_scale_pa {full_scale_pa / 1e3:.0f} kPa)')


def span_from_reference(values: Mapping[str, float], adc: Measurement,
                        reference_pa: float, zero_adc: float | None = None) -> SpanResult:
    """New volts_at_full: the slope from the count at rest to `adc` reading `reference_pa`.

    The count at rest is `zero_adc`, averaged at rest (the device's tare takes one noisy
    conversion: two counts off make a 0.5 % span error), else the count the current
    calibration reads as 0 Pa. The tare itself stays on the device's count.
    """
    pressure, _ = calibrations(values)
    full_scale = pressure.full_scale_pa
    if not math.isfinite(reference_pa) or reference_pa < MIN_CHECK_FRACTION * full_scale:
        raise CalibrationError(
            f'a reference of {reference_pa / 1e3:.1f} kPa is too close to zero to judge the span:'
            f' {_minimum_check(full_scale)}')
    zero_volts = pressure.volts_at_zero + pressure.tare_offset_pa / pressure.pa_per_volt
    zero_count = zero_volts * ADC_FULL_SCALE / pressure.adc_reference_v \
        if zero_adc is None else zero_adc
    counts = adc.mean - zero_count
    reading = pressure.adc_to_pa(adc.mean)
    if counts < 0.1 * MIN_CHECK_FRACTION * ADC_FULL_SCALE:
        raise CalibrationError(f'the sensor moved only {counts:.1f} ADC counts from zero: is the '
                               'muscle pressurised, and the sensor connected?')
    factor = reference_pa / reading
    if abs(factor - 1.0) > MAX_SPAN_ERROR:
        raise CalibrationError(
            f'the sensor read {reading / 1e3:.1f} kPa where the gauge read '
            f'{reference_pa / 1e3:.1f} kPa ({100 * (factor - 1):+.0f} %): more than '
            f'{100 * MAX_SPAN_ERROR:.0f} % is a misread gauge, a wrong full_scale_pa or '
            'another sensor, not a span error; nothing changed')
    pa_per_volt = reference_pa / pressure.adc_to_volts(counts)
    volts_at_full = pressure.volts_at_zero + full_scale / pa_per_volt
    tare = (zero_volts - pressure.volts_at_zero) * pa_per_volt
    return SpanResult(reading, reference_pa, volts_at_full, tare)


def length_offset_from_tape(values: Mapping[str, float], echo_us: Sequence[int],
                            tape_m: float) -> LengthResult:
    """New length_offset_m so that the range measured at rest reads as the tape's length."""
    low, high = REST_LENGTH_BOUNDS_M
    if not math.isfinite(tape_m) or not low <= tape_m <= high:
        raise CalibrationError(f'{tape_m * 100:.1f} cm is not a muscle at rest (expected '
                               f'{low * 100:.0f} to {high * 100:.0f} cm)')
    _, length = calibrations(values)
    ranges = [length.echo_to_range_m(echo) for echo in echo_us]
    if len(ranges) < MIN_SAMPLES:
        raise CalibrationError(f'only {len(ranges)} readings (at least {MIN_SAMPLES})')
    valid = [r for r in ranges if math.isfinite(r)]
    if len(valid) < max(MIN_ECHO_SHARE * len(ranges), MIN_SAMPLES):
        raise CalibrationError(f'only {len(valid)} of {len(ranges)} readings had an echo: aim '
                               'the sensor at the plate (docs/hardware.md) and try again')
    range_m = Measurement.of(valid).mean
    offset = tape_m - length.range_sign * range_m
    previous = length.range_to_length_m(range_m)
    LengthCalibration(length.speed_of_sound_m_s, offset, length.range_sign)  # validates
    return LengthResult(range_m, tape_m, offset, previous)


def check_result(values: Mapping[str, float], changes: Mapping[str, float]) -> dict:
    """The driver's parameters with the changes; CalibrationError with the driver's reason."""
    unknown = [name for name in changes if name not in PARAMETERS]
    if unknown:
        raise CalibrationError(f'not driver parameters: {", ".join(unknown)}')
    merged = {**values, **changes}
    reason = check_parameters(merged, None)
    if reason:
        raise CalibrationError(f'the driver would refuse it: {reason}')
    return merged


def params_file_text(values: Mapping[str, float], notes: Sequence[str]) -> str:
    """A `/**: ros__parameters:` file of the calibration, for driver_node --params-file."""
    now = datetime.datetime.now().astimezone().isoformat(timespec='seconds')
    lines = [f'# driver_node calibration written by `pma calibrate` on {now}.',
             '# Load it after the rig file: driver_node --ros-args --params-file my_rig.yaml '
             '--params-file THIS',
             '# (or bringup.launch.py driver_params_file:=THIS). No tare here: the device',
             '# forgets its tare when it restarts, so tare at rest every session',
             '# (`pma tare --vent`).']
    lines += [f'# {note}' for note in notes]
    lines += ['/**:', '  ros__parameters:']
    for name in FILE_PARAMETERS:
        lines.append(f'    {name}: {float(values[name])!r}')
    return '\n'.join(lines) + '\n'
