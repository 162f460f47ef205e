"""The firmware's own AVR image on simavr, in front of the simulated rig (simavr_arduino).

No wall clock and no ROS here: `Bench` runs the image as fast as simavr goes, in simulated
time, so every figure below is a property of the image (cycles counted by simavr), the same
on any machine. Built by tools/firmware.sh (firmware_build.py), which installs simavr when it
is missing; without it these tests are skipped, saying so.

What the host build (test_firmware_build.py) cannot show: 16-bit `int`, the stack in 8 KiB,
the Arduino core's timers and interrupts, pulseInLong's micros(), the UART at its baud rate.
"""

from __future__ import annotations

import dataclasses
import itertools
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from firmware_build import (
    SIXTEEN_BIT_OVERFLOW,
    mutated_firmware,
    require_simulator,
    run_firmware_script,
    session_build,
)
from test_firmware_build import (
    COMMAND_CASES,
    RIG_DIR,
    SKETCH,
    adc_for,
    command,
    firmware_integers,
    protocol,
    run_rig,
    spec_doc_banner,
)

from pma_common.stop import StopRequest
from pma_sim import simavr_arduino
from pma_sim.device import DeviceConfig, Rig
from pma_sim.simavr_arduino import SimavrDevice

MEGA_VARIANT = Path('/usr/share/arduino/hardware/arduino/avr/variants/mega/pins_arduino.h')
@pytest.fixture(scope='module')
def build():
    return require_simulator(session_build())


@dataclasses.dataclass
class Bench:
    """The image, the rig and a host that writes at chosen device times and reads all."""

    device: SimavrDevice
    rig: Rig
    frames: list = dataclasses.field(default_factory=list)

    @classmethod
    def start(cls, build, seed: int = 0, **config) -> Bench:
        config = DeviceConfig(seed=seed, **config)
        rig = Rig(config)
        return cls(SimavrDevice(config, rig, build.simulator, build.elf), rig)

    def __post_init__(self):
        self._decoder = protocol.FrameDecoder(protocol.parse_device_line)

    @property
    def t_ms(self) -> int:
        return self.device.t_ms

    def run(self, ms: int, heartbeat_ms: int | None = None, step_ms: int = 50) -> None:
        """Advance `ms`, sending HB every `heartbeat_ms` (None: stay silent)."""
        end = self.t_ms + ms
        next_beat = self.t_ms
        while self.t_ms < end:
            if heartbeat_ms is not None and self.t_ms >= next_beat:
                self.send(command('HB'))
                next_beat += heartbeat_ms
            self.device.advance_to(min(end, self.t_ms + step_ms))
            self._read()

    def send(self, *lines: str) -> None:
        self.device.receive(''.join(line + '\n' for line in lines).encode('ascii'))

    def _read(self) -> None:
        self.frames += self._decoder.feed(b''.join(self.device.take_output()))
        assert self._decoder.dropped_total == 0, (self._decoder.dropped,
                                                  self._decoder.last_error)

    def samples(self, since_ms: int = 0) -> list[protocol.Sample]:
        return [f for f in self.frames if isinstance(f, protocol.Sample) and f.t_ms >= since_ms]

    def replies(self) -> list:
        return [f for f in self.frames if not isinstance(f, protocol.Sample)]

    def stats(self) -> simavr_arduino.FirmwareStats:
        return self.device.simulator.stats()

    def close(self) -> None:
        self.device.close()


@pytest.fixture
def bench(build):
    benches: list[Bench] = []

    def start(**config) -> Bench:
        benches.append(Bench.start(build, **config))
        return benches[-1]

    yield start
    for made in benches:
        made.close()


def gaps_ms(samples) -> list[int]:
    return [later.t_ms - earlier.t_ms for earlier, later in itertools.pairwise(samples)]


# ---- Command line ----------------------------------------------------------------------------

def test_options_the_image_has_compiled_in_are_refused_with_the_reason(capsys):
    for argv in (['--rate', '50'], ['--max-rate', '50'], ['--ceiling-pa', '300000'],
                 ['--hb-timeout-ms', '500'], ['--no-heartbeat-check']):
        with pytest.raises(SystemExit) as exited:
            simavr_arduino.parse_args(argv)
        assert exited.value.code == 2
        assert f'{argv[0]} is not for the real firmware: ' in capsys.readouterr().err
    # The image's own values, and fake_arduino's other options, are welcome.
    args = simavr_arduino.parse_args(['--rate', '20', '--seed', '3', '--drop-rate', '0.1'])
    assert (args.seed, args.drop_rate) == (3, 0.1)


def test_a_missing_image_says_how_to_build_it(tmp_path):
    args = simavr_arduino.parse_args(['--firmware', str(tmp_path / 'none.elf'),
                                      '--link', str(tmp_path / 'tty')])
    with pytest.raises(FileNotFoundError,
                       match=r'no (simulator|firmware image) at .*make firmware'):
        simavr_arduino.run(args, StopRequest())
    assert not (tmp_path / 'tty').exists()


# ---- Wiring -------------------------------------------------------------------------------

def mega_pin_table() -> dict[int, str]:
    """Arduino pin number -> port pin ('E3'), from the Mega variant of the Arduino core."""
    rows = re.findall(r'P([A-L])\s+(\d)\s+\*\*\s+(\d+)\s+\*\*', MEGA_VARIANT.read_text())
    return {int(number): port + bit for port, bit, number in rows}


def test_the_simulated_wiring_is_the_sketch_s(build):
    # `build` first: it installs the Arduino core whose pin table this reads.
    pins = firmware_integers()
    table = mega_pin_table()
    assert table[5] == 'E3' and table[13] == 'B7'            # the table reads as expected
    wiring = simavr_arduino.WIRING
    assert table[pins['PIN_INLET_VALVE']] == wiring['inlet']
    assert table[pins['PIN_EXHAUST_VALVE']] == wiring['exhaust']
    assert table[pins['PIN_ULTRASONIC_TRIGGER']] == wiring['trigger']
    assert table[pins['PIN_ULTRASONIC_ECHO']] == wiring['echo']
    assert pins['PIN_PRESSURE_SENSOR'] == f'A{simavr_arduino.PRESSURE_ADC_CHANNEL}'
    sketch = SKETCH.read_text()
    for valve in ('INLET', 'EXHAUST'):
        assert f'const uint8_t {valve}_OPEN_LEVEL = HIGH;' in sketch
        assert getattr(simavr_arduino, f'{valve}_OPEN_LEVEL') == 1
    assert pins['TRIGGER_PULSE_US'] >= simavr_arduino.MIN_TRIGGER_US


# ---- Boot, stream, answer -------------------------------------------------------------------

def test_boots_with_the_banner_and_streams_at_20_hz(bench):
    b = bench()
    b.run(5_000, heartbeat_ms=500)
    banner = b.frames[0]
    assert isinstance(banner, protocol.Hello)
    assert {k: str(v) for k, v in dataclasses.asdict(banner).items()} == spec_doc_banner()
    samples = b.samples()
    assert [s.seq for s in samples] == list(range(len(samples)))
    assert len(samples) in (99, 100)
    assert set(gaps_ms(samples)) <= {49, 50, 51}
    # The rig at rest, through the real ADC and pulseInLong: ~0 kPa and the 30 cm muscle.
    counts = [s.adc for s in samples]
    assert abs(sum(counts) / len(counts) - adc_for(0)) < 1 and max(counts) - min(counts) < 16
    rest_us = b.rig.range_sensor.length_to_echo_us(b.rig.length_m)
    assert all(abs(s.echo_us - rest_us) < 30 for s in samples)
    assert all(s.valve == protocol.Valve.VENT and s.status == 0 for s in samples)
    stats = b.stats()
    assert stats.values['rx_overruns'] == 0 and stats.values['triggers_short'] == 0


def test_stats_answer_before_the_first_step(bench):
    """A stop that comes before the device ever ran still reports the firmware's counters.

    pma_simavr reports the pin levels at power-on before any `run`; stats() once read that
    event as its answer, so simavr_arduino stopped early printed no firmware line (CI, a
    signal test whose burst came right after 'device at').
    """
    b = bench()
    stats = b.stats()
    assert stats.values['loops'] == 0, stats.values
    assert b.device.both_valves_open == 0
    b.run(200, heartbeat_ms=100)
    assert b.stats().values['loops'] > 0
    assert b.samples(), 'the device streams after an early stats'


def test_the_image_answers_every_line_as_the_host_build(bench):
    """The same table of lines and answers as the sketch compiled for the PC."""
    b = bench(pressure_noise_pa=0.0)
    for line, replies in COMMAND_CASES:
        b.rig = b.device.rig = Rig(b.device.config)      # an empty muscle for each line
        b.device.boot()
        b.frames.clear()
        b.run(20)
        b.device.receive(line.encode('latin-1') + b'\n')
        b.run(30)
        assert b.replies()[1:] == replies, line     # [0] is the boot banner


def test_the_echo_is_timed_within_a_few_microseconds_also_under_serial_traffic(bench):
    """An interrupt may delay an edge, never shorten the echo by the time it steals.

    The image once timed the echo with pulseIn, which counts loop turns: every UART interrupt
    during the echo stole some. With commands arriving and their ACKs leaving it read up to
    97 us short (a muscle 17 mm too long; CI saw 0.318 m at rest). pulseInLong times the edges
    with micros() (4 us steps), so each edge is late by at most one interrupt and one turn.
    """
    b = bench(length_noise_m=0.0)
    b.run(3_000, heartbeat_ms=500)
    truth = b.rig.range_sensor.length_to_echo_us(round(b.rig.length_m / 0.003) * 0.003)
    quiet = [s.echo_us - truth for s in b.samples()]
    start = b.t_ms
    for burst in range(100):          # 12 commands a sample, both UART directions kept busy
        b.send(*[command('SET', 0)] * 12)
        b.run(47 + burst % 7)
    busy = [s.echo_us - truth for s in b.samples(since_ms=start + 50)]
    assert len(busy) > 90
    for errors in (quiet, busy):
        assert all(-16 <= error <= 16 for error in errors), sorted(set(errors))
    assert b.stats().values['rx_overruns'] == 0


# ---- Rates, loop time, stack, UART ----------------------------------------------------------

def startup_burst(rate_hz: int) -> list[str]:
    """What driver_node sends back to back after a handshake (parameters.startup_commands)."""
    return [command('HELLO'), command('HBTO', 1000), command('MAX', 500_000),
            command('RATE', rate_hz)]


@pytest.mark.parametrize('rate_hz', [20, 50])
def test_the_rate_holds_without_overruns_while_the_host_talks(bench, rate_hz):
    """Heartbeats at 2 Hz and a new setpoint every second at 20 Hz and at MAX_RATE_HZ (50)."""
    assert firmware_integers()['MAX_RATE_HZ'] == 50
    b = bench()
    b.run(200)
    b.send(*startup_burst(rate_hz))
    b.run(1_000, heartbeat_ms=500)
    b.stats()                                         # the window starts here
    start, sent = b.t_ms, 0
    for second in range(10):
        b.send(command('SET', 100_000 + 20_000 * (second % 5)))
        sent += 1
        b.run(1_000, heartbeat_ms=500)
        sent += 2
    stats = b.stats()
    samples = b.samples(since_ms=start + 100)
    period_ms = 1000 // rate_hz
    assert [s.seq for s in samples] == list(range(samples[0].seq, samples[0].seq + len(samples)))
    assert set(gaps_ms(samples)) <= {period_ms - 1, period_ms, period_ms + 1}
    assert len(samples) >= 9.8 * rate_hz
    acks = [r for r in b.replies() if isinstance(r, protocol.Ack) and r.command in ('SET', 'HB')]
    assert len(acks) >= sent and not [r for r in b.replies() if isinstance(r, protocol.Nak)]
    v = stats.values
    assert v['rx_overruns'] == 0 and v['rx_dropped'] == 0
    # The longest pass of loop() (a sample: echo, four conversions, a line out) fits in a
    # period with room to spare, and the stack stays far from the static data.
    assert stats.window_longest_loop_us < 0.25 * period_ms * 1000
    assert stats.stack_peak_bytes < 256 and stats.free_ram_bytes > 6_000
    tx_share = v['tx_bytes'] * v['cycles_per_byte'] / v['cycle']
    print(f'\n{rate_hz} Hz: {len(samples)} samples in 10 s, gaps {sorted(set(gaps_ms(samples)))}'
          f' ms; longest loop pass {stats.window_longest_loop_us:.0f} us; stack peak '
          f'{stats.stack_peak_bytes} B, free RAM {stats.free_ram_bytes} B; UART TX busy '
          f'{100 * tx_share:.0f} %; RX backlog max {v["rx_backlog_max"]} B, overruns '
          f'{v["rx_overruns"]}')


def test_a_lost_echo_at_50_hz_costs_the_next_sample_too(bench):
    """The HC-SR04 holds Echo high ~38 ms when nothing answers: longer than a 20 ms period."""
    b = bench(echo_timeout_rate=0.2, seed=3)
    b.run(200)
    b.send(command('RATE', 50))
    b.run(5_000, heartbeat_ms=500)
    samples = b.samples(since_ms=500)
    lost = [s.echo_us == 0 for s in samples]
    assert 0.2 < sum(lost) / len(lost) < 0.6
    # Each loss the rig draws is followed by another: the sensor was still busy.
    runs = [len(list(group)) for value, group in itertools.groupby(lost) if value]
    assert min(runs) >= 2
    assert b.stats().values['triggers_ignored'] > 0


# ---- Safety, by the image itself ------------------------------------------------------------

def test_heartbeat_loss_vents_after_the_timeout(bench):
    b = bench()
    b.run(200)
    b.send(command('SET', 200_000))
    b.run(3_000, heartbeat_ms=400)
    assert b.rig.pressure_pa > 180_000
    silent_from = b.t_ms
    b.run(2_500)                                        # the host goes quiet
    after = b.samples(since_ms=silent_from + 1_100)
    assert after and all(s.status & protocol.STATUS_HEARTBEAT_LOST and s.setpoint_pa == 0
                         and s.valve == protocol.Valve.VENT for s in after)
    assert b.rig.pressure_pa < 100_000


def test_a_16_bit_overflow_passes_the_host_build_but_not_the_avr(tmp_path, build):
    """The bug the host build hides: `int` is 32 bits on the PC and 16 on the Mega."""
    broken = mutated_firmware(tmp_path, SIXTEEN_BIT_OVERFLOW)
    # On the PC the broken sketch still regulates: the host build cannot tell.
    compiler = shutil.which('g++')
    if compiler is None:
        pytest.skip('no host C++ compiler (g++) for the host build')
    binary = tmp_path / 'host_rig'
    subprocess.run([compiler, '-std=gnu++11', '-O1', f'-I{RIG_DIR}',
                    f'-I{broken / "pma_firmware"}', str(RIG_DIR / 'host_main.cpp'), '-o',
                    str(binary)], check=True, capture_output=True, timeout=120)
    for gauge_pa, valve in ((150_000, protocol.Valve.FILL), (250_000, protocol.Valve.VENT)):
        run = run_rig(binary, f'!adc {adc_for(gauge_pa)}', '!echo 583',
                      command('SET', 200_000), '!run 60')
        assert run.samples[-1].valve == valve
    # On the AVR every count reads about -60 kPa: it fills past the setpoint and the ceiling
    # to the sensor's end of span, blind to its own overpressure check.
    image = require_simulator(run_firmware_script(tmp_path / 'build', broken))
    b = Bench.start(image)
    try:
        b.run(200)
        b.send(command('SET', 200_000))
        b.run(4_000, heartbeat_ms=400)
        assert b.rig.pressure_pa > firmware_integers()['CEILING_LIMIT_PA']
        after = b.samples(since_ms=1_000)
        assert {s.valve for s in after} <= {protocol.Valve.FILL, protocol.Valve.VENT}
        assert not any(s.status & protocol.STATUS_OVERPRESSURE for s in after)
    finally:
        b.close()
