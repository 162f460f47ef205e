"""One device sample as the driver's three messages, and its /diagnostics status: pure functions.

No node, no clock, no publishing: the driver calls these and publishes what they return, and
the unit tests check every field.
"""

from __future__ import annotations

import math

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import FluidPressure, Range

from pma_common import protocol
from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_driver.link import LinkState, LinkStats
from pma_interfaces.msg import PmaState

FIELD_OF_VIEW_RAD = 0.26          # HC-SR04: about 15 degrees
FAULT_BITS = (protocol.STATUS_OVERPRESSURE | protocol.STATUS_HEARTBEAT_LOST
              | protocol.STATUS_SENSOR_RANGE)


def to_time_msg(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def sample_messages(sample: protocol.Sample, stamp_ns: int, *, frame_id: str,
                    pressure: PressureCalibration, length: LengthCalibration,
                    ambient_pressure_pa: float) -> tuple[PmaState, FluidPressure, Range]:
    """pma/state, pma/pressure and pma/range for one sample taken at `stamp_ns` (ROS time)."""
    gauge_pa = pressure.adc_to_pa(sample.adc)
    state = PmaState()
    state.header.stamp = to_time_msg(stamp_ns)
    state.header.frame_id = frame_id
    state.seq = sample.seq
    state.device_time_s = sample.t_ms / 1000.0
    state.gauge_pressure_pa = gauge_pa
    state.length_m = length.echo_to_length_m(sample.echo_us)
    state.gauge_setpoint_pa = float(sample.setpoint_pa)
    state.valve_state = sample.valve
    state.status = sample.status
    state.pressure_adc = sample.adc
    state.echo_us = sample.echo_us

    absolute = FluidPressure()
    absolute.header = state.header
    absolute.fluid_pressure = gauge_pa + ambient_pressure_pa
    absolute.variance = pressure.pa_per_count ** 2 / 12.0   # quantisation of one count

    ranged = Range()
    ranged.header = state.header
    ranged.radiation_type = Range.ULTRASOUND
    ranged.field_of_view = FIELD_OF_VIEW_RAD
    ranged.min_range = length.min_range_m
    ranged.max_range = length.max_range_m
    # REP-117: +inf = nothing within range (no echo); NaN = a reading outside the span.
    ranged.range = math.inf if sample.echo_us == 0 else length.echo_to_range_m(sample.echo_us)
    return state, absolute, ranged


def link_level(stats: LinkStats, latest: protocol.Sample | None) -> tuple[bytes, str]:
    """The serial link's diagnostic level and message."""
    state = stats.state
    if state is LinkState.STREAMING:
        if latest is not None and latest.status & FAULT_BITS:
            return (DiagnosticStatus.ERROR,
                    f'device fault: {protocol.status_text(latest.status & FAULT_BITS)}')
        if latest is not None and latest.status & protocol.STATUS_ECHO_TIMEOUT:
            return DiagnosticStatus.WARN, 'streaming; ultrasonic echo timeout'
        return DiagnosticStatus.OK, 'streaming'
    if state in (LinkState.HANDSHAKE, LinkState.STALLED):
        return DiagnosticStatus.WARN, stats.state_detail or state.value
    if state is LinkState.DISCONNECTED and stats.connects:
        return DiagnosticStatus.ERROR, f'disconnected, reconnecting: {stats.state_detail}'
    return DiagnosticStatus.ERROR, stats.state_detail or state.value


def link_values(stats: LinkStats, baud: int) -> dict[str, str]:
    """The link's counters as diagnostic key/values (the node adds its own)."""
    hello = stats.hello
    sequence = stats.sequence
    return {
        'link state': stats.state.value,
        'baud': str(baud),
        'firmware': f'{hello.firmware} {hello.fw_version}' if hello else '-',
        'protocol version': str(hello.proto) if hello else '-',
        'device ceiling at handshake [Pa]': str(hello.ceiling_pa) if hello else '-',
        'device limit [Pa]': str(hello.limit_pa) if hello else '-',
        'samples decoded': str(stats.samples),
        'samples before handshake': str(stats.ignored_before_hello),
        'frames': str(stats.frames),
        'bad frames': str(stats.dropped_total),
        **{f'bad frames ({reason})': str(n) for reason, n in sorted(stats.dropped.items())},
        # By seq: what never came, apart from late, repeated and stray numbers.
        'lost samples': str(sequence.lost),
        'sequence gaps': str(sequence.gaps),
        'late samples': str(sequence.late),
        'duplicate samples': str(sequence.duplicates),
        'stray sequence numbers': str(sequence.stray),
        'sequence restarts': str(sequence.restarts),
        'connects': str(stats.connects),
        'disconnects': str(stats.disconnects),
        'ACK': str(stats.acks), 'NAK': str(stats.naks),
        'command timeouts': str(stats.command_timeouts),
        'last NAK': stats.last_nak or '-',
        'last error': stats.last_error or '-',
    }
