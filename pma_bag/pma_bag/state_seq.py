"""PmaState.seq from a raw (CDR) message, for the recorder's loss accounting.

Reading seq at its byte offset is much cheaper than decoding the message, and pma/state
arrives at up to 1 kHz; but the offset follows from PmaState's field order, which the
decoder cannot see. So `state_seq_reader` checks the offset read against the generated
type once (rclpy serialises PmaStates with known seqs) and falls back to full decoding,
saying why, when the two disagree.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from rclpy.serialization import deserialize_message, serialize_message

from pma_interfaces.msg import PmaState

_U32 = struct.Struct('<I')
CDR_LE = 1          # second byte of the encapsulation header: plain CDR, little-endian
# Every alignment of seq behind the frame_id string, and values that fill all 32 bits.
CHECK_FRAME_IDS = ('', 'a', 'ab', 'abc', 'pma_link')
CHECK_SEQS = (0, 1, 0x01020304, 4_000_000_123, 2 ** 32 - 1)


def pma_state_seq(cdr: bytes) -> int:
    """PmaState.seq read straight from the CDR bytes, without decoding the message.

    Layout after the 4-byte encapsulation header: header.stamp (sec, nanosec), the frame_id
    string (uint32 length incl. NUL, the bytes), then seq aligned to 4.
    """
    if cdr[1] != CDR_LE:
        raise ValueError('not little-endian CDR')
    (length,) = _U32.unpack_from(cdr, 4 + 8)
    offset = 8 + 4 + length
    offset += -offset % 4
    return _U32.unpack_from(cdr, 4 + offset)[0]


def decoded_state_seq(cdr: bytes) -> int:
    """PmaState.seq by decoding the whole message (any layout or byte order)."""
    return deserialize_message(cdr, PmaState).seq


def serialized_state(seq: int, frame_id: str) -> bytes:
    """A PmaState with `seq`, its other fields set to values unlike any seq checked."""
    state = PmaState(seq=seq, device_time_s=1.5, gauge_pressure_pa=-2.5, length_m=0.25,
                     gauge_setpoint_pa=3.5, valve_state=2, status=0x0505,
                     pressure_adc=0x0303, echo_us=0x0A0B0C0D)
    state.header.frame_id = frame_id
    state.header.stamp.sec = 17
    state.header.stamp.nanosec = 0x0F0F0F0F
    return serialize_message(state)


def offset_read_problem(serialize: Callable[[int, str], bytes] = serialized_state,
                        read: Callable[[bytes], int] = pma_state_seq) -> str:
    """'' if `read` gets back the seq of every `serialize(seq, frame_id)` checked, else why not."""
    for frame_id in CHECK_FRAME_IDS:
        for seq in CHECK_SEQS:
            try:
                got = read(serialize(seq, frame_id))
            except (ValueError, IndexError, struct.error) as exc:
                return (f'the offset read of seq fails on a PmaState with frame_id '
                        f'{frame_id!r}: {exc}')
            if got != seq:
                return (f'the offset read of seq gives {got} for a PmaState with seq {seq} and '
                        f'frame_id {frame_id!r}: the message layout is not the one it assumes')
    return ''


def fast_state_seq(cdr: bytes) -> int:
    """The offset read for little-endian CDR (what every PMA node sends), else a decode."""
    return pma_state_seq(cdr) if cdr[1] == CDR_LE else decoded_state_seq(cdr)


def state_seq_reader(serialize: Callable[[int, str], bytes] = serialized_state
                     ) -> tuple[Callable[[bytes], int], str]:
    """(how to read seq, '' or why the offset read is not used): checked once, at start-up.

    `serialize` stands for the generated type; tests give it other layouts.
    """
    problem = offset_read_problem(serialize)
    if problem:
        return decoded_state_seq, f'{problem}; decoding every PmaState in full instead'
    return fast_state_seq, ''
