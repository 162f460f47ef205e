"""BagWriter output against the rosbag2 (jazzy) compatibility checklist, read by three readers.

Checklist numbers refer to section 2 of the rosbag2-mcap guide (summarised in docs/bags.md).
Values are compared after decoding, never as bytes (rclpy leaves padding bytes undefined).
"""

import math
import os
import re
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.reader import make_reader
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagReader, BagWriter
from pma_bag.schemas import (
    SCHEMA_DELIMITER,
    TYPE_HASH_PATTERN,
    interface_file,
    message_definition,
    type_hash,
)
from pma_interfaces.msg import PmaState

STATE = 'pma_interfaces/msg/PmaState'
DIAGNOSTICS = 'diagnostic_msgs/msg/DiagnosticArray'
RELIABLE = {'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
            'durability': 'volatile', 'deadline': {'sec': 9223372036, 'nsec': 854775807},
            'lifespan': {'sec': 9223372036, 'nsec': 854775807}, 'liveliness': 'automatic',
            'liveliness_lease_duration': {'sec': 9223372036, 'nsec': 854775807},
            'avoid_ros_namespace_conventions': False}
LATCHED = {**RELIABLE, 'durability': 'transient_local', 'depth': 1}
QOS_KEYS = set(RELIABLE)


def make_state(seq: int) -> PmaState:
    msg = PmaState(seq=seq, device_time_s=seq * 0.002, gauge_pressure_pa=123.5 * seq,
                   length_m=0.3 - 1e-5 * seq, gauge_setpoint_pa=2e5, valve_state=seq % 3,
                   status=seq % 16, pressure_adc=seq % 1024, echo_us=1700 + seq)
    msg.header.frame_id = 'muscle'
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + seq // 500, (seq % 500) * 2_000_000
    if seq % 7 == 3:
        msg.length_m = math.nan
    return msg


def make_diagnostics(seq: int) -> DiagnosticArray:
    status = DiagnosticStatus(level=DiagnosticStatus.WARN, name=f'pma: {seq}', message='test',
                              values=[KeyValue(key='seq', value=str(seq))])
    return DiagnosticArray(status=[status])


def state_values(msg) -> tuple:
    """Field values of a PmaState from any reader (rclpy, rosbags or mcap_ros2 object)."""
    length = msg.length_m
    return (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec, msg.seq,
            msg.device_time_s, msg.gauge_pressure_pa, 'nan' if math.isnan(length) else length,
            msg.gauge_setpoint_pa, msg.valve_state, msg.status, msg.pressure_adc, msg.echo_us)


def diagnostics_values(msg) -> tuple:
    # `byte` fields: rclpy gives bytes, rosbags and mcap_ros2 give int.
    return tuple((int.from_bytes(s.level) if isinstance(s.level, bytes) else s.level, s.name,
                  s.message, tuple((v.key, v.value) for v in s.values)) for s in msg.status)


@pytest.fixture(scope='module')
def written(tmp_path_factory):
    """A bag of 600 PmaState (4 small chunks and more) + 20 DiagnosticArray; and the truth."""
    bag = tmp_path_factory.mktemp('bags') / 'checklist'
    t0 = time.time_ns()
    truth = []
    with BagWriter(bag, chunk_size=16 * 1024) as writer:
        writer.add_topic('/pma/state', STATE, [RELIABLE])
        writer.add_topic('/diagnostics', DIAGNOSTICS, [RELIABLE, LATCHED])
        for seq in range(600):
            log_time = t0 + seq * 2_000_000
            writer.write('/pma/state', serialize_message(make_state(seq)), log_time)
            truth.append(('/pma/state', log_time, state_values(make_state(seq))))
            if seq % 30 == 0:
                msg = make_diagnostics(seq)
                writer.write('/diagnostics', serialize_message(msg), log_time + 1)
                truth.append(('/diagnostics', log_time + 1, diagnostics_values(msg)))
    return bag, truth


def mcap_file(bag: Path) -> Path:
    return bag / f'{bag.name}_0.mcap'


def test_1_profile_and_layout(written):
    bag, _ = written
    assert sorted(p.name for p in bag.iterdir()) == ['checklist_0.mcap', 'metadata.yaml']
    with open(mcap_file(bag), 'rb') as stream:
        assert make_reader(stream).get_header().profile == 'ros2'


def test_2_summary_has_statistics_and_chunks_have_message_indexes(written):
    bag, truth = written
    with open(mcap_file(bag), 'rb') as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == len(truth)
    assert len(summary.chunk_indexes) > 1
    for chunk in summary.chunk_indexes:
        assert chunk.message_index_offsets, 'chunk without message index'


def test_3_schemas_are_ros2msg_with_rosbag2_separators(written):
    bag, _ = written
    with open(mcap_file(bag), 'rb') as stream:
        schemas = make_reader(stream).get_summary().schemas.values()
    assert sorted(s.name for s in schemas) == sorted([STATE, DIAGNOSTICS])
    for schema in schemas:
        text = schema.data.decode()
        assert schema.encoding == 'ros2msg'
        assert re.fullmatch(r'[a-z_]+/msg/[A-Za-z0-9]+', schema.name)
        for line in text.splitlines():
            if line.startswith('='):
                assert line == '=' * 80
        headers = re.findall(rf'{SCHEMA_DELIMITER}\nMSG: (\S+)\n', text)
        assert all(re.fullmatch(r'[a-z_]+/[A-Za-z0-9]+', h) for h in headers)
        assert len(headers) == len(set(headers)), 'a dependency repeated'
        generate_dynamic(schema.name, text)  # parses, or raises


def test_schema_text_is_installed_msg_files_in_rosbag2_order():
    """Root verbatim, then dependencies depth first in sorted order (rosbag2's algorithm)."""
    text = message_definition(DIAGNOSTICS)
    parts = text.split(f'\n{SCHEMA_DELIMITER}\n')
    names = ['diagnostic_msgs/DiagnosticArray'] + [p.split('\n', 1)[0][5:] for p in parts[1:]]
    assert names == ['diagnostic_msgs/DiagnosticArray', 'diagnostic_msgs/DiagnosticStatus',
                     'diagnostic_msgs/KeyValue', 'std_msgs/Header', 'builtin_interfaces/Time']
    for name, part in zip(names, parts, strict=True):
        body = part if name == names[0] else part.split('\n', 1)[1]
        package, type_name = name.split('/')
        assert body == interface_file(package, type_name, '.msg').read_text()


def test_4_channels(written):
    bag, _ = written
    with open(mcap_file(bag), 'rb') as stream:
        summary = make_reader(stream).get_summary()
    for channel in summary.channels.values():
        assert channel.message_encoding == 'cdr'
        assert channel.schema_id != 0
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert isinstance(profiles, list) and profiles
        assert all(set(p) == QOS_KEYS for p in profiles)
        type_name = summary.schemas[channel.schema_id].name
        assert TYPE_HASH_PATTERN.match(channel.metadata['topic_type_hash'])
        assert channel.metadata['topic_type_hash'] == type_hash(type_name)


def test_5_messages_are_cdr_le_with_epoch_log_times(written):
    bag, _ = written
    with open(mcap_file(bag), 'rb') as stream:
        messages = [m for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    assert all(m.data[:4] == b'\x00\x01\x00\x00' for m in messages)
    times = [m.log_time for m in messages]
    assert times == sorted(times)
    assert min(times) > 1_500_000_000 * 10**9  # ns since 1970, not since boot


def test_6_and_7_metadata_yaml_matches_the_file(written):
    bag, truth = written
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    required = {'version', 'storage_identifier', 'duration', 'starting_time', 'message_count',
                'topics_with_message_count', 'compression_format', 'compression_mode',
                'relative_file_paths', 'files', 'custom_data', 'ros_distro'}
    assert required <= set(info)
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert all((bag / p).is_file() for p in info['relative_file_paths'])
    with open(mcap_file(bag), 'rb') as stream:
        summary = make_reader(stream).get_summary()
    stats = summary.statistics
    assert info['message_count'] == stats.message_count == len(truth)
    assert info['starting_time']['nanoseconds_since_epoch'] == stats.message_start_time
    assert info['duration']['nanoseconds'] == stats.message_end_time - stats.message_start_time
    assert info['files'][0]['message_count'] == stats.message_count
    channels = {c.topic: c for c in summary.channels.values()}
    for entry in info['topics_with_message_count']:
        meta = entry['topic_metadata']
        channel = channels[meta['name']]
        assert entry['message_count'] == stats.channel_message_counts[channel.id]
        assert meta['offered_qos_profiles'] == yaml.safe_load(
            channel.metadata['offered_qos_profiles'])
        assert meta['type_description_hash'] == channel.metadata['topic_type_hash']
        assert meta['serialization_format'] == 'cdr'


def decoded_by_rosbags(path: Path) -> list:
    out = []
    with AnyReader([path]) as reader:
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            values = (state_values(msg) if connection.topic == '/pma/state'
                      else diagnostics_values(msg))
            out.append((connection.topic, timestamp, values))
    return out


def test_8_rosbags_reads_directory_and_bare_file(written):
    bag, truth = written
    assert decoded_by_rosbags(bag) == truth
    assert decoded_by_rosbags(mcap_file(bag)) == truth


def test_8_mcap_ros2_decoder_reads_the_file(written):
    bag, truth = written
    out = []
    with open(mcap_file(bag), 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
            values = (state_values(msg) if channel.topic == '/pma/state'
                      else diagnostics_values(msg))
            out.append((channel.topic, message.log_time, values))
    assert out == truth


def test_8_bag_reader_with_rclpy_deserialize(written):
    bag, truth = written
    classes = {STATE: (PmaState, state_values), DIAGNOSTICS: (DiagnosticArray,
                                                              diagnostics_values)}
    with BagReader(bag) as reader:
        assert {t.name: t.message_count for t in reader.topics.values()} == {
            '/pma/state': 600, '/diagnostics': 20}
        assert reader.topics['/diagnostics'].offered_qos_profiles == [RELIABLE, LATCHED]
        out = []
        for message in reader.messages():
            msg_type, values = classes[message.type_name]
            out.append((message.topic, message.log_time_ns,
                        values(deserialize_message(message.data, msg_type))))
    assert out == truth


def test_bag_reader_filters_topics_and_start_time(written):
    bag, truth = written
    start = truth[100][1]
    with BagReader(mcap_file(bag)) as reader:
        got = [(m.topic, m.log_time_ns) for m in reader.messages(['/diagnostics'], start)]
    assert got == [(t, ts) for t, ts, _ in truth if t == '/diagnostics' and ts >= start]


@pytest.mark.parametrize('frame_id', ['', 'a', 'ab', 'abc', 'pma_link', 'x' * 13])
def test_the_recorder_reads_pma_state_seq_without_decoding(frame_id):
    """The CDR offset of seq moves with the frame_id's length: every alignment case."""
    from rclpy.serialization import serialize_message

    from pma_bag.record import pma_state_seq
    from pma_interfaces.msg import PmaState

    state = PmaState(seq=4_000_000_123)
    state.header.frame_id = frame_id
    state.header.stamp.sec = 17
    assert pma_state_seq(serialize_message(state)) == 4_000_000_123


def test_info_into_a_pipe_closed_early_ends_quietly(written):
    """`ros2 run pma_bag info BAG | head -3` printed a BrokenPipeError traceback."""
    bag, _ = written
    info = Path(__file__).resolve().parents[2] / 'ros2_ws' / 'install' / 'pma_bag' / 'lib' / \
        'pma_bag' / 'info'
    read, write = os.pipe()
    os.close(read)                       # head has read its lines and left
    try:
        result = subprocess.run([str(info), str(bag)], stdout=write, stderr=subprocess.PIPE,
                                text=True, timeout=60, check=False)
    finally:
        os.close(write)
    assert (result.returncode, result.stderr) == (141, ''), result.stderr
