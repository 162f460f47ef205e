"""The Arduino Mega 2560 firmware (pma_driver/firmware/pma_firmware/).

Four kinds of check:
* it compiles for the atmega2560 with the real AVR toolchain (tools/firmware.sh, which installs
  the toolchain when missing), and a broken sketch fails that build;
* its constants agree with their other homes: the pin table in docs/hardware.md, protocol.py,
  calibration.py (pma_common), docs/serial-protocol.md and the simulated rig (pma_sim/device.py);
* the unmodified sketch, compiled for the PC against a simulated rig
  (test/firmware_host/), behaves as the protocol says, judged by the host's own parser;
* the simulated rig (fake_arduino's device) answers the same command lines the same way.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import itertools
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from firmware_build import (
    EXIT_NO_SIMULATOR,
    require_image,
    run_firmware_script,
    session_build,
)

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE_DIR = ROOT / 'pma_driver' / 'firmware'
SKETCH_DIR = FIRMWARE_DIR / 'pma_firmware'
SKETCH = SKETCH_DIR / 'pma_firmware.ino'
PROTOCOL_HEADER = SKETCH_DIR / 'pma_protocol.h'
HARDWARE_DOC = ROOT / 'docs' / 'hardware.md'
PROTOCOL_DOC = ROOT / 'docs' / 'serial-protocol.md'
RIG_DIR = Path(__file__).resolve().parent / 'firmware_host'


def _load(name: str):
    """Import a module of pma_common from its file, whether or not the package is installed."""
    path = ROOT / 'pma_common' / 'pma_common' / f'{name}.py'
    spec = importlib.util.spec_from_file_location(f'_firmware_test_{name}', path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while being built
    spec.loader.exec_module(module)
    return module


protocol = _load('protocol')
calibration = _load('calibration')


# ---- Reading the sources -------------------------------------------------------------------

def _strip_comments(source: str) -> str:
    return re.sub(r'//[^\n]*', '', source)


def firmware_integers() -> dict[str, int | str]:
    """`const <type> NAME = value;` of the sketch and its header (values as written if not int)."""
    constants: dict[str, int | str] = {}
    for path in (PROTOCOL_HEADER, SKETCH):
        pattern = r'const\s+\w+\s+([A-Z][A-Z0-9_]*)\s*=\s*([^;]+);'
        for name, written in re.findall(pattern, _strip_comments(path.read_text())):
            value = written.strip()
            constants[name] = int(value.rstrip('UL')) if re.fullmatch(r'-?\d+U?L*', value) \
                else value
    return constants


def firmware_strings() -> dict[str, str]:
    """`const char NAME[] [PROGMEM] = "text";` of the sketch and its header."""
    pattern = r'const\s+char\s+([A-Z][A-Z0-9_]*)\[\]\s*(?:PROGMEM\s*)?=\s*"([^"]*)"'
    strings: dict[str, str] = {}
    for path in (PROTOCOL_HEADER, SKETCH):
        strings.update(re.findall(pattern, _strip_comments(path.read_text())))
    return strings


def firmware_command_table() -> dict[str, int]:
    """Command name -> argument count, from the sketch's COMMANDS table."""
    table = re.search(r'COMMANDS\[\]\s*PROGMEM\s*=\s*\{(.*?)\};', SKETCH.read_text(), re.S)
    assert table, 'no COMMANDS table in the sketch'
    strings = firmware_strings()
    rows = re.findall(r'\{\s*(COMMAND_\w+)\s*,\s*(\d+)\s*,\s*\w+\s*\}', table.group(1))
    return {strings[name]: int(count) for name, count in rows}


def hardware_doc_pins() -> dict[str, str]:
    """Firmware constant -> pin, from the pin table of docs/hardware.md."""
    pins = {}
    for line in HARDWARE_DOC.read_text().splitlines():
        cells = [cell.strip() for cell in line.strip().strip('|').split('|')]
        constants = [c.strip('`') for c in cells if re.fullmatch(r'`PIN_\w+`', c)]
        if line.startswith('|') and constants:
            pins[constants[0]] = cells[1]
    return pins


def spec_doc_banner() -> dict[str, str]:
    """The example HELLO banner of docs/serial-protocol.md, field name -> text."""
    match = re.search(r'^device \$HELLO,([^*]+)\*', PROTOCOL_DOC.read_text(), re.M)
    assert match, 'no example device HELLO banner in the protocol spec'
    names = [field.name for field in dataclasses.fields(protocol.Hello)]
    values = match.group(1).split(',')
    assert len(values) == len(names)
    return dict(zip(names, values, strict=True))


def spec_doc_range(command: str) -> tuple[int, int]:
    """`outside LOW..HIGH` from the command's row of the spec's host-to-device table."""
    for line in PROTOCOL_DOC.read_text().splitlines():
        if line.startswith(f'| `{command}` |'):
            match = re.search(r'outside (\d+)\.\.(\d+)', line)
            assert match, f'no "outside LOW..HIGH" in the spec row of {command}'
            return int(match.group(1)), int(match.group(2))
    raise AssertionError(f'no row for {command} in the spec')


# ---- The AVR build -------------------------------------------------------------------------

@pytest.fixture(scope='module')
def avr_build():
    """This checkout's image (and simulator), built once per session by tools/firmware.sh."""
    return require_image(session_build())


def test_firmware_compiles_for_the_mega_2560(avr_build):
    build_dir, result = avr_build.build_dir, avr_build.result
    output = avr_build.output
    # EXIT_NO_SIMULATOR: the image built, only simavr (test_firmware_simavr.py) is missing.
    assert result.returncode in (0, EXIT_NO_SIMULATOR), output
    flash = re.search(r'flash: (\d+) bytes of (\d+)', output)
    ram = re.search(r'RAM: +(\d+) bytes of (\d+)', output)
    assert flash and ram, output
    # The numbers are avr-size's: cross-check them against the image itself.
    hex_lines = (build_dir / 'pma_firmware.hex').read_text().split()
    assert hex_lines and all(line.startswith(':') for line in hex_lines)
    data_bytes = sum(int(line[1:3], 16) for line in hex_lines if line[7:9] == '00')
    assert data_bytes == int(flash.group(1))
    assert 1000 < int(flash.group(1)) < int(flash.group(2))
    # Static RAM well under the Mega's 8 KiB, leaving the rest for the stack.
    assert int(ram.group(1)) < int(ram.group(2)) // 4
    elf = (build_dir / 'pma_firmware.elf').read_bytes()
    em_avr = 83
    assert elf[:4] == b'\x7fELF' and int.from_bytes(elf[18:20], 'little') == em_avr
    assert b'atmega2560' in (build_dir / 'build.log').read_bytes()


@pytest.mark.parametrize(('mutation', 'message'), [
    ('int setpointPa = this is not C++;', 'FIRMWARE BUILD FAILED'),
    ('int unusedHelper() { int unused = 1; return 0; }', 'HAS WARNINGS'),
])
def test_a_broken_sketch_fails_the_build(avr_build, tmp_path, mutation, message):
    assert avr_build.result.returncode in (0, EXIT_NO_SIMULATOR), 'the real sketch must build'
    firmware_copy = tmp_path / 'firmware'
    shutil.copytree(FIRMWARE_DIR, firmware_copy)
    sketch = firmware_copy / 'pma_firmware' / 'pma_firmware.ino'
    sketch.write_text(sketch.read_text() + '\n' + mutation + '\n')
    result = run_firmware_script(tmp_path / 'build', firmware_copy).result
    assert result.returncode == 1
    assert message in result.stdout
    assert 'pma_firmware.ino:' in result.stdout + result.stderr


# ---- Constants against their other homes ---------------------------------------------------

def test_pin_constants_match_the_wiring_table():
    sketch_pins = {name: str(value) for name, value in firmware_integers().items()
                   if name.startswith('PIN_')}
    assert len(sketch_pins) >= 5
    assert hardware_doc_pins() == sketch_pins


def test_protocol_constants_match_protocol_py():
    integers = firmware_integers()
    strings = firmware_strings()
    assert integers['PROTOCOL_VERSION'] == protocol.PROTOCOL_VERSION
    assert integers['MAX_LINE_BYTES'] == protocol.MAX_LINE_BYTES

    status_bits = {name: value for name, value in vars(protocol).items()
                   if name.startswith('STATUS_') and isinstance(value, int)}
    assert status_bits
    assert {n: v for n, v in integers.items() if n.startswith('STATUS_')} == status_bits

    def named(prefix, values):
        return {name[len(prefix):]: value for name, value in values.items()
                if name.startswith(prefix)}

    assert named('COMMAND_', strings) == {m.name: m.value for m in protocol.Command}
    assert named('NAK_', strings) == {m.name: m.value for m in protocol.NakReason}
    assert named('VALVE_', integers) == {m.name: m.value for m in protocol.Valve}
    assert firmware_command_table() == protocol.COMMAND_ARITY

    # Any other constant both files define must agree too (defaults, when protocol.py has them).
    shared = {name for name in vars(protocol) if name.isupper()} & set(integers)
    for name in shared:
        assert integers[name] == getattr(protocol, name), name


def test_defaults_and_limits_match_the_protocol_spec():
    integers = firmware_integers()
    strings = firmware_strings()
    banner = spec_doc_banner()
    assert integers['PROTOCOL_VERSION'] == int(banner['proto'])
    assert strings['FIRMWARE_NAME'] == banner['firmware']
    assert integers['DEFAULT_RATE_HZ'] == int(banner['rate_hz'])
    assert integers['MAX_RATE_HZ'] == int(banner['max_rate_hz'])
    assert integers['CEILING_LIMIT_PA'] == int(banner['ceiling_pa'])
    assert integers['CEILING_LIMIT_PA'] == int(banner['limit_pa'])
    assert integers['DEFAULT_HEARTBEAT_TIMEOUT_MS'] == int(banner['hb_timeout_ms'])
    assert (integers['MIN_HEARTBEAT_TIMEOUT_MS'], integers['MAX_HEARTBEAT_TIMEOUT_MS']) \
        == spec_doc_range('HBTO')


def test_the_spec_s_example_lines_are_valid_frames():
    lines = re.findall(r'^(?:host|device) +(\$\S+)$', PROTOCOL_DOC.read_text(), re.M)
    assert len(lines) >= 6
    for line in lines:
        protocol.split_frame(line.encode('ascii'))   # raises on a wrong checksum


def test_the_spec_states_the_firmware_s_safety_numbers():
    integers = firmware_integers()
    text = ' '.join(PROTOCOL_DOC.read_text().split())
    for name in ('OVERPRESSURE_MARGIN_PA', 'TARE_MAX_OFFSET_PA', 'DEADBAND_PA'):
        assert f'{integers[name] // 1000} kPa' in text, name
    assert f'{integers["REGULATION_PERIOD_MS"]} ms' in text
    assert f'{integers["ECHO_TIMEOUT_US"] // 1000} ms' in text


def test_sensor_constants_match_calibration_py():
    integers = firmware_integers()
    defaults = calibration.PressureCalibration()
    assert integers['ADC_FULL_SCALE'] == calibration.ADC_FULL_SCALE
    assert integers['ADC_REFERENCE_MV'] == round(defaults.adc_reference_v * 1000)
    assert integers['SENSOR_ZERO_MV'] == round(defaults.volts_at_zero * 1000)
    assert integers['SENSOR_FULL_MV'] == round(defaults.volts_at_full * 1000)
    assert integers['SENSOR_FULL_SCALE_PA'] == round(defaults.full_scale_pa)
    margin_v = inspect.signature(defaults.adc_in_span).parameters['margin_v'].default
    assert integers['SENSOR_SPAN_MARGIN_MV'] == round(margin_v * 1000)


# ---- The sketch on a simulated rig ---------------------------------------------------------

@pytest.fixture(scope='module')
def rig_binary(tmp_path_factory):
    compiler = shutil.which('g++')
    if compiler is None:
        pytest.skip('no host C++ compiler (g++) for the simulated rig')
    binary = tmp_path_factory.mktemp('rig') / 'firmware_rig'
    subprocess.run([compiler, '-std=gnu++11', '-O1', '-Wall', '-Wextra', f'-I{RIG_DIR}',
                    f'-I{SKETCH_DIR}', str(RIG_DIR / 'host_main.cpp'), '-o', str(binary)],
                   check=True, capture_output=True, text=True, timeout=120)
    return binary


@dataclasses.dataclass
class RigRun:
    frames: list
    pins: list[tuple[int, int]]

    @property
    def samples(self):
        return [f for f in self.frames if isinstance(f, protocol.Sample)]

    @property
    def replies(self):
        return [f for f in self.frames if not isinstance(f, protocol.Sample)]


def command(name: str, *args: int) -> str:
    return protocol.encode_command(name, *args).decode('ascii').rstrip('\n')


def raw_command(body: str) -> str:
    """A frame with a correct checksum around any body (for malformed commands)."""
    return protocol.frame(body).decode('ascii').rstrip('\n')


def adc_for(gauge_pa: float) -> int:
    return calibration.PressureCalibration().pa_to_adc(gauge_pa)


def largest_adc_at_or_below(gauge_pa: float) -> int:
    """The highest ADC count whose (untared) reading is at most gauge_pa."""
    sensor = calibration.PressureCalibration()
    return max(adc for adc in range(1024) if sensor.adc_to_pa(adc) <= gauge_pa)


def run_rig(binary: Path, *items: str, start_us: int = 0) -> RigRun:
    script = '\n'.join(items) + '\n'
    result = subprocess.run([str(binary), str(start_us)], input=script.encode('ascii'),
                            capture_output=True, timeout=60, check=False)
    assert result.returncode == 0, result.stdout.decode(errors='replace')[-2000:]
    decoder = protocol.FrameDecoder(protocol.parse_device_line)
    frames, pins = [], []
    for line in result.stdout.splitlines(keepends=True):
        if line.startswith(b'!pins'):
            inlet, exhaust = line.split()[1:]
            pins.append((int(inlet), int(exhaust)))
        else:
            frames += decoder.feed(line)
    # Every byte the firmware sent must pass the host's parser.
    assert decoder.dropped_total == 0, (decoder.dropped, decoder.last_error)
    return RigRun(frames, pins)


def gaps_ms(samples) -> list[int]:
    return [later.t_ms - earlier.t_ms for earlier, later in itertools.pairwise(samples)]


IDLE_RIG = ('!adc ' + str(adc_for(0)), '!echo 583')


def test_boot_banner_then_samples_on_a_steady_20_hz_schedule(rig_binary):
    # A slow loop (0.7 ms a pass) makes each sample start late; the schedule must not drift.
    run = run_rig(rig_binary, *IDLE_RIG, '!loop_us 700', '!run 10000')
    banner = run.frames[0]
    doc = spec_doc_banner()
    assert isinstance(banner, protocol.Hello)
    assert {k: str(v) for k, v in dataclasses.asdict(banner).items()} == doc
    samples = run.samples
    assert [s.seq for s in samples] == list(range(len(samples)))
    assert len(samples) in (199, 200)
    gaps = gaps_ms(samples)
    assert set(gaps) <= {49, 50, 51}
    # No drift: a period stretched by each sample's lateness would add up over 200 samples.
    assert (samples[-1].t_ms - samples[0].t_ms) == pytest.approx(50 * len(gaps), abs=1)
    assert all(s.echo_us == 583 and s.adc == adc_for(0) for s in samples)
    # Setpoint 0 at boot: the exhaust stays open.
    assert all(s.valve == protocol.Valve.VENT and s.setpoint_pa == 0 for s in samples)


def test_schedule_survives_the_micros_wrap(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, '!run 3000', start_us=2**32 - 1_000_000)
    samples = run.samples
    assert len(samples) in (59, 60)
    gaps = gaps_ms(samples)
    assert set(gaps) <= {49, 50, 51}


CEILING = 500_000
COMMAND_CASES = [
    (command('HB'), [protocol.Ack('HB')]),
    (command('SET', 250_000), [protocol.Ack('SET', 250_000)]),
    (command('SET', 0), [protocol.Ack('SET', 0)]),
    (command('SET', CEILING), [protocol.Ack('SET', CEILING)]),
    (command('SET', CEILING + 1), [protocol.Nak('SET', 'RANGE')]),
    (command('SET', -1), [protocol.Nak('SET', 'RANGE')]),
    (command('SET', 2**32 - 1), [protocol.Nak('SET', 'RANGE')]),
    (raw_command('SET,99999999999999999999'), [protocol.Nak('SET', 'RANGE')]),
    (command('VENT'), [protocol.Ack('VENT')]),
    (command('RATE', 50), [protocol.Ack('RATE', 50)]),
    (command('RATE', 0), [protocol.Nak('RATE', 'RANGE')]),
    (command('RATE', 51), [protocol.Nak('RATE', 'RANGE')]),
    (command('HBTO', 100), [protocol.Ack('HBTO', 100)]),
    (command('HBTO', 10_000), [protocol.Ack('HBTO', 10_000)]),
    (command('HBTO', 99), [protocol.Nak('HBTO', 'RANGE')]),
    (command('HBTO', 10_001), [protocol.Nak('HBTO', 'RANGE')]),
    (command('MAX', 300_000), [protocol.Ack('MAX', 300_000)]),
    (command('MAX', 0), [protocol.Nak('MAX', 'RANGE')]),
    (command('MAX', CEILING + 1), [protocol.Nak('MAX', 'RANGE')]),
    (command('TARE'), [protocol.Ack('TARE', adc_for(0))]),
    (command('FOO'), [protocol.Nak('FOO', 'UNKNOWN')]),
    (command('X' * 40), [protocol.Nak('X' * 12, 'UNKNOWN')]),     # the echo is cut
    (raw_command('SET,-99999999999'), [protocol.Nak('SET', 'RANGE')]),
    (raw_command('SET'), [protocol.Nak('SET', 'SYNTAX')]),
    (raw_command('SET,12a'), [protocol.Nak('SET', 'SYNTAX')]),
    (raw_command('SET,'), [protocol.Nak('SET', 'SYNTAX')]),
    (raw_command('HB,1'), [protocol.Nak('HB', 'SYNTAX')]),
    (command('HB')[:-2] + f'{int(command("HB")[-2:], 16) ^ 0xFF:02X}',
     [protocol.Nak('?', 'CHECKSUM')]),
    ('$HB', [protocol.Nak('?', 'SYNTAX')]),
    ('$HB*+A', [protocol.Nak('?', 'SYNTAX')]),
    (command('HB') + '\r\r', [protocol.Nak('?', 'SYNTAX')]),
    (command('HB').lower().replace('$hb', '$HB'), [protocol.Ack('HB')]),
    (command('HB') + '\r', [protocol.Ack('HB')]),
    ('garbage' + command('HB'), []),
    ('', []),
]


@pytest.mark.parametrize(('line', 'replies'), COMMAND_CASES)
def test_every_command_gets_its_ack_or_nak(rig_binary, line, replies):
    run = run_rig(rig_binary, *IDLE_RIG, '!run 10', line, '!run 10')
    assert run.replies[1:] == replies  # [0] is the boot banner


def test_hello_acks_and_resends_the_banner_with_the_applied_settings(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, command('RATE', 10), command('MAX', 300_000),
                  command('HBTO', 2000), command('HELLO'), '!run 10')
    integers = firmware_integers()
    # ceiling_pa is the lowered ceiling; limit_pa the compiled limit MAX may go back up to.
    assert run.replies[-2:] == [
        protocol.Ack('HELLO'),
        protocol.Hello(protocol.PROTOCOL_VERSION, 'pma_firmware', spec_doc_banner()['fw_version'],
                       10, integers['MAX_RATE_HZ'], 300_000, integers['CEILING_LIMIT_PA'],
                       2000)]


def test_lower_ceiling_refuses_setpoints_above_it_and_clamps_the_current_one(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, command('SET', 400_000), command('MAX', 300_000),
                  command('SET', 300_001), '!run 60')
    assert run.replies[-1] == protocol.Nak('SET', 'RANGE')
    assert run.samples[-1].setpoint_pa == 300_000


def test_tare_window_and_span(rig_binary):
    window = firmware_integers()['TARE_MAX_OFFSET_PA']
    inside = largest_adc_at_or_below(window)
    below_span = largest_adc_at_or_below(-window / 2)   # out of span, yet near zero
    for adc, reply in [(inside, protocol.Ack('TARE', inside)),
                       (inside + 1, protocol.Nak('TARE', 'RANGE')),
                       (below_span, protocol.Nak('TARE', 'RANGE'))]:
        run = run_rig(rig_binary, f'!adc {adc}', '!run 10', command('TARE'), '!run 10')
        assert run.replies[-1] == reply, adc


def test_tare_refused_when_the_muscle_is_not_empty(rig_binary):
    run = run_rig(rig_binary, '!adc ' + str(adc_for(100_000)), '!run 10', command('TARE'),
                  '!run 10')
    assert run.replies[-1] == protocol.Nak('TARE', 'RANGE')


def test_tare_shifts_the_zero_the_setpoint_is_held_to(rig_binary):
    deadband = firmware_integers()['DEADBAND_PA']
    offset_adc = adc_for(10_000)  # the sensor reads 10 kPa on an empty muscle
    setpoint = 200_000
    # Untared, this reading is inside the deadband; tared, 10 kPa lower, it is below it.
    reading = adc_for(setpoint - deadband + 8_000)
    run = run_rig(rig_binary, f'!adc {offset_adc}', '!echo 583', command('TARE'),
                  command('SET', setpoint), '!run 10', f'!adc {reading}', '!run 60')
    assert protocol.Ack('TARE', offset_adc) in run.replies
    assert run.samples[-1].valve == protocol.Valve.FILL


def _valve_at(binary, setpoint_pa: int, gauge_pa: float):
    run = run_rig(binary, f'!adc {adc_for(gauge_pa)}', '!echo 583', command('SET', setpoint_pa),
                  '!run 60', '!pins')
    return run.samples[-1].valve, run.pins[-1]


def test_bang_bang_regulation_with_a_deadband(rig_binary):
    deadband = firmware_integers()['DEADBAND_PA']
    pa_per_count = calibration.PressureCalibration().pa_per_count
    setpoint = 250_000
    margin = deadband + pa_per_count  # one ADC count beyond the band
    assert _valve_at(rig_binary, setpoint, setpoint - margin) == (protocol.Valve.FILL, (1, 0))
    assert _valve_at(rig_binary, setpoint, setpoint) == (protocol.Valve.HOLD, (0, 0))
    assert _valve_at(rig_binary, setpoint, setpoint + margin) == (protocol.Valve.VENT, (0, 1))
    # Setpoint 0 vents even when the pressure already reads (about) zero.
    assert _valve_at(rig_binary, 0, 0) == (protocol.Valve.VENT, (0, 1))


def tripping_adc() -> int:
    """The lowest reading above ceiling + margin: the first count that trips."""
    return largest_adc_at_or_below(CEILING + firmware_integers()['OVERPRESSURE_MARGIN_PA']) + 1


@pytest.mark.parametrize('trips', [False, True])
def test_overpressure_trips_only_above_the_ceiling_plus_the_margin(rig_binary, trips):
    # At a setpoint equal to the ceiling, a reading up to 10 kPa above it is regulation
    # overshoot and noise: vented by the bang-bang loop, not tripped.
    adc = tripping_adc() - (0 if trips else 1)
    run = run_rig(rig_binary, *IDLE_RIG, command('SET', CEILING), '!run 60', f'!adc {adc}',
                  '!run 120', '!pins')
    last = run.samples[-1]
    assert bool(last.status & protocol.STATUS_OVERPRESSURE) == trips
    assert last.setpoint_pa == (0 if trips else CEILING)
    assert last.valve == protocol.Valve.VENT and run.pins[-1] == (0, 1)


def test_overpressure_vents_and_latches_until_the_next_set(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, command('SET', 250_000), '!run 60',
                  f'!adc {tripping_adc()}', '!run 60', f'!adc {adc_for(0)}',
                  '!run 200', '!pins')
    after_trip = run.samples[-4:]
    assert all(s.status & protocol.STATUS_OVERPRESSURE for s in after_trip)
    assert all(s.setpoint_pa == 0 and s.valve == protocol.Valve.VENT for s in after_trip)
    assert run.pins[-1] == (0, 1)

    run = run_rig(rig_binary, *IDLE_RIG, command('SET', 250_000), '!run 60',
                  f'!adc {tripping_adc()}', '!run 60', f'!adc {adc_for(0)}',
                  command('SET', 100_000), '!run 60')
    assert run.samples[-1].status & protocol.STATUS_OVERPRESSURE == 0
    assert run.samples[-1].valve == protocol.Valve.FILL


def test_lost_heartbeat_vents_after_the_timeout_and_latches(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, '!run 200', command('SET', 250_000), '!run 1500')
    timeout = firmware_integers()['DEFAULT_HEARTBEAT_TIMEOUT_MS']
    for sample in run.samples:
        lost = bool(sample.status & protocol.STATUS_HEARTBEAT_LOST)
        if 200 + 10 < sample.t_ms < 200 + timeout - 5:
            assert not lost and sample.setpoint_pa == 250_000, sample
        elif sample.t_ms > 200 + timeout + 60:
            assert lost and sample.setpoint_pa == 0, sample
            assert sample.valve == protocol.Valve.VENT


def test_heartbeats_keep_the_setpoint_and_hello_clears_the_latch(rig_binary):
    beats = [item for _ in range(10) for item in (command('HB'), '!run 200')]
    run = run_rig(rig_binary, *IDLE_RIG, '!run 200', command('SET', 250_000), *beats)
    assert all(s.status & protocol.STATUS_HEARTBEAT_LOST == 0 for s in run.samples
               if s.t_ms > 200)
    assert run.samples[-1].setpoint_pa == 250_000

    run = run_rig(rig_binary, *IDLE_RIG, '!run 1500', command('HB'), '!run 100')
    assert run.samples[-1].status & protocol.STATUS_HEARTBEAT_LOST  # HB alone does not clear
    run = run_rig(rig_binary, *IDLE_RIG, '!run 1500', command('HELLO'), '!run 100')
    assert run.samples[-1].status & protocol.STATUS_HEARTBEAT_LOST == 0


def test_echo_timeout_reports_zero_and_keeps_the_rate(rig_binary):
    run = run_rig(rig_binary, f'!adc {adc_for(0)}', '!echo 0', '!run 1000')
    assert all(s.echo_us == 0 and s.status & protocol.STATUS_ECHO_TIMEOUT for s in run.samples)
    assert len(run.samples) in (19, 20)


def test_50_hz_keeps_its_period_with_or_without_echo(rig_binary):
    # The echo timeout (6 ms) fits in the 20 ms period: a missing echo no longer stretches it.
    run = run_rig(rig_binary, f'!adc {adc_for(0)}', '!echo 583', command('RATE', 50),
                  '!run 1000', '!echo 0', '!run 1000')
    # t_ms is read after the echo wait, so the switch itself shows once as a longer gap.
    for echo, phase in [(True, (100, 1000)), (False, (1100, 2000))]:
        samples = [s for s in run.samples if phase[0] < s.t_ms < phase[1]]
        assert all((s.echo_us != 0) == echo for s in samples)
        assert set(gaps_ms(samples)) <= {19, 20, 21}
        assert len(samples) >= 43


@pytest.mark.parametrize(('echo_us', 'measured'), [(5500, True), (5600, False)])
def test_echo_timeout_is_about_a_metre_of_range(rig_binary, echo_us, measured):
    # pulseInLong's timeout also covers the ~0.45 ms before the sensor raises Echo.
    assert calibration.LengthCalibration().echo_to_range_m(5500) > 0.9
    run = run_rig(rig_binary, f'!adc {adc_for(0)}', f'!echo {echo_us}', '!run 500')
    assert {s.echo_us for s in run.samples} == {echo_us if measured else 0}
    assert all(bool(s.status & protocol.STATUS_ECHO_TIMEOUT) != measured for s in run.samples)


def test_sensor_out_of_span_vents_and_flags_it(rig_binary):
    run = run_rig(rig_binary, *IDLE_RIG, command('SET', 250_000), '!run 60', '!adc 0',
                  '!run 60', '!pins', f'!adc {adc_for(100_000)}', '!run 60', '!pins')
    unplugged = [s for s in run.samples if s.adc == 0]
    assert unplugged
    assert all(s.status & protocol.STATUS_SENSOR_RANGE and s.valve == protocol.Valve.VENT
               for s in unplugged)
    assert run.pins == [(0, 1), (1, 0)]  # back in span: regulation resumes
    assert run.samples[-1].status & protocol.STATUS_SENSOR_RANGE == 0


def test_overlong_lines_are_dropped_whole(rig_binary):
    longest_body = 'SET,' + '0' * (protocol.MAX_LINE_BYTES - len('$SET,*HH\n') - 6) + '123456'
    longest = raw_command(longest_body)
    assert len(longest) + 1 == protocol.MAX_LINE_BYTES
    too_long = raw_command(longest_body.replace('SET,', 'SET,0'))
    run = run_rig(rig_binary, *IDLE_RIG, 'X' * 300, longest, too_long, command('HB'), '!run 10')
    assert run.replies[1:] == [protocol.Ack('SET', 123_456), protocol.Ack('HB')]


# ---- The simulated rig against the firmware ------------------------------------------------

@pytest.fixture(scope='module')
def sim():
    return pytest.importorskip('pma_sim.device')


def test_the_simulated_rig_uses_the_firmware_s_constants(sim):
    integers = firmware_integers()
    for name in ('OVERPRESSURE_MARGIN_PA', 'TARE_MAX_OFFSET_PA', 'DEADBAND_PA',
                 'REGULATION_PERIOD_MS', 'ADC_OVERSAMPLING', 'ECHO_TIMEOUT_US', 'NAK_NAME_MAX',
                 'MIN_HEARTBEAT_TIMEOUT_MS', 'MAX_HEARTBEAT_TIMEOUT_MS'):
        assert getattr(sim, name) == integers[name], name
    assert sim.COMPILED_CEILING_PA == integers['CEILING_LIMIT_PA']
    assert sim.UNTRUSTED_COMMAND.decode() == firmware_strings()['UNTRUSTED_COMMAND']
    defaults = sim.DeviceConfig()
    assert defaults.rate_hz == integers['DEFAULT_RATE_HZ']
    assert defaults.hb_timeout_ms == integers['DEFAULT_HEARTBEAT_TIMEOUT_MS']
    assert defaults.ceiling_pa == integers['CEILING_LIMIT_PA']
    assert defaults.deadband_pa == integers['DEADBAND_PA']
    # The sensor's delay before Echo rises, which the host rig and the sim both count.
    harness = (RIG_DIR / 'host_main.cpp').read_text()
    assert re.search(rf'ECHO_START_US = {sim.ECHO_START_US};', harness)


def sim_replies(sim, line: str) -> list:
    config = sim.DeviceConfig(max_rate_hz=firmware_integers()['MAX_RATE_HZ'],
                              pressure_noise_pa=0.0)
    device = sim.SimDevice(config)
    device.advance(10)
    device.take_output()   # the banner and samples
    device.receive(line.encode('ascii') + b'\n')
    device.advance(10)
    decoder = protocol.FrameDecoder(protocol.parse_device_line)
    frames = decoder.feed(b''.join(device.take_output()))
    assert decoder.dropped_total == 0, decoder.last_error
    return [f for f in frames if not isinstance(f, protocol.Sample)]


@pytest.mark.parametrize(('line', 'replies'), COMMAND_CASES)
def test_the_simulated_rig_answers_every_line_as_the_firmware(sim, line, replies):
    assert sim_replies(sim, line) == replies


def test_the_simulated_rig_drops_overlong_lines_as_the_firmware(sim):
    longest_body = 'SET,' + '0' * (protocol.MAX_LINE_BYTES - len('$SET,*HH\n') - 6) + '123456'
    assert sim_replies(sim, raw_command(longest_body)) == [protocol.Ack('SET', 123_456)]
    assert sim_replies(sim, raw_command(longest_body.replace('SET,', 'SET,0'))) == []
    assert sim_replies(sim, 'X' * 300) == []
