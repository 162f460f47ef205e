"""The PMA serial protocol, version 1 (docs/serial-protocol.md), for both sides.

Plain Python, no ROS: the driver node, the simulated rig and the tests share it.
Parsing never raises on bad input from the wire: `FrameDecoder` turns bytes into
frames and counts every dropped line by reason.
"""

from __future__ import annotations

import enum
import re
from collections import Counter
from dataclasses import dataclass

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 96
U32 = 2**32

# Status bits (same values as pma_interfaces/msg/PmaState STATUS_*).
STATUS_OVERPRESSURE = 1
STATUS_HEARTBEAT_LOST = 2
STATUS_ECHO_TIMEOUT = 4
STATUS_SENSOR_RANGE = 8
STATUS_NAMES = {
    STATUS_OVERPRESSURE: 'overpressure (device vented)',
    STATUS_HEARTBEAT_LOST: 'heartbeat lost (device vented)',
    STATUS_ECHO_TIMEOUT: 'ultrasonic echo timeout',
    STATUS_SENSOR_RANGE: 'pressure sensor out of range',
}


class Valve(enum.IntEnum):
    HOLD = 0
    FILL = 1
    VENT = 2


class Command(str, enum.Enum):
    HELLO = 'HELLO'
    HEARTBEAT = 'HB'
    SET = 'SET'
    VENT = 'VENT'
    RATE = 'RATE'
    TARE = 'TARE'
    HEARTBEAT_TIMEOUT = 'HBTO'
    MAX = 'MAX'


class NakReason(str, enum.Enum):
    RANGE = 'RANGE'
    SYNTAX = 'SYNTAX'
    UNKNOWN = 'UNKNOWN'
    CHECKSUM = 'CHECKSUM'


def status_text(status: int) -> str:
    """Human-readable list of the set status bits ('ok' when none)."""
    names = [text for bit, text in STATUS_NAMES.items() if status & bit]
    unknown = status & ~sum(STATUS_NAMES)
    if unknown:
        names.append(f'unknown bits 0x{unknown:04X}')
    return ', '.join(names) if names else 'ok'


@dataclass(frozen=True)
class Sample:
    seq: int
    t_ms: int
    adc: int
    echo_us: int
    valve: int
    setpoint_pa: int
    status: int


@dataclass(frozen=True)
class Hello:
    """The device's banner; fields in wire order.

    `ceiling_pa` is the current ceiling (lowered by `MAX`), `limit_pa` the firmware's
    compiled limit: the most `MAX` accepts, so the most a host may ever ask for.
    """

    proto: int
    firmware: str
    fw_version: str
    rate_hz: int
    max_rate_hz: int
    ceiling_pa: int
    limit_pa: int
    hb_timeout_ms: int


@dataclass(frozen=True)
class Ack:
    command: str
    value: int | None = None


@dataclass(frozen=True)
class Nak:
    command: str
    reason: str


@dataclass(frozen=True)
class HostCommand:
    """A command as the device receives it (parsed from host to device)."""

    command: str
    args: tuple[int, ...] = ()


Frame = Sample | Hello | Ack | Nak | HostCommand


class FrameError(ValueError):
    """A line that must be dropped; `reason` is the counter it is filed under."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason
        self.detail = detail


def checksum(body: bytes) -> int:
    value = 0
    for byte in body:
        value ^= byte
    return value


def frame(*fields: object) -> bytes:
    """Encode one line: `$f1,f2,...*HH\\n`."""
    return frame_body(','.join(str(f) for f in fields).encode('ascii'))


def frame_body(body: bytes) -> bytes:
    """Wrap a ready body as one line, `$body*HH\\n` (for bodies echoed byte for byte)."""
    return b'$' + body + b'*' + b'%02X' % checksum(body) + b'\n'


def encode_command(command: Command | str, *args: int) -> bytes:
    name = command.value if isinstance(command, Command) else command
    return frame(name, *(int(a) for a in args))


def encode_sample(sample: Sample) -> bytes:
    return frame('S', sample.seq, sample.t_ms, sample.adc, sample.echo_us, sample.valve,
                 sample.setpoint_pa, sample.status)


def encode_hello(hello: Hello) -> bytes:
    return frame('HELLO', hello.proto, hello.firmware, hello.fw_version, hello.rate_hz,
                 hello.max_rate_hz, hello.ceiling_pa, hello.limit_pa, hello.hb_timeout_ms)


def encode_ack(command: str, value: int | None = None) -> bytes:
    return frame('ACK', command) if value is None else frame('ACK', command, int(value))


def encode_nak(command: str, reason: NakReason | str) -> bytes:
    return frame('NAK', command, reason.value if isinstance(reason, NakReason) else reason)


HEX_PAIR = re.compile(rb'[0-9A-Fa-f]{2}')   # the checksum digits, exactly


def split_frame(line: bytes) -> list[str]:
    """Check framing and checksum of one line (without its newline); return the fields."""
    if line.endswith(b'\r'):
        line = line[:-1]   # one '\r' before the '\n' is tolerated, as by the firmware
    if len(line) + 1 > MAX_LINE_BYTES:
        raise FrameError('overlong', f'{len(line) + 1} bytes > {MAX_LINE_BYTES}')
    start = line.rfind(b'$')
    if start < 0:
        raise FrameError('framing', 'no "$"')
    if start > 0:
        # Bytes before the '$' are a partial or corrupted line: the whole line goes.
        raise FrameError('framing', 'bytes before "$"')
    star = line.rfind(b'*')
    if star < 0 or len(line) - star != 3:
        raise FrameError('framing', 'no "*HH" checksum at the end')
    body = line[1:star]
    # Exactly two hex digits: int(..., 16) alone would also take ' A', '+A' or '-A'.
    if not HEX_PAIR.fullmatch(line, star + 1):
        raise FrameError('framing', 'checksum is not two hex digits')
    expected = int(line[star + 1:], 16)
    if checksum(body) != expected:
        raise FrameError('checksum', f'got {expected:02X}, computed {checksum(body):02X}')
    try:
        text = body.decode('ascii')
    except UnicodeDecodeError:
        raise FrameError('framing', 'non-ASCII byte') from None
    if not text or not text.isprintable():
        raise FrameError('framing', 'empty or non-printable body')
    return text.split(',')


def _int(text: str, name: str, low: int, high: int) -> int:
    if not text or not (text.isdigit() or (text[0] == '-' and text[1:].isdigit())):
        raise FrameError('value', f'{name}={text!r} is not an integer')
    value = int(text)
    if not low <= value <= high:
        raise FrameError('value', f'{name}={value} outside {low}..{high}')
    return value


def _expect(fields: list[str], count: int) -> None:
    if len(fields) != count:
        raise FrameError('fields', f'{fields[0]} needs {count - 1} fields, got {len(fields) - 1}')


def parse_device_line(line: bytes) -> Sample | Hello | Ack | Nak:
    """Parse one device-to-host line (newline stripped) or raise FrameError."""
    fields = split_frame(line)
    kind = fields[0]
    if kind == 'S':
        _expect(fields, 8)
        return Sample(
            seq=_int(fields[1], 'seq', 0, U32 - 1),
            t_ms=_int(fields[2], 't_ms', 0, U32 - 1),
            adc=_int(fields[3], 'adc', 0, 1023),
            echo_us=_int(fields[4], 'echo_us', 0, 60000),
            valve=_int(fields[5], 'valve', 0, 2),
            setpoint_pa=_int(fields[6], 'setpoint_pa', 0, 10_000_000),
            status=_int(fields[7], 'status', 0, 0xFFFF),
        )
    if kind == 'HELLO':
        _expect(fields, 9)
        limit_pa = _int(fields[7], 'limit_pa', 0, 10_000_000)
        return Hello(
            proto=_int(fields[1], 'proto', 0, 255),
            firmware=fields[2],
            fw_version=fields[3],
            rate_hz=_int(fields[4], 'rate_hz', 1, 100_000),
            max_rate_hz=_int(fields[5], 'max_rate_hz', 1, 100_000),
            ceiling_pa=_int(fields[6], 'ceiling_pa', 0, limit_pa),
            limit_pa=limit_pa,
            hb_timeout_ms=_int(fields[8], 'hb_timeout_ms', 0, 3_600_000),
        )
    if kind == 'ACK':
        if len(fields) == 2:
            return Ack(fields[1])
        _expect(fields, 3)
        return Ack(fields[1], _int(fields[2], 'value', -(2**31), U32 - 1))
    if kind == 'NAK':
        _expect(fields, 3)
        return Nak(fields[1], fields[2])
    raise FrameError('unknown_type', f'message type {kind!r}')


COMMAND_ARITY = {
    Command.HELLO.value: 0, Command.HEARTBEAT.value: 0, Command.SET.value: 1,
    Command.VENT.value: 0, Command.RATE.value: 1, Command.TARE.value: 0,
    Command.HEARTBEAT_TIMEOUT.value: 1, Command.MAX.value: 1,
}


def parse_host_line(line: bytes) -> HostCommand:
    """Parse one host-to-device line, strictly (for test doubles of the device).

    Raises FrameError; `reason` maps onto the NAK the device answers with
    (`checksum` -> CHECKSUM, `fields`/`value` -> SYNTAX, `unknown_type` -> UNKNOWN).
    The simulated device uses `sim.device.parse_firmware_line` instead, which follows the
    firmware's handleLine exactly (silent drops, saturating integers, cut names).
    """
    fields = split_frame(line)
    name = fields[0]
    if name not in COMMAND_ARITY:
        raise FrameError('unknown_type', f'command {name!r}')
    _expect(fields, COMMAND_ARITY[name] + 1)
    args = tuple(_int(f, 'argument', -(2**31), U32 - 1) for f in fields[1:])
    return HostCommand(name, args)


class FrameDecoder:
    """Bytes in, complete frames out; every dropped line is counted by reason.

    Holds partial lines across reads (a line split over two USB packets is whole
    again here); an unterminated run longer than MAX_LINE_BYTES is discarded up to
    the next newline, so garbage cannot grow the buffer.
    """

    def __init__(self, parse=parse_device_line, drop_first_partial: bool = False):
        self._parse = parse
        self._buffer = bytearray()
        self._discarding = drop_first_partial
        self.dropped: Counter[str] = Counter()
        self.frames = 0
        self.last_error: FrameError | None = None

    def reset(self, drop_first_partial: bool = True) -> None:
        """Forget buffered bytes (after a reconnect); optionally drop the next partial line."""
        self._buffer.clear()
        self._discarding = drop_first_partial

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        self._buffer += data
        while True:
            newline = self._buffer.find(b'\n')
            if newline < 0:
                if len(self._buffer) > MAX_LINE_BYTES:
                    if not self._discarding:
                        self._count(FrameError('overlong', 'no newline within the line limit'))
                    self._buffer.clear()
                    self._discarding = True
                break
            line = bytes(self._buffer[:newline])
            del self._buffer[:newline + 1]
            if self._discarding:
                # The rest of an overlong line, or the partial line at port open - unless
                # it starts a frame: after a reset the first line is often whole (an
                # Arduino's boot HELLO), and only a valid checksum lets it through anyway.
                self._discarding = False
                if not line.startswith(b'$'):
                    continue
            if not line.strip():
                continue
            try:
                out.append(self._parse(line))
                self.frames += 1
            except FrameError as error:
                self._count(error)
        return out

    def _count(self, error: FrameError) -> None:
        self.dropped[error.reason] += 1
        self.last_error = error

