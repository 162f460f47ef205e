"""The simulated device, stepped in device time: commands, control loop and safety rules."""

import itertools

import pytest

from pma_common import protocol
from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.protocol import Ack, FrameDecoder, Hello, Nak, Sample, Valve
from pma_sim import device as sim
from pma_sim.device import DeviceConfig, LinkFaultConfig, LinkFaults, SimDevice, bang_bang

pytestmark = pytest.mark.in_process

SENSOR = PressureCalibration()
CEILING = sim.COMPILED_CEILING_PA


def largest_adc_at_or_below(pa: float) -> int:
    """The highest ADC count whose (untared) reading is <= pa."""
    return max(adc for adc in range(1024) if SENSOR.adc_to_pa(adc) <= pa)


class Host:
    """Talks to a SimDevice the way the driver would, without a serial port."""

    def __init__(self, **config):
        self.device = SimDevice(DeviceConfig(**config))
        self.decoder = FrameDecoder()
        self.frames = self.read()

    def read(self):
        return self.decoder.feed(b''.join(self.device.take_output()))

    def send(self, command, *args):
        self.device.receive(protocol.encode_command(command, *args))
        return self.read()

    def run(self, ms, heartbeat_ms=None):
        """Advance device time, sending HB every heartbeat_ms; return the samples."""
        frames = []
        for t in range(ms):
            if heartbeat_ms and t % heartbeat_ms == 0:
                frames += self.send('HB')
            self.device.advance(1)
            frames += self.read()
        return [f for f in frames if isinstance(f, Sample)]


def test_boot_banner_then_samples_at_the_configured_rate():
    host = Host(rate_hz=50)
    assert host.frames == [Hello(1, 'fake_arduino', '0.1.0', 50, 1000, 500_000, 500_000, 1000)]
    samples = host.run(1000, heartbeat_ms=200)
    assert [s.seq for s in samples] == list(range(50))
    assert [s.t_ms for s in samples] == list(range(20, 1001, 20))
    # Setpoint 0 at boot: the exhaust is open, as in the firmware.
    assert all(s.valve == Valve.VENT and s.setpoint_pa == 0 and s.status == 0 for s in samples)


def test_set_is_acknowledged_and_reached():
    host = Host(rate_hz=20)
    assert host.send('SET', 300_000) == [Ack('SET', 300_000)]
    samples = host.run(3000, heartbeat_ms=200)
    assert samples[0].valve == Valve.FILL
    settled = [SENSOR.adc_to_pa(s.adc) for s in samples[-10:]]
    assert all(abs(p - 300_000) < 12_000 for p in settled)   # deadband + sensor noise
    assert host.device.rig.length_m < 0.27                    # the muscle contracted


def test_set_above_the_ceiling_or_negative_is_refused_and_changes_nothing():
    host = Host()
    host.send('SET', 200_000)
    assert host.send('SET', 500_001) == [Nak('SET', 'RANGE')]
    assert host.send('SET', -5) == [Nak('SET', 'RANGE')]
    assert host.device.setpoint_pa == 200_000
    assert host.send('MAX', 250_000) == [Ack('MAX', 250_000)]
    assert host.send('SET', 260_000) == [Nak('SET', 'RANGE')]


def test_overpressure_vents_and_latches_until_the_next_set():
    host = Host(rate_hz=100)
    host.send('SET', 400_000)
    host.run(3000, heartbeat_ms=200)
    assert host.device.rig.pressure_pa > 380_000
    # Lower the ceiling under the current pressure: the device must vent on its own.
    assert host.send('MAX', 300_000) == [Ack('MAX', 300_000)]
    samples = host.run(200, heartbeat_ms=100)
    assert samples[-1].status & protocol.STATUS_OVERPRESSURE
    assert samples[-1].valve == Valve.VENT and samples[-1].setpoint_pa == 0
    samples = host.run(3000, heartbeat_ms=200)
    assert host.device.rig.pressure_pa < 20_000
    assert all(s.status & protocol.STATUS_OVERPRESSURE for s in samples)   # latched
    host.send('SET', 100_000)
    samples = host.run(100, heartbeat_ms=50)
    assert samples[-1].status == 0 and samples[-1].valve == Valve.FILL


def test_heartbeat_loss_vents_and_hello_clears_the_bit():
    host = Host(rate_hz=100)
    host.send('SET', 200_000)
    samples = host.run(1500, heartbeat_ms=300)
    assert not any(s.status for s in samples)
    pressure = host.device.rig.pressure_pa
    samples = host.run(1200)                                # host silent
    lost = [s for s in samples if s.status & protocol.STATUS_HEARTBEAT_LOST]
    assert lost and lost[0].t_ms - samples[0].t_ms >= 1000 - 300 - 10
    assert all(s.valve == Valve.VENT and s.setpoint_pa == 0 for s in lost)
    assert host.device.rig.pressure_pa < pressure
    frames = host.send('HELLO')
    assert frames[0] == Ack('HELLO') and isinstance(frames[1], Hello)
    samples = host.run(100, heartbeat_ms=50)
    assert samples[-1].status == 0 and samples[-1].valve == Valve.VENT   # vents until a SET


def test_heartbeat_check_can_be_disabled():
    host = Host(heartbeat_check=False)
    samples = host.run(3000)
    assert not any(s.status & protocol.STATUS_HEARTBEAT_LOST for s in samples)


def test_hbto_sets_the_timeout_within_its_range():
    host = Host(rate_hz=100)
    assert host.send('HBTO', 99) == [Nak('HBTO', 'RANGE')]
    assert host.send('HBTO', 10_001) == [Nak('HBTO', 'RANGE')]
    assert host.send('HBTO', 200) == [Ack('HBTO', 200)]
    samples = host.run(300)
    first_lost = next(s for s in samples if s.status & protocol.STATUS_HEARTBEAT_LOST)
    assert 200 <= first_lost.t_ms <= 215


def test_rate_changes_the_sample_period():
    host = Host(rate_hz=20)
    assert host.send('RATE', 0) == [Nak('RATE', 'RANGE')]
    assert host.send('RATE', 1001) == [Nak('RATE', 'RANGE')]
    assert host.send('RATE', 1000) == [Ack('RATE', 1000)]
    samples = host.run(500, heartbeat_ms=100)
    assert len(samples) == 500
    host.send('RATE', 300)
    samples = host.run(1000, heartbeat_ms=100)
    assert len(samples) == 300                             # no drift with a 3.33 ms period
    assert {b.t_ms - a.t_ms for a, b in itertools.pairwise(samples)} == {3, 4}


def test_tare_window_and_span_are_the_firmware_s():
    window = sim.TARE_MAX_OFFSET_PA
    assert window == 25_000
    inside = largest_adc_at_or_below(window)
    below_span = largest_adc_at_or_below(-window * 0.5)   # 0.33 V: out of span, near zero
    assert not SENSOR.adc_in_span(below_span) and abs(SENSOR.adc_to_pa(below_span)) < window
    for adc, answer in [(inside, Ack('TARE', inside)), (inside + 1, Nak('TARE', 'RANGE')),
                        (below_span, Nak('TARE', 'RANGE'))]:
        host = Host()
        host.device.rig.pressure_sensor_fault_adc = adc
        assert host.send('TARE') == [answer], adc


def test_tare_only_near_zero_pressure():
    host = Host()
    frames = host.send('TARE')
    assert frames == [Ack('TARE', host.device.tare_adc)]
    assert abs(SENSOR.adc_to_pa(frames[0].value)) < 5_000
    host.send('SET', 150_000)
    host.run(2000, heartbeat_ms=200)
    assert host.send('TARE') == [Nak('TARE', 'RANGE')]


def test_max_range_and_setpoint_clamp():
    host = Host()
    assert host.send('MAX', 0) == [Nak('MAX', 'RANGE')]
    assert host.send('MAX', 500_001) == [Nak('MAX', 'RANGE')]
    host.send('SET', 400_000)
    assert host.send('MAX', 350_000) == [Ack('MAX', 350_000)]
    assert host.device.setpoint_pa == 350_000
    frames = host.send('HELLO')
    # The current ceiling, and the compiled limit a host may raise it back to.
    assert (frames[1].ceiling_pa, frames[1].limit_pa) == (350_000, CEILING)
    assert host.send('MAX', CEILING) == [Ack('MAX', CEILING)]
    assert host.send('HELLO')[1].ceiling_pa == CEILING


@pytest.mark.parametrize('line, answer', [
    (b'$SET,1*00\n', Nak('?', 'CHECKSUM')),
    (b'$HB\n', Nak('?', 'SYNTAX')),
    (b'$HB*+A\n', Nak('?', 'SYNTAX')),
    (protocol.frame('SET'), Nak('SET', 'SYNTAX')),
    (protocol.frame('SET', 'lots'), Nak('SET', 'SYNTAX')),
    (protocol.frame('SET', '99999999999999999999'), Nak('SET', 'RANGE')),   # saturates
    (protocol.frame('FLY', 3), Nak('FLY', 'UNKNOWN')),
    (protocol.frame('X' * 40), Nak('X' * sim.NAK_NAME_MAX, 'UNKNOWN')),
    (protocol.frame('VENT'), Ack('VENT')),
    (protocol.frame('HB'), Ack('HB')),
    (protocol.frame('HB')[:-1] + b'\r\n', Ack('HB')),
])
def test_every_command_line_gets_an_answer(line, answer):
    host = Host()
    host.device.receive(line)
    assert host.read() == [answer]


@pytest.mark.parametrize('line, counted', [
    (b'garbage\n', 1),                                   # no '$'
    (b'x' + protocol.frame('HB'), 1),                     # bytes before the '$'
    (b'\r\n', 0), (b'  \n', 0),                           # blank: skipped, not counted
    (b'$SET,' + b'0' * 100 + b'*00\n', 1),                # overlong, complete
    (b'X' * 300, 1),                                     # overlong, no newline yet
])
def test_lines_the_firmware_drops_get_no_answer_and_are_no_heartbeat(line, counted):
    host = Host(rate_hz=100)
    host.device.advance(900)
    host.read()
    host.device.receive(line)
    assert host.read() == []
    assert host.device.decoder_dropped.total() == counted
    samples = host.run(200)
    assert samples[-1].status & protocol.STATUS_HEARTBEAT_LOST   # no heartbeat credit


def test_overpressure_trips_above_ceiling_plus_the_margin_only():
    assert sim.OVERPRESSURE_MARGIN_PA == 10_000
    limit = CEILING + sim.OVERPRESSURE_MARGIN_PA
    within = largest_adc_at_or_below(limit)              # 509.96 kPa: regulated, not tripped
    for adc, trips in [(within, False), (within + 1, True)]:
        host = Host(rate_hz=100)
        host.send('SET', CEILING)
        host.device.rig.pressure_sensor_fault_adc = adc
        samples = host.run(100, heartbeat_ms=50)
        assert bool(samples[-1].status & protocol.STATUS_OVERPRESSURE) == trips, adc
        assert samples[-1].valve == Valve.VENT               # above the band either way
        assert samples[-1].setpoint_pa == (0 if trips else CEILING)


def test_holding_the_ceiling_itself_never_trips():
    host = Host(rate_hz=50)
    assert host.send('SET', CEILING) == [Ack('SET', CEILING)]
    samples = host.run(8000, heartbeat_ms=200)
    assert host.device.rig.pressure_pa > CEILING - 10_000
    assert not any(s.status for s in samples)
    assert all(s.setpoint_pa == CEILING for s in samples)


def test_sensor_out_of_span_vents_and_flags_without_latching():
    host = Host(rate_hz=100)
    host.send('SET', 250_000)
    host.run(2000, heartbeat_ms=200)
    host.device.rig.pressure_sensor_fault_adc = 0            # unplugged: the input reads 0
    pressure = host.device.rig.pressure_pa
    samples = host.run(500, heartbeat_ms=200)[2:]
    assert all(s.adc == 0 and s.status == protocol.STATUS_SENSOR_RANGE for s in samples)
    assert all(s.valve == Valve.VENT and s.setpoint_pa == 250_000 for s in samples)
    assert host.device.rig.pressure_pa < pressure - 100_000  # really vented
    host.device.rig.pressure_sensor_fault_adc = None         # plugged back: regulation resumes
    samples = host.run(100, heartbeat_ms=50)
    assert samples[-1].status == 0 and samples[-1].valve == Valve.FILL


def test_setpoint_zero_vents_even_at_zero_pressure():
    host = Host(rate_hz=100)
    host.send('SET', 50_000)
    host.run(1000, heartbeat_ms=200)
    assert host.send('SET', 0) == [Ack('SET', 0)]
    samples = host.run(5000, heartbeat_ms=200)
    assert abs(host.device.rig.pressure_pa) < 1_000
    assert all(s.valve == Valve.VENT for s in samples)


def test_each_reading_is_the_rounded_mean_of_four_conversions_every_5_ms():
    host = Host(rate_hz=1)
    conversions = []

    def conversion():
        conversions.append(300 + len(conversions) % 4 // 2)   # 300, 300, 301, 301, ...
        return conversions[-1]

    host.device.rig.read_adc = conversion
    host.device.advance(100)
    assert len(conversions) == 20 * sim.ADC_OVERSAMPLING      # a reading at 5, 10, ... 100 ms
    assert host.device.last_adc == 301                        # 1202 / 4 = 300.5: rounded up
    samples = host.run(1000, heartbeat_ms=200)
    assert samples[0].adc == 301


def test_echo_times_out_beyond_the_firmware_s_range():
    length = Host().device.rig.length_m
    for range_m, timed_out in [(0.90, False), (1.00, True)]:
        host = Host(rate_hz=100)
        host.device.rig.range_sensor = LengthCalibration(length_offset_m=length + range_m)
        samples = host.run(200, heartbeat_ms=100)
        echoes = {s.echo_us == 0 for s in samples}
        assert echoes == {timed_out}, range_m
        assert all(bool(s.status & protocol.STATUS_ECHO_TIMEOUT) == timed_out for s in samples)


def test_vent_opens_the_exhaust_until_the_next_set():
    host = Host(rate_hz=100)
    host.send('SET', 300_000)
    host.run(2000, heartbeat_ms=200)
    host.send('VENT')
    samples = host.run(3000, heartbeat_ms=200)
    assert all(s.valve == Valve.VENT and s.setpoint_pa == 0 for s in samples)
    assert host.device.rig.pressure_pa < 10_000


def test_reboot_restarts_clock_and_counters_but_not_the_physics():
    host = Host(rate_hz=100)
    host.send('SET', 300_000)
    host.run(2000, heartbeat_ms=200)
    pressure = host.device.rig.pressure_pa
    host.device.boot()
    assert isinstance(host.read()[0], Hello)
    samples = host.run(100, heartbeat_ms=50)
    assert samples[0].seq == 0 and samples[0].t_ms == 10 and samples[0].setpoint_pa == 0
    assert SENSOR.adc_to_pa(samples[0].adc) == pytest.approx(pressure, abs=15_000)


def test_bang_bang_band():
    assert bang_bang(90_000, 100_000, 5_000) == Valve.FILL
    assert bang_bang(96_000, 100_000, 5_000) == Valve.HOLD
    assert bang_bang(104_000, 100_000, 5_000) == Valve.HOLD
    assert bang_bang(106_000, 100_000, 5_000) == Valve.VENT


def test_echo_timeouts_are_flagged():
    host = Host(rate_hz=1000, echo_timeout_rate=0.2)
    samples = host.run(1000, heartbeat_ms=200)
    timeouts = [s for s in samples if s.echo_us == 0]
    assert 140 < len(timeouts) < 260
    assert all(s.status & protocol.STATUS_ECHO_TIMEOUT for s in timeouts)
    assert not any(s.status & protocol.STATUS_ECHO_TIMEOUT for s in samples if s.echo_us)


def test_same_seed_same_bytes_other_seed_other_noise():
    def run(seed):
        device = SimDevice(DeviceConfig(rate_hz=100, seed=seed))
        device.receive(protocol.encode_command('SET', 250_000))
        device.advance(1500)
        return device.take_output()
    assert run(1) == run(1)
    assert run(1) != run(2)


def test_link_faults_do_what_they_say():
    lines = [protocol.encode_sample(Sample(i, i, 500, 600, 0, 0, 0)) for i in range(2000)]
    faults = LinkFaults(LinkFaultConfig(garbage_rate=0.1, bad_checksum_rate=0.1, drop_rate=0.1,
                                        split_rate=0.1), seed=4)
    faulted = [faults.apply(line) for line in lines]
    chunks = [f.chunks for f in faulted]
    assert sum(len(c) == 2 for c in chunks) == faults.counts['split']
    for name in faults.counts:
        assert sum(name in f.faults for f in faulted) == faults.counts[name]
    decoder = FrameDecoder()
    frames = decoder.feed(b''.join(b''.join(c) for c in chunks))
    assert all(130 < n < 230 for n in faults.counts.values())
    assert len(frames) == 2000 - faults.counts['dropped'] - faults.counts['bad_checksum']
    assert decoder.dropped['checksum'] == faults.counts['bad_checksum']
    assert decoder.dropped_total == faults.counts['bad_checksum'] + faults.counts['garbage']
