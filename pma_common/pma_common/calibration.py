"""Raw readings to SI units: pressure ADC counts to Pa, echo time to muscle length.

The one home of the sensors' transfer functions. The driver converts with them;
the simulated rig uses their inverses to produce the raw counts a real sensor
would give, so both sides agree by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

ADC_FULL_SCALE = 1023  # 10-bit ADC of the ATmega2560
MIN_SPAN_COUNTS = 100  # fewer counts over the sensor's span: worse than 1 % of full scale each
MAX_TARE_FRACTION = 0.1  # of full scale: the most a sensor's zero may be off and still be tared


@dataclass(frozen=True)
class PressureCalibration:
    """Ratiometric analog gauge sensor.

    `volts_at_zero` V at 0 Pa, `volts_at_full` V at `full_scale_pa`.
    """

    adc_reference_v: float = 5.0
    volts_at_zero: float = 0.5
    volts_at_full: float = 4.5
    full_scale_pa: float = 500_000.0
    tare_offset_pa: float = 0.0  # subtracted after conversion (set by tare at rest)

    def __post_init__(self):
        for name in ('adc_reference_v', 'volts_at_zero', 'volts_at_full', 'full_scale_pa',
                     'tare_offset_pa'):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f'{name} must be finite')
        for name in ('adc_reference_v', 'full_scale_pa'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0')
        if not self.volts_at_zero >= 0:
            raise ValueError('volts_at_zero must be >= 0 V (the ADC reads 0..adc_reference_v)')
        if not self.volts_at_full > self.volts_at_zero:
            raise ValueError('volts_at_full must be above volts_at_zero')
        if self.volts_at_full > self.adc_reference_v:
            raise ValueError(
                f'the sensor span {self.volts_at_zero:g}..{self.volts_at_full:g} V must lie '
                f'within the ADC reference 0..{self.adc_reference_v:g} V (adc_reference_v), '
                'or the top of the range reads as saturated')
        span_counts = (self.volts_at_full - self.volts_at_zero) / self.adc_reference_v \
            * ADC_FULL_SCALE
        if span_counts < MIN_SPAN_COUNTS:
            raise ValueError(
                f'the sensor span {self.volts_at_zero:g}..{self.volts_at_full:g} V covers only '
                f'{span_counts:.0f} ADC counts (at least {MIN_SPAN_COUNTS}: 1 % of full scale '
                'per count)')
        if abs(self.tare_offset_pa) > MAX_TARE_FRACTION * self.full_scale_pa:
            raise ValueError(
                f'tare_offset_pa {self.tare_offset_pa:.0f} Pa is more than '
                f'{MAX_TARE_FRACTION * 100:g} % of full_scale_pa {self.full_scale_pa:.0f} Pa: '
                'a zero that far off is a wrong or broken sensor, not an offset')

    @property
    def pa_per_volt(self) -> float:
        return self.full_scale_pa / (self.volts_at_full - self.volts_at_zero)

    @property
    def pa_per_count(self) -> float:
        """Resolution of one ADC count [Pa] (about 611 Pa with the defaults)."""
        return self.pa_per_volt * self.adc_reference_v / ADC_FULL_SCALE

    def adc_to_volts(self, adc: float) -> float:
        return adc * self.adc_reference_v / ADC_FULL_SCALE

    def adc_to_pa(self, adc: float) -> float:
        """Gauge pressure [Pa] for an ADC count, tare applied."""
        above_zero_v = self.adc_to_volts(adc) - self.volts_at_zero
        return above_zero_v * self.pa_per_volt - self.tare_offset_pa

    def pa_to_adc(self, gauge_pa: float) -> int:
        """The count an ideal sensor gives at this gauge pressure (inverse of adc_to_pa)."""
        volts = self.volts_at_zero + (gauge_pa + self.tare_offset_pa) / self.pa_per_volt
        count = round(volts * ADC_FULL_SCALE / self.adc_reference_v)
        return int(min(ADC_FULL_SCALE, max(0, count)))

    def adc_in_span(self, adc: int, margin_v: float = 0.1) -> bool:
        """False when the reading is outside the sensor's output span (broken or unplugged)."""
        volts = self.adc_to_volts(adc)
        return self.volts_at_zero - margin_v <= volts <= self.volts_at_full + margin_v

    def with_tare(self, adc_at_zero: float) -> PressureCalibration:
        """A copy whose tare makes this ADC reading 0 Pa."""
        untared = (self.adc_to_volts(adc_at_zero) - self.volts_at_zero) * self.pa_per_volt
        return PressureCalibration(self.adc_reference_v, self.volts_at_zero, self.volts_at_full,
                                   self.full_scale_pa, untared)


@dataclass(frozen=True)
class LengthCalibration:
    """HC-SR04 echo time to muscle length through the mounting geometry.

    The sensor looks along the muscle at a plate on its free end:
    `length_m = length_offset_m + range_sign * range_m`. With the defaults the sensor
    sits 0.40 m from the muscle's fixed end, facing it: a 0.30 m muscle leaves a
    0.10 m range, and contraction lengthens the range (sign -1).
    """

    speed_of_sound_m_s: float = 343.0  # dry air, 20 degC
    length_offset_m: float = 0.40
    range_sign: float = -1.0
    min_range_m: float = 0.02   # HC-SR04 datasheet
    max_range_m: float = 4.0

    def __post_init__(self):
        speed = self.speed_of_sound_m_s
        if not (math.isfinite(speed) and 300.0 <= speed <= 400.0):
            raise ValueError('speed_of_sound_m_s must be within 300..400 m/s')
        if self.range_sign not in (-1.0, 1.0):
            raise ValueError('range_sign must be -1 or +1')
        if not math.isfinite(self.length_offset_m):
            raise ValueError('length_offset_m must be finite')
        longest_m = max(self.range_to_length_m(r) for r in (self.min_range_m, self.max_range_m))
        if longest_m <= 0:
            raise ValueError(
                f'length_offset_m {self.length_offset_m:g} m with range_sign '
                f'{self.range_sign:+g} gives no muscle length > 0 within the sensor range '
                f'{self.min_range_m:g}..{self.max_range_m:g} m')

    def echo_to_range_m(self, echo_us: float) -> float:
        """Distance to the target [m]; NaN for no echo or a reading outside the sensor's range."""
        if echo_us <= 0:
            return math.nan
        range_m = echo_us * 1e-6 * self.speed_of_sound_m_s / 2.0
        if not self.min_range_m <= range_m <= self.max_range_m:
            return math.nan
        return range_m

    def range_to_length_m(self, range_m: float) -> float:
        return self.length_offset_m + self.range_sign * range_m

    def echo_to_length_m(self, echo_us: float) -> float:
        return self.range_to_length_m(self.echo_to_range_m(echo_us))

    def length_to_echo_us(self, length_m: float) -> int:
        """Echo width an ideal sensor reports for this muscle length (the rig's inverse)."""
        range_m = (length_m - self.length_offset_m) / self.range_sign
        return max(0, round(range_m * 2.0 / self.speed_of_sound_m_s * 1e6))
