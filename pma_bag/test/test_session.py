"""The recorder's bag session without ROS: real bags written, read back by BagReader and rosbags.

A hand-set clock stands for the DDS receive stamps, so pauses are exact. The last tests
check how the recorder reads pma/state's seq (state_seq.py): the offset read is used only if
it reads the generated PmaState right.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from std_msgs.msg import Header

from pma_bag import BagError, BagReader
from pma_bag.info import LOSS_KEYS
from pma_bag.session import (
    EVENT_HISTORY_SLACK_NS,
    STATE_TYPE,
    RecordingSession,
    RecordOptions,
    header_stamp_ns,
    rig_info_from,
)
from pma_bag.state_seq import (
    decoded_state_seq,
    fast_state_seq,
    offset_read_problem,
    pma_state_seq,
    serialized_state,
    state_seq_reader,
)
from pma_interfaces.msg import PmaPrediction, PmaState, SweepRecord

STATE = '/pma/state'
PREDICTION = '/pma/prediction'
EVENTS = '/pma/sweep_record'
T0 = 1_700_000_000 * 10**9
MS = 1_000_000


class Clock:
    """Nanoseconds, set by the test."""

    def __init__(self, now: int = T0):
        self.now = now

    def __call__(self) -> int:
        return self.now


def open_session(bag: Path, clock: Clock | None = None, failures: list | None = None,
                 topics=(STATE,), **kwargs) -> RecordingSession:
    options = kwargs.pop('options', RecordOptions())
    session = RecordingSession(bag, topics, options, read_seq=fast_state_seq,
                               clock=clock or Clock(),
                               on_fail=None if failures is None else failures.append, **kwargs)
    session.declare(STATE, STATE_TYPE)
    return session


def receive(session: RecordingSession, seq: int, received_ns: int) -> None:
    session.receive(STATE, serialize_message(PmaState(seq=seq)), received_ns, received_ns)


def seqs_read_back(bag: Path) -> list[int]:
    """pma/state seqs in log-time order, by BagReader; rosbags must read the same."""
    with BagReader(bag) as reader:
        ours = [(m.log_time_ns, deserialize_message(m.data, PmaState).seq)
                for m in reader.messages([STATE])]
    with AnyReader([bag]) as reader:
        theirs = [(t, reader.deserialize(raw, c.msgtype).seq)
                  for c, t, raw in reader.messages() if c.topic == STATE]
    assert theirs == ours, 'rosbags reads what BagReader reads'
    return [seq for _, seq in ours]


def custom_data(bag: Path) -> dict[str, str]:
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return info['custom_data']


@pytest.mark.in_process
def test_pause_windows_go_by_receive_time_and_a_pause_is_not_a_loss(tmp_path):
    clock = Clock()
    session = open_session(tmp_path / 'bag', clock)
    for seq in range(10):
        receive(session, seq, T0 + seq * MS)
    clock.now = T0 + 10 * MS
    assert session.set_paused(True) and not session.set_paused(True)
    receive(session, 10, T0 + 9 * MS + MS // 2)    # arrived before the pause, handled after
    for seq in range(11, 20):
        receive(session, seq, T0 + seq * MS)
    clock.now = T0 + 20 * MS
    assert session.set_paused(False) and not session.paused
    receive(session, 20, T0 + 19 * MS + MS // 2)   # arrived while paused, handled after
    for seq in range(21, 30):
        receive(session, seq, T0 + seq * MS)
    clock.now = T0 + 30 * MS
    session.receive(STATE, serialize_message(PmaState(seq=30)))   # no stamp: the clock's
    summary = session.finish()
    assert summary.error == '' and summary.message_count == 21
    assert seqs_read_back(tmp_path / 'bag') == [*range(11), *range(21, 31)]
    assert summary.loss == {'lost_messages': 0, 'lost_state_samples': 0,
                            'state_sequence_gaps': 0, 'dds_messages_lost': 0}
    assert summary.lines() == [f'wrote 21 messages to {tmp_path / "bag"}']
    assert custom_data(tmp_path / 'bag')['lost_messages'] == '0'


@pytest.mark.in_process
def test_a_split_on_request_and_one_refused_on_an_empty_file(tmp_path):
    bag = tmp_path / 'bag'
    session = open_session(bag)
    for seq in range(5):
        receive(session, seq, T0 + seq * MS)
    assert session.split() == (True, 'now writing bag_1.mcap')
    assert session.split() == (False, 'bag_1.mcap holds no message yet; not split')
    for seq in range(5, 12):
        receive(session, seq, T0 + seq * MS)
    assert session.status_values()['file'] == 'bag_1.mcap'
    assert session.finish().message_count == 12
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['relative_file_paths'] == ['bag_0.mcap', 'bag_1.mcap']
    assert [f['message_count'] for f in info['files']] == [5, 7]
    assert seqs_read_back(bag) == list(range(12))


@pytest.mark.in_process
def test_losses_across_a_gap_and_a_device_restart_and_dds_lost_events(tmp_path):
    """A gap of 50 is lost; a repeated number and the counter starting again are not."""
    bag = tmp_path / 'bag'
    session = open_session(bag)
    sent = [*range(100), 99, *range(150, 200), *range(100)]
    for k, seq in enumerate(sent):
        receive(session, seq, T0 + k * MS)
    session.add_dds_lost(STATE, 3)
    session.add_dds_lost('/not/in/this/bag', 5)
    assert session.state_trackers[STATE].stats().restarts == 1
    summary = session.finish()
    assert tuple(summary.loss) == LOSS_KEYS, 'the keys info lists'
    assert summary.loss == {'lost_messages': 53, 'lost_state_samples': 50,
                            'state_sequence_gaps': 1, 'dds_messages_lost': 3}
    assert summary.lines()[1] == ('53 messages were lost before reaching the recorder '
                                  '(pma/state sequence: 50 in 1 gaps; DDS message-lost '
                                  'events: 3)')
    assert {k: v for k, v in custom_data(bag).items() if k in summary.loss} == {
        'lost_messages': '53', 'lost_state_samples': '50', 'state_sequence_gaps': '1',
        'dds_messages_lost': '3'}
    assert seqs_read_back(bag) == sent, 'every message received is written'


@pytest.mark.in_process
def test_custom_data_layers_and_rig_info_seen_later(tmp_path):
    bag = tmp_path / 'bag'
    options = RecordOptions(custom_data={'note': 'from the command line', 'rig': 'a'})
    session = open_session(bag, options=options, custom_data={'note': 'from ~/start'},
                           rig_info={'firmware': 'pma-1.2', 'rig': 'ignored'})
    receive(session, 0, T0)
    array = DiagnosticArray(status=[
        DiagnosticStatus(values=[KeyValue(key='protocol', value='-')]),
        DiagnosticStatus(values=[KeyValue(key='protocol', value='3'),
                                 KeyValue(key='firmware', value='pma-9'),
                                 KeyValue(key='other', value='x')])])
    assert rig_info_from(array) == {'protocol': '3', 'firmware': 'pma-9'}
    session.add_custom_data(rig_info_from(array))
    session.finish()
    data = custom_data(bag)
    assert {k: data[k] for k in ('note', 'rig', 'firmware', 'protocol')} == {
        'note': 'from ~/start', 'rig': 'a', 'firmware': 'pma-1.2', 'protocol': '3'}
    with AnyReader([bag]) as reader:
        assert reader.topics[STATE].msgcount == 1


@pytest.mark.in_process
def test_event_history_from_before_the_bag_is_not_written(tmp_path):
    bag = tmp_path / 'bag'
    session = open_session(bag, event_topics=[EVENTS], topics=(STATE, EVENTS))
    session.declare(EVENTS, 'pma_interfaces/msg/SweepRecord')
    old, recent = T0 - EVENT_HISTORY_SLACK_NS - 1, T0 - EVENT_HISTORY_SLACK_NS
    for sweep_id, source_ns in (('old', old), ('recent', recent), ('unstamped', None)):
        session.receive(EVENTS, serialize_message(SweepRecord(sweep_id=sweep_id)), T0,
                        source_ns)
    assert session.heard == {EVENTS}
    session.finish()
    with BagReader(bag) as reader:
        assert [deserialize_message(m.data, SweepRecord).sweep_id
                for m in reader.messages([EVENTS])] == ['recent']


@pytest.mark.in_process
def test_a_path_holding_a_bag_is_refused_with_a_bag_error(tmp_path):
    open_session(tmp_path / 'done').finish()
    with pytest.raises(BagError, match='holds a bag'):
        open_session(tmp_path / 'done')


def test_a_failed_write_stops_the_session_once_and_says_how_to_recover(tmp_path,
                                                                       small_filesystem):
    """A real 192 KiB tmpfs fills up while the session writes (docs/bags.md, Errors)."""
    failures: list[str] = []
    with small_filesystem(tmp_path / 'small', 192 * 1024) as disk:
        bag = disk / 'full'
        session = open_session(bag, failures=failures)
        seq = 0
        while not session.error and seq < 100_000:
            receive(session, seq, T0 + seq * MS)
            seq += 1
        assert 'No space left' in session.error and failures == [session.error]
        assert not session.records(STATE)
        receive(session, seq, T0 + seq * MS)          # the node checks records() first;
        session.flush_if_due()                        # nothing raises either way
        assert session.split() == (False, 'not recording')
        assert not session.fail('again') and failures == [session.error]
        summary = session.finish()
        assert not (bag / 'metadata.yaml').exists(), 'no metadata for data not on disk'
    assert 'No space left' in summary.error
    assert summary.lines()[0].startswith(f'ERROR bag {bag} is incomplete (')
    assert 'recover' in summary.lines()[0] and str(bag) in summary.lines()[0]


def stamped(message, stamp_ns: int):
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return serialize_message(message)


@pytest.mark.in_process
def test_a_stop_ends_the_bag_at_its_last_sample_and_lets_its_predictions_catch_up(tmp_path):
    """A model behind the driver publishes the last samples' predictions after ~/stop came:
    those are still written, and nothing newer is (a sample after the end, or its prediction)."""
    bag = tmp_path / 'bag'
    session = open_session(bag, topics=(STATE, PREDICTION), derived_topics=(PREDICTION,))
    session.declare(PREDICTION, 'pma_interfaces/msg/PmaPrediction')

    def state(seq):
        session.receive(STATE, stamped(PmaState(seq=seq), T0 + seq * MS), T0 + seq * MS)

    def prediction(seq):
        session.receive(PREDICTION, stamped(PmaPrediction(gauge_pressure_pa=float(seq)),
                                            T0 + seq * MS), T0 + (seq + 50) * MS)

    for seq in range(10):
        state(seq)
    for seq in range(6):
        prediction(seq)
    assert session.lagging_topics() == [], 'nothing lags before the stop'
    session.end_at_last_sample()
    assert session.lagging_topics() == [PREDICTION]
    state(10)                                   # arrived after the stop: not the bag's
    for seq in range(6, 9):
        prediction(seq)
    assert session.lagging_topics() == [PREDICTION]
    prediction(9)
    prediction(10)                              # of the sample after the end
    assert session.lagging_topics() == []
    summary = session.finish()
    assert summary.message_count == 20 and summary.loss['lost_messages'] == 0
    assert seqs_read_back(bag) == list(range(10))
    with BagReader(bag) as reader:
        predicted = [deserialize_message(m.data, PmaPrediction).gauge_pressure_pa
                     for m in reader.messages([PREDICTION])]
    assert predicted == [float(seq) for seq in range(10)]


@pytest.mark.in_process
def test_a_stop_waits_for_nothing_without_a_model_or_samples(tmp_path):
    quiet = open_session(tmp_path / 'no_model', topics=(STATE, PREDICTION),
                         derived_topics=(PREDICTION,))
    quiet.receive(STATE, stamped(PmaState(seq=1), T0), T0)
    quiet.end_at_last_sample()
    assert quiet.lagging_topics() == [], 'no prediction heard in the bag: no model to wait for'
    empty = open_session(tmp_path / 'no_samples', topics=(STATE, PREDICTION),
                         derived_topics=(PREDICTION,))
    empty.declare(PREDICTION, 'pma_interfaces/msg/PmaPrediction')
    empty.receive(PREDICTION, stamped(PmaPrediction(), T0), T0)
    empty.end_at_last_sample()
    assert empty.lagging_topics() == [] and empty.end_stamp_ns is None
    for session in (quiet, empty):
        assert session.finish().error == ''


@pytest.mark.in_process
@pytest.mark.parametrize('stamp_ns', [0, 1, T0 + 123_456_789, -5 * 10**9 + 7])
def test_the_header_stamp_is_read_from_the_raw_message(stamp_ns):
    for message in (PmaState(seq=7), PmaPrediction(predicted_length_m=0.25)):
        message.header.frame_id = 'pma_link'
        assert header_stamp_ns(stamped(message, stamp_ns)) == stamp_ns
    big_endian = b'\x00\x00\x00\x00' + struct.pack('>iI', 3, 5) + bytes(8)
    assert header_stamp_ns(big_endian) == 3 * 10**9 + 5


def test_the_session_module_imports_no_rclpy():
    code = 'import sys, pma_bag.session; sys.exit(int("rclpy" in sys.modules))'
    assert subprocess.run([sys.executable, '-c', code], check=False).returncode == 0


# -- pma/state seq ---------------------------------------------------------------------------


def reordered_state(seq: int, frame_id: str) -> bytes:
    """CDR of a PmaState whose device_time_s came before seq (the header as rclpy writes it)."""
    end = 4 + 8 + 4 + len(frame_id) + 1                 # the header, as rclpy serialises it
    body = bytearray(serialize_message(Header(frame_id=frame_id))[:end])
    body += bytes(-(len(body) - 4) % 8)
    body += struct.pack('<dI', 1.5, seq)
    return bytes(body)


@pytest.mark.in_process
def test_the_offset_read_matches_the_generated_type_and_is_used():
    assert offset_read_problem() == ''
    reader, why = state_seq_reader()
    assert (reader, why) == (fast_state_seq, '')
    assert fast_state_seq(serialized_state(4_000_000_123, 'pma_link')) == 4_000_000_123


@pytest.mark.in_process
def test_the_check_catches_a_layout_the_offset_read_does_not_know():
    assert decoded_state_seq(serialized_state(7, 'x')) == 7
    problem = offset_read_problem(reordered_state)
    assert 'not the one it assumes' in problem, problem
    reader, why = state_seq_reader(reordered_state)
    assert reader is decoded_state_seq and problem in why and 'in full' in why
    assert reader(serialized_state(4_000_000_123, 'ab')) == 4_000_000_123


@pytest.mark.in_process
def test_the_check_catches_a_read_that_forgets_the_alignment():
    def unaligned(cdr: bytes) -> int:
        (length,) = struct.unpack_from('<I', cdr, 12)
        return struct.unpack_from('<I', cdr, 16 + length)[0]

    assert 'frame_id' in offset_read_problem(read=unaligned)
    assert offset_read_problem(read=pma_state_seq) == ''
