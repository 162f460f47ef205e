"""The simulated device, stepped in device time: commands, control loop and safety rules."""

import itertools

import pytest

from pma_driver import protocol
from pma_driver.calibration import PressureCalibration
from pma_driver.protocol import Ack, FrameDecoder, Hello, Nak, Sample, Valve
from pma_driver.sim.device import DeviceConfig, LinkFaultConfig, LinkFaults, SimDevice, bang_bang

SENSOR = PressureCalibration()


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
    assert host.frames == [Hello(1, 'fake_arduino', '0.1.0', 50, 1000, 500_000, 1000)]
    samples = host.run(1000, heartbeat_ms=200)
    assert [s.seq for s in samples] == list(range(50))
    assert [s.t_ms for s in samples] == list(range(20, 1001, 20))
    assert all(s.valve == Valve.HOLD and s.setpoint_pa == 0 and s.status == 0 for s in samples)


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
    assert frames[1].ceiling_pa == 350_000


@pytest.mark.parametrize('line, answer', [
    (b'$SET,1*00\n', Nak('?', 'CHECKSUM')),
    (protocol.frame('SET'), Nak('SET', 'SYNTAX')),
    (protocol.frame('SET', 'lots'), Nak('SET', 'SYNTAX')),
    (protocol.frame('FLY', 3), Nak('FLY', 'UNKNOWN')),
    (b'garbage\n', Nak('?', 'SYNTAX')),
    (protocol.frame('VENT'), Ack('VENT')),
    (protocol.frame('HB'), Ack('HB')),
])
def test_every_command_line_gets_an_answer(line, answer):
    host = Host()
    host.device.receive(line)
    assert host.read() == [answer]


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
    chunks = [faults.apply(line) for line in lines]
    assert sum(len(c) == 2 for c in chunks) == faults.counts['split']
    decoder = FrameDecoder()
    frames = decoder.feed(b''.join(b''.join(c) for c in chunks))
    assert all(130 < n < 230 for n in faults.counts.values())
    assert len(frames) == 2000 - faults.counts['dropped'] - faults.counts['bad_checksum']
    assert decoder.dropped['checksum'] == faults.counts['bad_checksum']
    assert decoder.dropped_total == faults.counts['bad_checksum'] + faults.counts['garbage']
