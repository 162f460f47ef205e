"""BagReader on damaged and foreign input, recover_bag, write errors and a real SIGKILL."""

import shutil
import signal
import time
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagError, BagReader, BagWriteError, BagWriter, recover_bag
from pma_bag.reader import TruncatedBagWarning
from pma_interfaces.msg import PmaState

STATE = 'pma_interfaces/msg/PmaState'
HELPERS = Path(__file__).resolve().parents[2] / 'tests' / 'helpers'


def write_states(bag: Path, count: int, *, chunk_size: int = 4096, close: bool = True,
                 log_times=None) -> list[int]:
    """A bag of `count` PmaState with seq = index; returns the log times used."""
    t0 = time.time_ns()
    log_times = log_times or [t0 + i * 1_000_000 for i in range(count)]
    writer = BagWriter(bag, chunk_size=chunk_size)
    writer.add_topic('/pma/state', STATE)
    for seq, log_time in enumerate(log_times):
        writer.write('/pma/state', serialize_message(PmaState(seq=seq)), log_time)
    writer.flush()
    if close:
        writer.close()
    return log_times


def seqs(reader: BagReader) -> list[int]:
    return [deserialize_message(m.data, PmaState).seq for m in reader.messages()]


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(steps=st.lists(st.integers(min_value=-3_000_000, max_value=3_000_000), min_size=1,
                      max_size=300),
       chunk_size=st.sampled_from([64, 1024, 1 << 20]))
def test_reader_yields_log_time_order_even_when_written_out_of_order(tmp_path_factory, steps,
                                                                      chunk_size):
    bag = tmp_path_factory.mktemp('order') / 'bag'
    t0 = time.time_ns()
    log_times = [t0 + sum(steps[:i + 1]) for i in range(len(steps))]
    write_states(bag, len(steps), chunk_size=chunk_size, log_times=log_times)
    with BagReader(bag) as reader:
        got = [(m.log_time_ns, deserialize_message(m.data, PmaState).seq)
               for m in reader.messages()]
    assert got == sorted(zip(log_times, range(len(steps)), strict=True))


def test_truncated_file_reads_the_complete_prefix(tmp_path):
    bag = tmp_path / 'bag'
    write_states(bag, 2000, close=False)  # killed writer: flushed chunks, no summary
    source = bag / 'bag_0.mcap'
    full = source.read_bytes()
    previous = -1
    for fraction in (0.3, 0.55, 0.8, 1.0):
        cut = tmp_path / f'cut{fraction}.mcap'
        cut.write_bytes(full[:int(len(full) * fraction)])
        with pytest.warns(TruncatedBagWarning):
            reader = BagReader(cut)
        with reader:
            got = seqs(reader)
            assert reader.truncated
            assert reader.topics['/pma/state'].message_count == len(got)
        assert got == list(range(len(got))), 'not a gap-free prefix'
        assert len(got) > previous
        previous = len(got)
    assert previous == 2000


def test_recover_rewrites_a_truncated_bag_that_every_reader_opens(tmp_path):
    bag = tmp_path / 'crashed'
    write_states(bag, 1500, close=False)
    path = bag / 'crashed_0.mcap'
    path.write_bytes(path.read_bytes()[:-100])  # and the last chunk cut short
    with pytest.warns(TruncatedBagWarning):
        expected = seqs(BagReader(bag))
    report = recover_bag(bag)
    assert report.input_was_truncated and report.message_count == len(expected) > 1000
    assert_readable_by_all(report.output, expected)
    assert path.exists(), 'the damaged input must be kept'


def assert_readable_by_all(bag: Path, expected_seqs: list[int]) -> None:
    """Our reader, rosbags (directory and file) and mcap_ros2 decode the same seqs."""
    with BagReader(bag) as reader:
        assert not reader.truncated
        assert seqs(reader) == expected_seqs
    mcap_path = next(bag.glob('*.mcap'))
    for target in (bag, mcap_path):
        with AnyReader([target]) as reader:
            got = [reader.deserialize(raw, c.msgtype).seq for c, _, raw in reader.messages()]
        assert got == expected_seqs, f'rosbags on {target}'
    with open(mcap_path, 'rb') as stream:
        decoded = make_reader(stream, decoder_factories=[DecoderFactory()])
        got = [m.seq for _, _, _, m in decoded.iter_decoded_messages()]
    assert got == expected_seqs


def test_missing_empty_and_foreign_inputs_raise_bag_error(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        BagReader(tmp_path / 'nothing')
    (tmp_path / 'empty.mcap').write_bytes(b'')
    with pytest.raises(BagError, match='empty'):
        BagReader(tmp_path / 'empty.mcap')
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(BagError, match=r'no \.mcap'):
        BagReader(tmp_path / 'empty_dir')
    (tmp_path / 'text.mcap').write_text('hello, not a bag\n')
    with pytest.raises(BagError, match='not an MCAP file'):
        BagReader(tmp_path / 'text.mcap')
    with open(tmp_path / 'foxglove.mcap', 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='', library='test')
        schema = writer.register_schema('Point', 'jsonschema', b'{}')
        channel = writer.register_channel('/point', 'json', schema)
        writer.add_message(channel, 1, b'{}', 1)
        writer.finish()
    with pytest.raises(BagError, match='profile'):
        BagReader(tmp_path / 'foxglove.mcap')
    with open(tmp_path / 'json.mcap', 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('Point', 'jsonschema', b'{}')
        writer.register_channel('/point', 'json', schema)
        writer.finish()
    with pytest.raises(BagError, match='not "cdr"'):
        BagReader(tmp_path / 'json.mcap')


def test_unwritable_path_raises_bag_write_error(tmp_path):
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    with pytest.raises(BagWriteError, match='cannot create bag'):
        BagWriter(blocker / 'bag')
    with pytest.raises(BagWriteError, match='not a directory'):
        BagWriter(blocker)
    write_states(tmp_path / 'done', 3)
    with pytest.raises(BagWriteError, match='holds a bag'):
        BagWriter(tmp_path / 'done')


def test_a_directory_holding_other_files_is_refused_and_left_alone(tmp_path):
    """Regression: a directory with unrelated files was written into (only a bag refused)."""
    notes = tmp_path / 'experiment'
    notes.mkdir()
    (notes / 'notes.txt').write_text('do not mix a bag into me')
    with pytest.raises(BagWriteError, match='holds other files'):
        BagWriter(notes)
    assert sorted(p.name for p in notes.iterdir()) == ['notes.txt']
    empty = tmp_path / 'empty'
    empty.mkdir()
    write_states(empty, 3)   # an existing empty directory is fine (rosbag2 accepts it too)
    with BagReader(empty) as reader:
        assert reader.message_count == 3


def test_sigkill_keeps_all_but_the_last_second_and_recovers(procs, tmp_path):
    bag = tmp_path / 'killed'
    writer = procs.python(HELPERS / 'bag_writer_process.py', str(bag), '--rate', '500')
    writer.wait_for_line('writer: started', timeout=20)
    time.sleep(3.0)
    writer.signal(signal.SIGKILL)
    writer.popen.wait(5)
    reported = [int(line.split()[-1]) for line in writer.output.splitlines()
                if line.startswith('writer: wrote')]
    assert reported, writer.output
    with pytest.warns(TruncatedBagWarning):
        reader = BagReader(bag)
    with reader:
        kept = seqs(reader)
    assert kept == list(range(len(kept)))
    assert len(kept) >= reported[-1], 'lost data that had been flushed'
    assert len(kept) >= 3.0 * 500 - 500 * 1.0 - 200  # at most ~1 s (+ start-up slack) lost
    recovered = recover_bag(bag, tmp_path / 'recovered')
    assert_readable_by_all(recovered.output, kept)
    shutil.rmtree(bag)


def test_a_file_cut_anywhere_opens_or_is_refused_with_a_bag_error(tmp_path):
    bag = tmp_path / 'whole'
    write_states(bag, 50, chunk_size=512)
    data = (bag / 'whole_0.mcap').read_bytes()
    for cut in [*range(1, 120), *range(120, len(data), 97)]:
        piece = tmp_path / f'cut{cut}.mcap'
        piece.write_bytes(data[:cut])
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore', TruncatedBagWarning)
                with BagReader(piece) as reader:
                    assert reader.truncated
                    got = seqs(reader)
        except BagError as error:
            assert str(piece) in str(error)
            continue
        assert got == list(range(len(got))), 'a prefix, in order, nothing made up'
