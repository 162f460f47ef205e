"""The device side of protocol v1, as the firmware behaves, around a simulated rig.

ROS-free and clock-driven: `SimDevice.advance_to(t_ms)` steps the physics at 1 ms and
emits samples on a drift-free schedule in device time; `receive(bytes)` handles host
commands at the current device time. The caller (fake_arduino, or a test) decides how
device time relates to wall time, so tests can step it exactly.

Firmware behaviour mirrored here (docs/serial-protocol.md, docs/simulated-rig.md):
bang-bang with deadband on the filtered pressure, device-side ceiling, overpressure and
heartbeat-loss venting, latched status bits, ACK/NAK for every command line.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

from pma_driver import protocol
from pma_driver.calibration import LengthCalibration, PressureCalibration
from pma_driver.protocol import Command, NakReason, Valve
from pma_driver.sim.muscle import PreisachMuscle
from pma_driver.sim.pneumatics import PneumaticParams, Pneumatics

FIRMWARE_NAME = 'fake_arduino'
FIRMWARE_VERSION = '0.1.0'
COMPILED_CEILING_PA = 500_000   # the firmware's compiled limit for MAX
STEP_MS = 1                     # physics and control period
HBTO_RANGE_MS = (100, 10_000)
TARE_WINDOW_PA = 20_000         # TARE only when the reading is this close to nominal zero
NAK_NAME_MAX = 12               # echoed command names are cut (keeps the NAK line short)
_NOISE_BYTES = bytes(b for b in range(256) if b != 0x0A)


@dataclass(frozen=True)
class DeviceConfig:
    rate_hz: int = 20
    max_rate_hz: int = 1000
    ceiling_pa: int = COMPILED_CEILING_PA
    hb_timeout_ms: int = 1000
    heartbeat_check: bool = True
    deadband_pa: float = 5_000.0
    # Measured pressure above ceiling + margin vents: the margin keeps sensor noise at
    # a setpoint equal to the ceiling from tripping (2 % FS, about 16 ADC counts).
    overpressure_margin_pa: float = 10_000.0
    pressure_filter_s: float = 0.010           # firmware's EMA on the ADC before control
    pressure_noise_pa: float = 2_500.0         # 0.5 % FS, one sigma
    length_noise_m: float = 0.0015             # HC-SR04: about +/-3 mm (two sigma)
    length_resolution_m: float = 0.003         # HC-SR04 datasheet resolution
    echo_timeout_rate: float = 0.0             # probability a sample has no echo
    seed: int = 0
    pneumatics: PneumaticParams = field(default_factory=PneumaticParams)

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


class Rig:
    """The physical side, which survives a device reboot: air, muscle and sensors."""

    def __init__(self, config: DeviceConfig):
        self.pneumatics = Pneumatics(config.pneumatics)
        self.muscle = PreisachMuscle()
        self.pressure_sensor = PressureCalibration()
        self.range_sensor = LengthCalibration()
        self._config = config
        self._rng = random.Random(f'rig-{config.seed}')

    @property
    def pressure_pa(self) -> float:
        return self.pneumatics.pressure_pa

    @property
    def length_m(self) -> float:
        return self.muscle.length_m

    def step(self, dt_s: float, valve: Valve) -> None:
        self.muscle.update(self.pneumatics.step(dt_s, valve))

    def read_adc(self) -> int:
        noisy = self.pneumatics.pressure_pa + self._rng.gauss(0.0, self._config.pressure_noise_pa)
        return self.pressure_sensor.pa_to_adc(noisy)

    def read_echo_us(self) -> int:
        """One HC-SR04 reading; 0 when the echo timed out."""
        if self._rng.random() < self._config.echo_timeout_rate:
            return 0
        resolution = self._config.length_resolution_m
        noisy = self.muscle.length_m + self._rng.gauss(0.0, self._config.length_noise_m)
        return self.range_sensor.length_to_echo_us(round(noisy / resolution) * resolution)


def bang_bang(measured_pa: float, setpoint_pa: float, deadband_pa: float) -> Valve:
    """The firmware's pressure loop: fill below the band, vent above it, hold inside."""
    if measured_pa < setpoint_pa - deadband_pa:
        return Valve.FILL
    if measured_pa > setpoint_pa + deadband_pa:
        return Valve.VENT
    return Valve.HOLD


@dataclass(frozen=True)
class _Rejected:
    """A host line that cannot be carried out: answered with NAK `command,reason`."""

    command: str
    reason: NakReason


def _parse_host_line_or_reject(line: bytes):
    try:
        return protocol.parse_host_line(line)
    except protocol.FrameError as error:
        if error.reason == 'checksum':
            return _Rejected('?', NakReason.CHECKSUM)
        if error.reason in ('fields', 'value', 'unknown_type'):
            name = protocol.split_frame(line)[0][:NAK_NAME_MAX] or '?'
            reason = NakReason.UNKNOWN if error.reason == 'unknown_type' else NakReason.SYNTAX
            return _Rejected(name, reason)
        return _Rejected('?', NakReason.SYNTAX)   # framing: nothing in it can be trusted


class SimDevice:
    """The Arduino: protocol, control loop and safety; `boot()` is a reset."""

    def __init__(self, config: DeviceConfig = DeviceConfig(), rig: Rig | None = None):
        self.config = config
        self.rig = rig or Rig(config)
        self._calibration = PressureCalibration()
        self._filter_alpha = 1.0 - math.exp(-STEP_MS * 1e-3 / config.pressure_filter_s)
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
        self.forced_vent = False
        self.tare_adc = self._calibration.pa_to_adc(0.0)
        self._tared = self._calibration
        self.last_adc = self.rig.read_adc()
        self.filtered_pa = self._tared.adc_to_pa(self.last_adc)
        self._last_command_ms = 0
        self._restart_schedule()
        self._decoder = protocol.FrameDecoder(parse=_parse_host_line_or_reject)
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
        c = self.config
        self.t_ms += STEP_MS
        self.rig.step(STEP_MS * 1e-3, self.valve)
        self.last_adc = self.rig.read_adc()
        measured = self._tared.adc_to_pa(self.last_adc)
        self.filtered_pa += self._filter_alpha * (measured - self.filtered_pa)
        if (c.heartbeat_check and not self.latched_status & protocol.STATUS_HEARTBEAT_LOST
                and self.t_ms - self._last_command_ms >= self.hb_timeout_ms):
            self._safety_vent(protocol.STATUS_HEARTBEAT_LOST)
        if self.filtered_pa > self.ceiling_pa + c.overpressure_margin_pa:
            self._safety_vent(protocol.STATUS_OVERPRESSURE)
        if self.forced_vent:
            self.valve = Valve.VENT
        else:
            self.valve = bang_bang(self.filtered_pa, self.setpoint_pa, c.deadband_pa)
        if self.t_ms >= self.next_sample_ms:
            self._samples_since_anchor += 1
            self._outbox.append(protocol.encode_sample(self._sample()))

    def _safety_vent(self, bit: int) -> None:
        self.latched_status |= bit
        self.setpoint_pa = 0
        self.forced_vent = True
        self.valve = Valve.VENT

    def _sample(self) -> protocol.Sample:
        echo_us = self.rig.read_echo_us()
        status = self.latched_status
        if echo_us == 0:
            status |= protocol.STATUS_ECHO_TIMEOUT
        if not self._calibration.adc_in_span(self.last_adc):
            status |= protocol.STATUS_SENSOR_RANGE
        sample = protocol.Sample(
            seq=self.seq, t_ms=self.t_ms % protocol.U32, adc=self.last_adc, echo_us=echo_us,
            valve=int(self.valve), setpoint_pa=self.setpoint_pa, status=status)
        self.seq = (self.seq + 1) % protocol.U32
        return sample

    # -- commands ---------------------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Bytes from the host; answers go to the outbox."""
        for item in self._decoder.feed(data):
            if isinstance(item, _Rejected):
                self._outbox.append(protocol.encode_nak(item.command, item.reason))
            else:
                self._last_command_ms = self.t_ms
                self._outbox.extend(self._execute(item))

    @property
    def decoder_dropped(self):
        """Host lines discarded without any answer (overlong runs without a newline)."""
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
            self.forced_vent = False
            self.latched_status = 0
            return [protocol.encode_ack(name, value)]
        if name == Command.VENT:
            self.setpoint_pa = 0
            self.forced_vent = True
            return [protocol.encode_ack(name)]
        if name == Command.RATE:
            if not 1 <= value <= self.config.max_rate_hz:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.rate_hz = value
            self._restart_schedule()
            return [protocol.encode_ack(name, value)]
        if name == Command.TARE:
            if abs(self._calibration.adc_to_pa(self.last_adc)) > TARE_WINDOW_PA:
                return [protocol.encode_nak(name, NakReason.RANGE)]
            self.tare_adc = self.last_adc
            self._tared = self._calibration.with_tare(self.tare_adc)
            self.filtered_pa = self._tared.adc_to_pa(self.last_adc)
            return [protocol.encode_ack(name, self.tare_adc)]
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
        return [protocol.encode_nak(name[:NAK_NAME_MAX], NakReason.UNKNOWN)]  # arity table only

    def _banner(self) -> bytes:
        return protocol.encode_hello(protocol.Hello(
            proto=protocol.PROTOCOL_VERSION, firmware=FIRMWARE_NAME, fw_version=FIRMWARE_VERSION,
            rate_hz=self.rate_hz, max_rate_hz=self.config.max_rate_hz,
            ceiling_pa=self.ceiling_pa, hb_timeout_ms=self.hb_timeout_ms))


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


class LinkFaults:
    """Deterministic (seeded) corruption of device lines; counts what it did."""

    def __init__(self, config: LinkFaultConfig, seed: int = 0):
        self.config = config
        self._rng = random.Random(f'link-{seed}')
        self.counts = {'garbage': 0, 'bad_checksum': 0, 'dropped': 0, 'split': 0}

    def apply(self, line: bytes) -> list[bytes]:
        """The chunks to write for one line: [] dropped, two chunks when split."""
        c, rng = self.config, self._rng
        if c.drop_rate and rng.random() < c.drop_rate:
            self.counts['dropped'] += 1
            return []
        if c.bad_checksum_rate and rng.random() < c.bad_checksum_rate:
            self.counts['bad_checksum'] += 1
            good = int(line[-3:-1], 16)
            line = line[:-3] + f'{good ^ rng.randint(1, 255):02X}'.encode('ascii') + b'\n'
        if c.garbage_rate and rng.random() < c.garbage_rate:
            self.counts['garbage'] += 1
            # Its own line (newline-terminated, first byte printable so it is never blank).
            noise = bytes(rng.choice(_NOISE_BYTES) for _ in range(rng.randint(0, 30)))
            line = bytes([rng.randint(0x21, 0x7E)]) + noise + b'\n' + line
        if c.split_rate and rng.random() < c.split_rate and len(line) > 1:
            self.counts['split'] += 1
            cut = rng.randint(1, len(line) - 1)
            return [line[:cut], line[cut:]]
        return [line]
