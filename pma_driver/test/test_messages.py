"""A sample as the driver's three messages, and the link's diagnostics: pure functions."""

from __future__ import annotations

import math

import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import Range

from pma_common import protocol
from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.protocol import Hello, Sample
from pma_common.sequence import SequenceStats
from pma_driver.link import LinkState, LinkStats
from pma_driver.messages import link_level, link_values, sample_messages

pytestmark = pytest.mark.in_process

PRESSURE = PressureCalibration()
LENGTH = LengthCalibration()


def convert(sample: Sample, stamp_ns: int = 1_700_000_000_123_456_789):
    return sample_messages(sample, stamp_ns, frame_id='pma_link', pressure=PRESSURE,
                           length=LENGTH, ambient_pressure_pa=101_325.0)


def test_a_sample_becomes_state_pressure_and_range_with_one_stamp():
    echo_us = LENGTH.length_to_echo_us(0.28)
    state, pressure, ranged = convert(Sample(41, 2050, 512, echo_us, 1, 200_000, 0))
    assert (state.header.stamp.sec, state.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert pressure.header == state.header == ranged.header
    assert state.header.frame_id == 'pma_link'
    assert (state.seq, state.device_time_s, state.pressure_adc, state.echo_us) == (
        41, 2.05, 512, echo_us)
    assert state.gauge_pressure_pa == PRESSURE.adc_to_pa(512)
    assert state.length_m == pytest.approx(0.28, abs=0.001)
    assert (state.gauge_setpoint_pa, state.valve_state, state.status) == (200_000.0, 1, 0)
    assert pressure.fluid_pressure == PRESSURE.adc_to_pa(512) + 101_325.0   # absolute
    assert pressure.variance == pytest.approx(PRESSURE.pa_per_count ** 2 / 12)
    assert ranged.radiation_type == Range.ULTRASOUND
    assert ranged.range == pytest.approx(0.12, abs=0.001)
    assert (ranged.min_range, ranged.max_range) == pytest.approx((0.02, 4.0))


def test_no_echo_is_infinitely_far_and_a_reading_outside_the_span_is_nan():   # REP-117
    state, _, ranged = convert(Sample(1, 0, 102, 0, 2, 0, protocol.STATUS_ECHO_TIMEOUT))
    assert ranged.range == math.inf and math.isnan(state.length_m)
    state, _, ranged = convert(Sample(1, 0, 102, 30_000, 2, 0, 0))    # 5.1 m: beyond 4 m
    assert math.isnan(ranged.range) and math.isnan(state.length_m)


def stats(state: LinkState = LinkState.STREAMING, **changes) -> LinkStats:
    fields = dict(state=state, state_detail='', frames=10, samples=9,
                  hello=Hello(1, 'fake_arduino', '0.1.0', 20, 1000, 500_000, 500_000, 1000),
                  dropped={'checksum': 2}, sequence=SequenceStats(9, 3, 1, 1, 2, 1, 0),
                  acks=4, naks=1, command_timeouts=0, connects=1, disconnects=0,
                  last_error='', last_nak='SET RANGE', ignored_before_hello=0)
    return LinkStats(**{**fields, **changes})


@pytest.mark.parametrize(('link', 'status', 'level', 'message'), [
    (stats(), 0, DiagnosticStatus.OK, 'streaming'),
    (stats(), protocol.STATUS_ECHO_TIMEOUT, DiagnosticStatus.WARN,
     'streaming; ultrasonic echo timeout'),
    (stats(), protocol.STATUS_HEARTBEAT_LOST, DiagnosticStatus.ERROR,
     'device fault: heartbeat lost (device vented)'),
    (stats(LinkState.STALLED, state_detail='no data from P for 1.2 s'), 0,
     DiagnosticStatus.WARN, 'no data from P for 1.2 s'),
    (stats(LinkState.DISCONNECTED, state_detail='lost P'), 0, DiagnosticStatus.ERROR,
     'disconnected, reconnecting: lost P'),
])
def test_the_link_level_says_what_is_wrong(link, status, level, message):
    assert link_level(link, Sample(1, 0, 102, 583, 2, 0, status)) == (level, message)


def test_the_link_values_count_the_sequence_by_kind():
    values = link_values(stats(), 115200)
    assert values['firmware'] == 'fake_arduino 0.1.0' and values['protocol version'] == '1'
    assert (values['lost samples'], values['sequence gaps'], values['late samples'],
            values['duplicate samples'], values['stray sequence numbers']) == (
        '3', '1', '1', '2', '1')
    assert values['bad frames'] == '2' and values['bad frames (checksum)'] == '2'
