"""Protocol v1: encode/parse round trips and a fuzzed FrameDecoder that must never lose count."""

import itertools
from collections import Counter

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pma_common import protocol
from pma_common.protocol import (
    Ack,
    Command,
    FrameDecoder,
    FrameError,
    Hello,
    HostCommand,
    Nak,
    NakReason,
    Sample,
)

pytestmark = pytest.mark.in_process

U32 = protocol.U32

samples = st.builds(
    Sample, seq=st.integers(0, U32 - 1), t_ms=st.integers(0, U32 - 1), adc=st.integers(0, 1023),
    echo_us=st.integers(0, 60000), valve=st.integers(0, 2),
    setpoint_pa=st.integers(0, 10_000_000), status=st.integers(0, 0xFFFF))
names = st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters=',$*'),
                min_size=1, max_size=12)
hellos = st.integers(0, 10_000_000).flatmap(lambda limit: st.builds(
    Hello, proto=st.integers(0, 255), firmware=names, fw_version=names,
    rate_hz=st.integers(1, 100_000), max_rate_hz=st.integers(1, 100_000),
    ceiling_pa=st.integers(0, limit), limit_pa=st.just(limit),
    hb_timeout_ms=st.integers(0, 3_600_000)))
acks = st.one_of(st.builds(Ack, command=names),
                 st.builds(Ack, command=names, value=st.integers(-(2**31), U32 - 1)))
naks = st.builds(Nak, command=names, reason=st.sampled_from([r.value for r in NakReason]))


def encode(frame) -> bytes:
    if isinstance(frame, Sample):
        return protocol.encode_sample(frame)
    if isinstance(frame, Hello):
        return protocol.encode_hello(frame)
    if isinstance(frame, Ack):
        return protocol.encode_ack(frame.command, frame.value)
    return protocol.encode_nak(frame.command, frame.reason)


device_frames = st.one_of(samples, hellos, acks, naks)


@given(device_frames)
def test_every_device_message_round_trips(frame):
    line = encode(frame)
    assert line.startswith(b'$') and line.endswith(b'\n')
    assert len(line) <= protocol.MAX_LINE_BYTES
    assert protocol.parse_device_line(line[:-1]) == frame
    assert protocol.parse_device_line(line[:-1] + b'\r') == frame  # CRLF accepted


@pytest.mark.parametrize('command, args', [
    (Command.HELLO, ()), (Command.HEARTBEAT, ()), (Command.SET, (250_000,)),
    (Command.VENT, ()), (Command.RATE, (100,)), (Command.TARE, ()),
    (Command.HEARTBEAT_TIMEOUT, (500,)), (Command.MAX, (400_000,)), (Command.SET, (-1,)),
])
def test_every_host_command_round_trips(command, args):
    line = protocol.encode_command(command, *args)
    assert protocol.parse_host_line(line[:-1]) == HostCommand(command.value, args)


def test_checksum_is_the_xor_of_the_body_in_either_hex_case():
    xor = 0
    for byte in b'SET,250000':
        xor ^= byte
    assert protocol.encode_command(Command.SET, 250000) == b'$SET,250000*%02X\n' % xor
    assert protocol.split_frame(b'$SET,250000*%02x' % xor) == ['SET', '250000']


@pytest.mark.parametrize('line, reason', [
    (b'S,1,2,3,4,0,0,0*00', 'framing'),                  # no '$'
    (b'xx$HB*4A', 'framing'),                            # bytes before '$'
    (b'$HB', 'framing'),                                 # no checksum
    (b'$HB*4', 'framing'),                               # one hex digit
    (b'$HB*ZZ', 'framing'),
    (b'$HB*00', 'checksum'),
    (b'$' + b'A' * 100 + b'*00', 'overlong'),
    (b'$HB*0A\r\r', 'framing'),                          # one '\r' is tolerated, not two
])
def test_bad_framing_is_classified(line, reason):
    with pytest.raises(FrameError) as info:
        protocol.parse_device_line(line)
    assert info.value.reason == reason


@pytest.mark.parametrize('digits', [b' A', b'A ', b'+A', b'-A', b'0x', b'_A', b'\xff\xff'])
def test_checksum_must_be_exactly_two_hex_digits(digits):
    """int(b' A', 16) and int(b'+A', 16) parse: the check must not rely on int() alone."""
    body = b'HB'
    with pytest.raises(FrameError) as info:
        protocol.split_frame(b'$' + body + b'*' + digits)
    assert info.value.reason == 'framing'
    assert protocol.split_frame(b'$HB*%02X' % protocol.checksum(body)) == ['HB']


def test_hello_carries_the_current_ceiling_and_the_compiled_limit():
    hello = Hello(1, 'pma_firmware', '0.1.0', 20, 50, 300_000, 500_000, 1000)
    line = protocol.encode_hello(hello)
    assert line == protocol.frame('HELLO', 1, 'pma_firmware', '0.1.0', 20, 50, 300_000, 500_000,
                                  1000)
    assert protocol.parse_device_line(line[:-1]) == hello


@pytest.mark.parametrize('fields, reason', [
    (('HELLO', 1, 'f', '0', 20, 50, 500_000, 1000), 'fields'),            # v1 without limit_pa
    (('HELLO', 1, 'f', '0', 20, 50, 500_001, 500_000, 1000), 'value'),    # ceiling above limit
])
def test_bad_hello_is_dropped(fields, reason):
    with pytest.raises(FrameError) as info:
        protocol.parse_device_line(protocol.frame(*fields)[:-1])
    assert info.value.reason == reason


def bad_fields(*fields) -> bytes:
    return protocol.frame(*fields)[:-1]


@pytest.mark.parametrize('line, reason', [
    (bad_fields('S', 1, 2, 3), 'fields'),
    (bad_fields('S', 1, 2, 'x', 4, 0, 0, 0), 'value'),
    (bad_fields('S', 1, 2, 1024, 4, 0, 0, 0), 'value'),   # adc above 10 bits
    (bad_fields('S', 1, 2, 3, 4, 3, 0, 0), 'value'),      # no valve state 3
    (bad_fields('S', -1, 2, 3, 4, 0, 0, 0), 'value'),
    (bad_fields('S', 1, 2, 3, 4, 0, 0, 1.5), 'value'),
    (bad_fields('ZAP', 1), 'unknown_type'),
    (bad_fields('NAK', 'SET'), 'fields'),
])
def test_bad_fields_are_classified(line, reason):
    with pytest.raises(FrameError) as info:
        protocol.parse_device_line(line)
    assert info.value.reason == reason


def test_host_parser_classifies_what_the_device_answers():
    for line, reason in [(bad_fields('SET'), 'fields'), (bad_fields('SET', 'abc'), 'value'),
                         (bad_fields('FLY'), 'unknown_type'), (b'$SET,1*00', 'checksum')]:
        with pytest.raises(FrameError) as info:
            protocol.parse_host_line(line)
        assert info.value.reason == reason


def test_a_split_line_is_whole_again():
    decoder = FrameDecoder()
    line = protocol.encode_sample(Sample(1, 2, 3, 4, 0, 5, 0))
    assert decoder.feed(line[:7]) == []
    assert decoder.feed(line[7:]) == [protocol.parse_device_line(line[:-1])]


def test_first_partial_line_is_dropped_after_reset():
    decoder = FrameDecoder()
    line = protocol.encode_sample(Sample(1, 2, 3, 4, 0, 5, 0))
    decoder.reset(drop_first_partial=True)
    assert decoder.feed(line[10:] + line) == [protocol.parse_device_line(line[:-1])]
    assert decoder.dropped_total == 0


def test_a_whole_first_line_after_reset_is_kept():
    # An Arduino reset by the port opening starts with its HELLO: no need to lose it.
    decoder = FrameDecoder()
    hello = protocol.encode_hello(Hello(1, 'pma_firmware', '0.1.0', 20, 50, 500_000, 500_000,
                                        1000))
    decoder.reset(drop_first_partial=True)
    assert decoder.feed(hello) == [protocol.parse_device_line(hello[:-1])]


# ---- fuzzing ----------------------------------------------------------------------------
# A stream is a list of pieces, each either a valid frame (expected out exactly once) or a
# bad line (expected to be counted once). Bad lines carry their own newline, never contain
# another one, and are never blank, so "one bad line = one count" is exact.

printable_junk = st.binary(min_size=0, max_size=40).map(lambda b: b.replace(b'\n', b''))


def corrupt_checksum(line: bytes, flip: int) -> bytes:
    good = int(line[-3:-1], 16)
    return line[:-3] + f'{good ^ flip:02X}'.encode() + b'\n'


@st.composite
def bad_lines(draw):
    """(bytes, reason) for one line the decoder must drop and count."""
    kind = draw(st.sampled_from(['garbage', 'checksum', 'truncated', 'overlong_line',
                                 'non_numeric', 'out_of_range', 'wrong_count', 'unknown']))
    frame = draw(samples)
    good = protocol.encode_sample(frame)
    if kind == 'garbage':
        body = draw(printable_junk)
        line = b'#' + body + b'\n'        # never starts a frame, never blank
        return line, None                 # reason depends on content (framing/overlong)
    if kind == 'checksum':
        return corrupt_checksum(good, draw(st.integers(1, 255))), 'checksum'
    if kind == 'truncated':
        cut = draw(st.integers(1, len(good) - 2))
        tail = good[:cut]
        return tail + b'\n', None          # framing or (by luck) checksum: both counted
    if kind == 'overlong_line':
        return b'$S,' + b'1' * draw(st.integers(100, 300)) + b'*00\n', 'overlong'
    if kind == 'non_numeric':
        return protocol.frame('S', 'x', 2, 3, 4, 0, 0, 0), 'value'
    if kind == 'out_of_range':
        return protocol.frame('S', 1, 2, 5000, 4, 0, 0, 0), 'value'
    if kind == 'wrong_count':
        return protocol.frame('S', 1, 2, 3), 'fields'
    return protocol.frame('WHAT', 1), 'unknown_type'


pieces = st.lists(st.one_of(device_frames.map(lambda f: ('good', f)),
                            bad_lines().map(lambda b: ('bad', b))), max_size=30)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pieces=pieces, cuts=st.lists(st.integers(0, 10_000), max_size=20))
def test_decoder_yields_every_valid_frame_once_and_counts_every_bad_line(pieces, cuts):
    stream = b''.join(encode(p[1]) if p[0] == 'good' else p[1][0] for p in pieces)
    expected = [p[1] for p in pieces if p[0] == 'good']
    bad = [p[1] for p in pieces if p[0] == 'bad']
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    decoder = FrameDecoder()
    out = []
    for start, end in itertools.pairwise(points):
        out += decoder.feed(stream[start:end])
    assert out == expected
    assert decoder.frames == len(expected)
    assert decoder.dropped_total == len(bad)
    for reason, count in Counter(r for _, r in bad if r is not None).items():
        assert decoder.dropped[reason] >= count


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 2000), max_size=10))
def test_random_bytes_never_raise_and_never_grow_the_buffer(data, cuts):
    decoder = FrameDecoder()
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    for start, end in itertools.pairwise(points):
        decoder.feed(data[start:end])
        assert len(decoder._buffer) <= protocol.MAX_LINE_BYTES
    # Whatever came before, a clean line after a newline is decoded.
    frame = Sample(7, 8, 9, 10, 1, 11, 0)
    assert decoder.feed(b'\n' + protocol.encode_sample(frame))[-1:] == [frame]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(samples.map(lambda f: ('good', f)),
                          printable_junk.map(lambda j: ('junk', j))), max_size=20))
def test_unterminated_junk_costs_at_most_the_next_line(items):
    """Junk without a newline glues onto the next line: that line is lost, never misread."""
    decoder = FrameDecoder()
    out = []
    for kind, item in items:
        out += decoder.feed(protocol.encode_sample(item) if kind == 'good' else item)
    goods = [item for kind, item in items if kind == 'good']
    junk_pieces = sum(1 for kind, _ in items if kind == 'junk')
    remaining = iter(goods)
    assert all(frame in remaining for frame in out)   # an in-order subsequence of the input
    assert len(out) >= len(goods) - junk_pieces
