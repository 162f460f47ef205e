"""The device side of protocol v1, as the firmware behaves, around a simulated rig.

ROS-free and clock-driven: `SimDevice.advance_to(t_ms)` steps the physics at 1 ms and
emits samples on a drift-free schedule in device time; `receive(bytes)` handles host
commands at the current device time. The caller (fake_arduino, or a test) decides how
device time relates to wall time, so tests can step it exactly.

It mirrors the firmware (pma_driver/firmware/pma_firmware/pma_firmware.ino) rule for rule,
with the same constants under the same names (test_firmware_build.py compares them):
each pressure reading is the rounded mean of ADC_OVERSAMPLING conversions (no other
filter); a reading is taken and the valves decided every REGULATION_PERIOD_MS and for
every sample; bang-bang with a DEADBAND_PA band; setpoint 0 or a reading outside the
sensor's span vents; a reading above ceiling + OVERPRESSURE_MARGIN_PA vents and latches
OVERPRESSURE; heartbeat loss vents and latches HEARTBEAT_LOST; host lines are handled as
the firmware's handleLine does (`parse_firmware_line`). docs/simulated-rig.md lists the
few deliberate differences (faster rates, a 1 ms step).
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field

from pma_common import protocol
from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.protocol import Command, NakReason, Valve
from pma_sim.families import Muscle
from pma_sim.pneumatics import PneumaticParams, Pneumatics
from pma_sim.registry import DEFAULT_FAMILY, muscle_from_spec, parse_muscle_spec

FIRMWARE_NAME = 'fake_arduino'
FIRMWARE_VERSION = '0.1.0'
STEP_MS = 1                     # physics step; the firmware's loop passes are finer still

# The firmware's constants (pma_protocol.h / pma_firmware.ino), same names where it has one.
COMPILED_CEILING_PA = 500_000   # CEILING_LIMIT_PA: default ceiling, most MAX may set, limit_pa
OVERPRESSURE_MARGIN_PA = 10_000  # trip at a reading above ceiling + this (see the firmware)
TARE_MAX_OFFSET_PA = 25_000     # TARE only when the untared reading is this close to zero
DEADBAND_PA = 5_000             # bang-bang band around the setpoint
REGULATION_PERIOD_MS = 5        # valves decided this often between samples
ADC_OVERSAMPLING = 4            # conversions averaged into one reading
ECHO_TIMEOUT_US = 6_000         # pulseInLong timeout, counted from the trigger
ECHO_START_US = 450             # HC-SR04: trigger to rising echo, inside that timeout
NAK_NAME_MAX = 12               # a NAK echoes at most this much of the command's name
MIN_HEARTBEAT_TIMEOUT_MS = 100
MAX_HEARTBEAT_TIMEOUT_MS = 10_000
HBTO_RANGE_MS = (MIN_HEARTBEAT_TIMEOUT_MS, MAX_HEARTBEAT_TIMEOUT_MS)
UNTRUSTED_COMMAND = b'?'        # the name of a NAK for a line whose name cannot be trusted

_NOISE_BYTES = bytes(b for b in range(256) if b != 0x0A)
_COMMAND_ARITY = {name.encode('ascii'): count for name, count in protocol.COMMAND_ARITY.items()}


@dataclass(frozen=True)
class DeviceConfig:
    rate_hz: int = 20
    max_rate_hz: int = 1000
    ceiling_pa: int = COMPILED_CEILING_PA
    hb_timeout_ms: int = 1000
    heartbeat_check: bool = True
    deadband_pa: float = DEADBAND_PA
    pressure_noise_pa: float = 2_500.0         # per conversion: 0.5 % FS, one sigma
    length_noise_m: float = 0.0015             # HC-SR04: about +/-3 mm (two sigma)
    length_resolution_m: float = 0.003         # HC-SR04 datasheet resolution
    echo_timeout_rate: float = 0.0             # probability a sample has no echo
    seed: int = 0
    pneumatics: PneumaticParams = field(default_factory=PneumaticParams)
    muscle: str = DEFAULT_FAMILY               # pma_sim.registry: a family, '+drift' optional

    def __post_init__(self):
        if not 1 <= self.max_rate_hz <= 1000:
            raise ValueError('max_rate_hz must be within 1..1000 (1 ms control step)')
        if not 1 <= self.rate_hz <= self.max_rate_hz:
            raise ValueError(f'rate_hz must be within 1..max_rate_hz ({self.max_rate_hz})')
        if not 0 < self.ceiling_pa <= COMPILED_CEILING_PA:
            raise ValueError(f'ceiling_pa must be within 1..{COMPILED_CEILING_PA}')
        if not HBTO_RANGE_MS[0] <= self.hb_timeout_ms <= HBTO_RANGE_MS[1]:
            raise ValueError(f'hb_timeout_ms must be within {HBTO_RANGE_MS}')
        if not 0.0 <= self.echo_timeout_rate <= 1.0:
            raise ValueError('echo_timeout_rate must be within 0..1')
        parse_muscle_spec(self.muscle)   # an unknown family fails here, with the choices


class Rig:
    """The physical side, which survives a device reboot: air, muscle and sensors.

    The muscle is `config.muscle`'s family unless one is given; `time_s` is the rig's own
    clock (the muscle families' time argument), advanced by `step`.
    """

    def __init__(self, config: DeviceConfig, muscle: Muscle | None = None):
        self.pneumatics = Pneumatics(config.pneumatics)
        self.muscle = muscle if muscle is not None else muscle_from_spec(config.muscle)
        self.time_s = 0.0
        self.pressure_sensor = PressureCalibration()
        self.range_sensor = LengthCalibration()
        # A broken or unplugged pressure sensor: every conversion reads this count.
        self.pressure_sensor_fault_adc: int | None = None
        self._config = config
        self._rng = random.Random(f'rig-{config.seed}')

    @property
    def pressure_pa(self) -> float:
        return self.pneumatics.pressure_pa

    @property
    def length_m(self) -> float:
        return self.muscle.length_m

    def step(self, dt_s: float, valve: Valve) -> None:
        self.time_s += dt_s
        self.muscle.update(self.pneumatics.step(dt_s, valve), self.time_s)

    def read_adc(self) -> int:
        """One ADC conversion of the pressure sensor, with its own noise."""
        if self.pressure_sensor_fault_adc is not None:
            return self.pressure_sensor_fault_adc
        noisy = self.pneumatics.pressure_pa + self._rng.gauss(0.0, self._config.pressure_noise_pa)
        return self.pressure_sensor.pa_to_adc(noisy)

    def read_echo_us(self) -> int:
        """One HC-SR04 reading as pulseInLong() returns it; 0 when the echo timed out.

        Lost at random (`echo_timeout_rate`), or when the rising edge plus the echo do not
        fit in the firmware's ECHO_TIMEOUT_US (a target farther than ~0.95 m).
        """
        if self._rng.random() < self._config.echo_timeout_rate:
            return 0
        resolution = self._config.length_resolution_m
        noisy = self.muscle.length_m + self._rng.gauss(0.0, self._config.length_noise_m)
        echo_us = self.range_sensor.length_to_echo_us(round(noisy / resolution) * resolution)
        return 0 if ECHO_START_US + echo_us > ECHO_TIMEOUT_US else echo_us


def bang_bang(measured_pa: float, setpoint_pa: float, deadband_pa: float) -> Valve:
    """The firmware's pressure loop: fill below the band, vent above it, hold inside."""
    if measured_pa < setpoint_pa - deadband_pa:
        return Valve.FILL
    if measured_pa > setpoint_pa + deadband_pa:
        return Valve.VENT
    return Valve.HOLD


@dataclass(frozen=True)
class Rejected:
    """A host line answered with NAK `command,reason` (the name as the firmware echoes it)."""

    command: bytes
    reason: NakReason


def _firmware_integer(text: bytes) -> int | None:
    """The firmware's parseInteger: decimal with an optional '-', saturating at 32 bits."""
    negative = text.startswith(b'-')
    digits = text[1:] if negative else text
    if not digits or not all(0x30 <= byte <= 0x39 for byte in digits):
        return None
    magnitude = min(int(digits), 2**31 if negative else 2**31 - 1)
    return -magnitude if negative else magnitude


def parse_firmware_line(line: bytes) -> protocol.HostCommand | Rejected:
    """One host line (without its '\\n') as the firmware's handleLine takes it.

    Returns the command to carry out or the NAK to answer with. Raises FrameError for the
    lines the firmware drops without an answer: overlong, empty, or not starting with '$'.
    """
    if line.endswith(b'\r'):
        line = line[:-1]
    if len(line) + 1 > protocol.MAX_LINE_BYTES:
        raise protocol.FrameError('overlong', f'{len(line) + 1} bytes')
    if not line.startswith(b'$'):
        raise protocol.FrameError('framing', 'no "$" at the start of the line')
    if len(line) < 4 or line[-3:-2] != b'*':
        return Rejected(UNTRUSTED_COMMAND, NakReason.SYNTAX)
    if not protocol.HEX_PAIR.fullmatch(line, len(line) - 2):
        return Rejected(UNTRUSTED_COMMAND, NakReason.SYNTAX)
    if protocol.checksum(line[1:-3]) != int(line[-2:], 16):
        return Rejected(UNTRUSTED_COMMAND, NakReason.CHECKSUM)
    body = line[1:-3].split(b'\0', 1)[0]    # the firmware's C strings end at a NUL byte
    fields = body.split(b',')
    name = fields[0]
    arity = _COMMAND_ARITY.get(name)
    if arity is None:
        return Rejected(name[:NAK_NAME_MAX], NakReason.UNKNOWN)
    value = _firmware_integer(fields[1]) if arity == 1 and len(fields) == 2 else None
    if len(fields) != arity + 1 or (arity == 1 and value is None):
        return Rejected(name, NakReason.SYNTAX)
    return protocol.HostCommand(name.decode('ascii'), () if value is None else (value,))


def encode_nak(command: bytes, reason: NakReason) -> bytes:
    """A NAK echoing the command's name byte for byte, as the firmware does."""
    return protocol.frame_body(b'NAK,' + command + b',' + reason.value.encode('ascii'))


class SimDevice:
    """The Arduino: protocol, control loop and safety; `boot()` is a reset."""

    def __init__(self, config: DeviceConfig = DeviceConfig(), rig: Rig | None = None,
                 on_sample: Callable[[protocol.Sample, Rig], None] | None = None):
        self.config = config
        self.rig = rig or Rig(config)
        # Sees every sample with the rig that made it (the true length, for evaluation).
        self.on_sample = on_sample
        self._calibration = PressureCalibration()
        self.boot()

    # -- state ------------------------------------------------------------------------------
    def boot(self) -> None:
        """Power-on reset: clock and counters restart, valves closed, setpoint 0, banner out."""
        c = self.config
        self.t_ms = 0
        self.seq = 0
        self.rate_hz = c.rate_hz
        self.ceiling_pa = c.ceiling_pa
        self.hb_timeout_ms = c.hb_timeout_ms
        self.setpoint_pa = 0
        self.valve = Valve.HOLD
        self.latched_status = 0
        self.tare_adc = self._calibration.pa_to_adc(0.0)
        self._tared = self._calibration
        # As in the firmware: no reading yet; the first regulation, 5 ms in, takes one.
        self.last_adc = 0
        self.sensor_in_span = False
        self.pressure_reading_pa = 0.0
        self._last_regulation_ms = 0
        self._last_command_ms = 0
        self._restart_schedule()
        self._decoder = protocol.FrameDecoder(parse=parse_firmware_line)
        self._outbox: list[bytes] = [self._banner()]

    def _restart_schedule(self) -> None:
        self._schedule_anchor_ms = self.t_ms
        self._samples_since_anchor = 1   # the first sample one period from now

    @property
    def next_sample_ms(self) -> int:
        """Device time of the next sample (integer ms; the schedule itself is exact)."""
        due = self._schedule_anchor_ms + self._samples_since_anchor * 1000.0 / self.rate_hz
        return math.ceil(due - 1e-9)

    @property
    def status(self) -> int:
        return self.latched_status

    def take_output(self) -> list[bytes]:
        """Lines the device has written since the last call, oldest first."""
        out, self._outbox = self._outbox, []
        return out

    # -- time -------------------------------------------------------------------------------
    def advance_to(self, t_ms: int) -> None:
        """Run the firmware loop in 1 ms steps up to device time t_ms."""
        while self.t_ms < t_ms:
            self._step()

    def advance(self, ms: int) -> None:
        self.advance_to(self.t_ms + ms)

    def _step(self) -> None:
        """One pass of the firmware's loop() (commands arrive through receive())."""
        self.t_ms += STEP_MS
        self.rig.step(STEP_MS * 1e-3, self.valve)
        if (self.config.heartbeat_check
                and not self.latched_status & protocol.STATUS_HEARTBEAT_LOST
                and self.t_ms - self._last_command_ms >= self.hb_timeout_ms):
            # The host is gone or hung: nobody is watching the muscle, so empty it.
            self.latched_status |= protocol.STATUS_HEARTBEAT_LOST
            self.setpoint_pa = 0
            self._regulate()
        if self.t_ms >= self.next_sample_ms:
            self._samples_since_anchor += 1
            self._outbox.append(protocol.encode_sample(self._sample()))
        elif self.t_ms - self._last_regulation_ms >= REGULATION_PERIOD_MS:
            self._regulate()

    def read_pressure_adc(self) -> int:
        """One reading: the rounded mean of ADC_OVERSAMPLING conversions (readPressureAdc)."""
        total = sum(self.rig.read_adc() for _ in range(ADC_OVERSAMPLING))
        return (total + ADC_OVERSAMPLING // 2) // ADC_OVERSAMPLING

    def _regulate(self) -> None:
        """Measure, check the safety limits and decide the valves (the firmware's regulate)."""
        self.last_adc = self.read_pressure_adc()
        self.sensor_in_span = self._calibration.adc_in_span(self.last_adc)
        self.pressure_reading_pa = self._tared.adc_to_pa(self.last_adc)
        # Checked even outside the span: a saturated sensor may well be a real overpressure.
        if self.pressure_reading_pa > self.ceiling_pa + OVERPRESSURE_MARGIN_PA:
            self.latched_status |= protocol.STATUS_OVERPRESSURE
            self.setpoint_pa = 0
        if not self.sensor_in_span or self.setpoint_pa == 0:
            self.valve = Valve.VENT   # blind, or asked for nothing: empty is the safe state
        else:
            self.valve = bang_bang(self.pressure_reading_pa, self.setpoint_pa,
                                   self.config.deadband_pa)
        self._last_regulation_ms = self.t_ms

    def _sample(self) -> protocol.Sample:
        echo_us = self.rig.read_echo_us()
        self._regulate()   # a fresh pressure reading and valve decision for this sample
        status = self.latched_status
        if echo_us == 0:
            status |= protocol.STATUS_ECHO_TIMEOUT
        if not self.sensor_in_span:
            status |= protocol.STATUS_SENSOR_RANGE
        sample = protocol.Sample(
            seq=self.seq, t_ms=self.t_ms % protocol.U32, adc=self.last_adc, echo_us=echo_us,
            valve=int(self.valve), setpoint_pa=self.setpoint_pa, status=status)
        self.seq = (self.seq + 1) % protocol.U32
        if self.on_sample is not None:
            self.on_sample(sample, self.rig)
        return sample

    # -- commands ---------------------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host; answers go to the outbox."""
        for item in self._decoder.feed(data):
            if isinstance(item, Rejected):
                self._outbox.append(encode_nak(item.command, item.reason))
            else:
                # A well-formed command proves the host alive, even one refused for its value.
                self._last_command_ms = self.t_ms
                self._outbox.extend(self._execute(item))

    @property
    def decoder_dropped(self):
        """Host lines dropped without an answer, by reason (no '$', overlong, ...)."""
        return self._decoder.dropped

    def _execute(self, command: protocol.HostCommand) -> list[bytes]:
        name = command.command
        value = command.args[0] if command.args else None
        if name == Command.HELLO:
            self.latched_status &= ~protocol.STATUS_HEARTBEAT_LOST
            return [protocol.encode_ack(name), self._banner()]
        if name == Command.HEARTBEAT:
            return [protocol.encode_ack(name)]
        if name == Command.SET:
            if not 0 <= value <= self.ceiling_pa:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.setpoint_pa = value
            # A new setpoint is the host's acknowledgement of the faults that vented.
            self.latched_status &= ~(protocol.STATUS_OVERPRESSURE | protocol.STATUS_HEARTBEAT_LOST)
            return [protocol.encode_ack(name, value)]
        if name == Command.VENT:
            self.setpoint_pa = 0
            self._regulate()   # open the exhaust now, not at the next regulation
            return [protocol.encode_ack(name)]
        if name == Command.RATE:
            if not 1 <= value <= self.config.max_rate_hz:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.rate_hz = value
            self._restart_schedule()
            return [protocol.encode_ack(name, value)]
        if name == Command.TARE:
            adc = self.read_pressure_adc()   # a fresh reading, as the firmware takes
            offset_pa = self._calibration.adc_to_pa(adc)
            if not self._calibration.adc_in_span(adc) or abs(offset_pa) > TARE_MAX_OFFSET_PA:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.tare_adc = adc
            self._tared = self._calibration.with_tare(adc)
            return [protocol.encode_ack(name, adc)]
        if name == Command.HEARTBEAT_TIMEOUT:
            if not HBTO_RANGE_MS[0] <= value <= HBTO_RANGE_MS[1]:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.hb_timeout_ms = value
            return [protocol.encode_ack(name, value)]
        if name == Command.MAX:
            if not 0 < value <= COMPILED_CEILING_PA:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.ceiling_pa = value
            self.setpoint_pa = min(self.setpoint_pa, value)  # never regulate above it
            return [protocol.encode_ack(name, value)]
        raise AssertionError(f'no handler for {name}')   # parse_firmware_line knows them all

    def _banner(self) -> bytes:
        return protocol.encode_hello(protocol.Hello(
            proto=protocol.PROTOCOL_VERSION, firmware=FIRMWARE_NAME, fw_version=FIRMWARE_VERSION,
            rate_hz=self.rate_hz, max_rate_hz=self.config.max_rate_hz,
            ceiling_pa=self.ceiling_pa, limit_pa=COMPILED_CEILING_PA,
            hb_timeout_ms=self.hb_timeout_ms))


@dataclass(frozen=True)
class LinkFaultConfig:
    """Probabilities per device line of what a flaky USB-serial link does to it."""

    garbage_rate: float = 0.0       # a line of random bytes before the line
    bad_checksum_rate: float = 0.0  # checksum digits corrupted
    drop_rate: float = 0.0          # line lost entirely
    split_rate: float = 0.0         # line delivered in two writes with a pause between

    def __post_init__(self):
        for name in ('garbage_rate', 'bad_checksum_rate', 'drop_rate', 'split_rate'):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f'{name} must be within 0..1')


@dataclass(frozen=True)
class FaultedLine:
    """One device line after the link: the chunks to write and the faults applied to it."""

    chunks: list[bytes]          # [] when dropped, two when split
    faults: frozenset[str]       # keys of LinkFaults.counts


class LinkFaults:
    """Deterministic (seeded) corruption of device lines; counts what it did.

    A garbage run is a line of its own (newline-terminated, never blank) written just before
    the line, so it costs the host that one bad line and leaves the line after it intact.
    """

    FAULTS = ('garbage', 'bad_checksum', 'dropped', 'split')

    def __init__(self, config: LinkFaultConfig, seed: int = 0):
        self.config = config
        self._rng = random.Random(f'link-{seed}')
        self.counts = dict.fromkeys(self.FAULTS, 0)

    def apply(self, line: bytes) -> FaultedLine:
        c, rng = self.config, self._rng
        faults: set[str] = set()
        if c.drop_rate and rng.random() < c.drop_rate:
            self.counts['dropped'] += 1
            return FaultedLine([], frozenset({'dropped'}))
        if c.bad_checksum_rate and rng.random() < c.bad_checksum_rate:
            faults.add('bad_checksum')
            good = int(line[-3:-1], 16)
            line = line[:-3] + f'{good ^ rng.randint(1, 255):02X}'.encode('ascii') + b'\n'
        if c.garbage_rate and rng.random() < c.garbage_rate:
            faults.add('garbage')
            # Its own line (newline-terminated, first byte printable so it is never blank).
            noise = bytes(rng.choice(_NOISE_BYTES) for _ in range(rng.randint(0, 30)))
            line = bytes([rng.randint(0x21, 0x7E)]) + noise + b'\n' + line
        chunks = [line]
        if c.split_rate and rng.random() < c.split_rate and len(line) > 1:
            faults.add('split')
            cut = rng.randint(1, len(line) - 1)
            chunks = [line[:cut], line[cut:]]
        for fault in faults:
            self.counts[fault] += 1
        return FaultedLine(chunks, frozenset(faults))
