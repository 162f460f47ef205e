"""Split bags, chunk compression, custom_data and CRC checks of BagWriter/BagReader.

Each written bag is read back by BagReader, rosbags (directory) and mcap's own reader, which
must all see every message exactly once.
"""

import warnings
from pathlib import Path

import pytest
import yaml
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagReader, BagWriter, recover_bag
from pma_bag.reader import TruncatedBagWarning
from pma_interfaces.msg import PmaState

STATE = 'pma_interfaces/msg/PmaState'
T0 = 1_700_000_000 * 10**9


def write(bag: Path, count: int, *, period_ns: int = 1_000_000, close: bool = True, **options):
    writer = BagWriter(bag, **options)
    writer.add_topic('/pma/state', STATE)
    for seq in range(count):
        writer.write('/pma/state', serialize_message(PmaState(seq=seq)), T0 + seq * period_ns)
    if close:
        writer.close()
    else:
        writer.flush()
    return writer


def bag_info(bag: Path) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


def assert_every_reader_sees(bag: Path, count: int) -> None:
    with BagReader(bag) as reader:
        assert [deserialize_message(m.data, PmaState).seq for m in reader.messages()] \
            == list(range(count))
        assert reader.message_count == count
    with AnyReader([bag]) as reader:
        got = [reader.deserialize(raw, c.msgtype).seq for c, _, raw in reader.messages()]
    assert got == list(range(count)), 'rosbags on the directory'
    seen = []
    for path in sorted(bag.glob('*.mcap')):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            assert reader.get_summary().statistics is not None, f'{path} was not finished'
            seen += [m.seq for _, _, _, m in reader.iter_decoded_messages()]
    assert sorted(seen) == list(range(count)), 'mcap + mcap_ros2, file by file'


def test_split_by_size_lists_every_file_in_metadata(tmp_path):
    bag = tmp_path / 'sized'
    write(bag, 5000, max_bag_size=64 * 1024, chunk_size=8 * 1024)
    info = bag_info(bag)
    names = [f'sized_{i}.mcap' for i in range(len(info['files']))]
    assert len(names) > 3
    assert info['relative_file_paths'] == names == [f['path'] for f in info['files']]
    assert sorted(p.name for p in bag.glob('*.mcap')) == sorted(names)
    assert sum(f['message_count'] for f in info['files']) == info['message_count'] == 5000
    for entry in info['files'][:-1]:
        # Split before the message that would go past the limit: at most one chunk over.
        assert (bag / entry['path']).stat().st_size < 64 * 1024 + 16 * 1024
    starts = [f['starting_time']['nanoseconds_since_epoch'] for f in info['files']]
    assert starts == sorted(starts) and starts[0] == T0
    assert_every_reader_sees(bag, 5000)


def test_split_by_duration_and_on_request(tmp_path):
    bag = tmp_path / 'timed'
    writer = BagWriter(bag, max_bag_duration_s=1.0)
    writer.add_topic('/pma/state', STATE)
    assert not writer.split(), 'nothing written yet: no empty file'
    for seq in range(3500):                      # 3.5 s at 1 kHz
        writer.write('/pma/state', serialize_message(PmaState(seq=seq)), T0 + seq * 1_000_000)
        if seq == 2200:
            assert writer.split()
    writer.close()
    info = bag_info(bag)
    # A file spans at most 1 s of log time (1001 messages at 1 kHz), as rosbag2 splits.
    assert [f['message_count'] for f in info['files']] == [1001, 1001, 199, 1001, 298]
    for entry in info['files']:
        assert entry['duration']['nanoseconds'] <= 1_000_000_000
    assert_every_reader_sees(bag, 3500)


@pytest.mark.parametrize('compression', ['zstd', 'lz4'])
def test_chunk_compression_is_read_by_every_reader(tmp_path, compression):
    plain = write(tmp_path / 'plain', 3000)
    packed = write(tmp_path / 'packed', 3000, compression=compression, max_bag_size=20_000,
                   chunk_size=16 * 1024)
    info = bag_info(tmp_path / 'packed')
    assert info['compression_format'] == '' and info['compression_mode'] == '', \
        'chunk compression is the storage\'s, not rosbag2\'s file/message compression'
    assert len(info['files']) > 1
    for path in (tmp_path / 'packed').glob('*.mcap'):
        with open(path, 'rb') as stream:
            chunks = make_reader(stream).get_summary().chunk_indexes
        assert chunks and {c.compression for c in chunks} == {compression}
    size = sum(p.stat().st_size for p in packed.file_paths)
    assert size < 0.6 * plain.mcap_path.stat().st_size
    with BagReader(tmp_path / 'packed') as reader:
        assert reader.compressions == {compression}
        assert all(report.ok for report in reader.check())
    assert_every_reader_sees(tmp_path / 'packed', 3000)


def test_custom_data_in_metadata_yaml_and_in_a_crashed_file(tmp_path):
    note = {'note': 'first run: muscle 2, new sleeve', 'rig': 'bench-a'}
    bag = tmp_path / 'noted'
    write(bag, 10, custom_data=note)
    assert bag_info(bag)['custom_data'] == note
    with BagReader(bag) as reader:
        assert reader.custom_data == note
    # A recorder killed before close: no metadata.yaml, but the Metadata record written at
    # open (and again when custom_data changed) keeps the experiment's description.
    crashed = tmp_path / 'crashed'
    writer = write(crashed, 10, close=False, custom_data=note, compression='zstd')
    writer.update_custom_data({'firmware': 'pma_fw 1.2.0'})
    writer.flush()
    with pytest.warns(TruncatedBagWarning), BagReader(crashed) as reader:
        assert reader.custom_data == {**note, 'firmware': 'pma_fw 1.2.0'}
    report = recover_bag(crashed, tmp_path / 'recovered')
    assert bag_info(report.output)['custom_data'] == {**note, 'firmware': 'pma_fw 1.2.0'}
    with BagReader(report.output) as reader:
        assert reader.compressions == {'zstd'}


def test_a_split_dumps_the_new_file_entries_only_and_the_record_reads_as_before(
        tmp_path, monkeypatch):
    """The rosbag2 Metadata record lists every file and is written twice per split. Dumped
    whole each time, a split of a 300-file bag took 110 ms, and a burst of 300
    ~/split_bagfile requests stalled a 200 Hz recorder for tens of seconds (samples lost):
    a finished file's entry is dumped once now. The record says what it said."""
    real_dump = yaml.safe_dump
    entries_dumped = []

    def file_entries(value) -> int:
        if isinstance(value, dict):
            return ({'path', 'starting_time', 'message_count'} <= value.keys()) + sum(
                file_entries(item) for item in value.values())
        return sum(file_entries(item) for item in value) if isinstance(value, list) else 0

    def counting_dump(data, *args, **kwargs):
        entries_dumped.append(file_entries(data))
        return real_dump(data, *args, **kwargs)

    monkeypatch.setattr(yaml, 'safe_dump', counting_dump)
    bag = tmp_path / 'many'
    writer = BagWriter(bag, custom_data={'note': 'split 200 times'})
    writer.add_topic('/pma/state', STATE)
    splits = 200
    for seq in range(splits + 1):
        writer.write('/pma/state', serialize_message(PmaState(seq=seq)), T0 + seq * 1_000_000)
        assert seq == splits or writer.split()
    writer.close()
    # Whole, the records would dump about splits**2 (40,000) entries; metadata.yaml (at
    # close) dumps them once.
    assert sum(entries_dumped) < 5 * splits, sum(entries_dumped)
    info = bag_info(bag)
    assert len(info['files']) == splits + 1
    with BagReader(bag) as reader:
        record = reader.files[-1].metadata_records['rosbag2']['serialized_metadata']
        assert reader.custom_data == {'note': 'split 200 times'}
    assert yaml.safe_load(record) == info
    assert record == real_dump(info, default_flow_style=False, sort_keys=False)
    assert_every_reader_sees(bag, splits + 1)


def test_a_killed_split_recording_reads_in_split_order_and_recovers(tmp_path):
    bag = tmp_path / 'killed'
    writer = write(bag, 6000, close=False, max_bag_size=16 * 1024, chunk_size=4096)
    assert len(writer.file_paths) > 10, 'enough files that _10 sorts wrongly as text'
    with pytest.warns(TruncatedBagWarning), BagReader(bag) as reader:
        assert [deserialize_message(m.data, PmaState).seq for m in reader.messages()] \
            == list(range(6000))
    recovered = recover_bag(bag, tmp_path / 'recovered')
    assert recovered.message_count == 6000
    assert_every_reader_sees(recovered.output, 6000)


def test_check_finds_a_flipped_byte_like_mcaps_validating_reader(tmp_path):
    bag = tmp_path / 'checked'
    write(bag, 2000, chunk_size=4096, compression='zstd')
    path = bag / 'checked_0.mcap'
    with BagReader(bag) as reader:
        (report,) = reader.check()
    assert report.ok and report.chunks_checked > 3 and report.chunks_without_crc == 0
    assert (report.data_section, report.summary) == ('ok', 'ok')
    data = bytearray(path.read_bytes())
    with open(path, 'rb') as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[1]
    # A byte inside the second chunk's compressed records.
    data[chunk.chunk_start_offset + chunk.chunk_length - 40] ^= 0x5A
    broken = tmp_path / 'broken.mcap'
    broken.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', TruncatedBagWarning)
        with BagReader(broken) as reader:
            (report,) = reader.check()
    assert not report.ok and any('chunk' in p or 'data section' in p for p in report.problems)
    with open(broken, 'rb') as stream, pytest.raises((McapError, Exception)):
        for _ in NonSeekingReader(stream, validate_crcs=True).iter_messages():
            pass


def test_check_reports_a_file_that_was_not_closed(tmp_path):
    bag = tmp_path / 'open'
    write(bag, 500, close=False)
    with pytest.warns(TruncatedBagWarning), BagReader(bag) as reader:
        (report,) = reader.check()
    assert not report.ok and report.data_section == 'missing'
    assert report.chunks_checked >= 1
