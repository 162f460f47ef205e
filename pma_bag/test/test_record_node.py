"""The recorder node, in-process: what it does before any discovery has happened."""

from __future__ import annotations

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.context import Context
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter

from pma_bag.record import DEFAULT_TOPICS, Recorder, RecordOptions, parse_args
from pma_bag.state_seq import fast_state_seq
from pma_common.parameters import refusal_reason
from pma_interfaces.srv import StartRecording


@pytest.fixture
def context():
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.shutdown(context=context)


@pytest.fixture
def recorder(context):
    node = Recorder(RecordOptions(), context=context)
    yield node
    node.finish_bag()
    node.destroy_node()


def start(recorder: Recorder, path='', topics=(), request_id='') -> StartRecording.Response:
    """~/start as the service calls it (it answers without awaiting: no publishers here)."""
    request = StartRecording.Request(bag_path=str(path), topics=list(topics),
                                     request_id=request_id)
    coroutine = recorder.on_start(request, StartRecording.Response())
    with pytest.raises(StopIteration) as answered:
        coroutine.send(None)
    return answered.value.value


def set_topics(recorder: Recorder, topics: list[str]):
    parameter = Parameter('topics', Parameter.Type.STRING_ARRAY, topics)
    return recorder.set_parameters([parameter])[0]


def test_the_pma_topics_are_subscribed_at_once_not_after_discovery(recorder):
    """rosbag2 subscribes what it can at start; the old recorder waited for a graph check to
    find publishers, and each bag missed its first 0.5-3 s of already streaming topics."""
    subscribed = set(recorder.subscribed)
    assert {recorder.resolve_topic_name(t) for t in DEFAULT_TOPICS} <= subscribed
    assert all(e.subscription is not None for e in recorder.subscribed.values())


def test_a_topics_set_at_run_time_applies_to_the_next_bag(recorder, tmp_path):
    """Regression: `pma param set recorder topics ...` was accepted and then ignored (the
    value was read once at start); the next sweep recorded every default topic."""
    assert start(recorder, tmp_path / 'a').success
    before = list(recorder.bag.topics)
    assert set_topics(recorder, ['pma/state', 'extra/topic']).successful
    assert recorder.bag.topics == before, 'the open bag keeps its topics'
    answer = start(recorder, tmp_path / 'b')
    assert answer.success, answer.message
    assert recorder.bag.topics == ['/pma/state', '/extra/topic']
    assert '/extra/topic' in recorder.wanted_topics()    # looked up in the graph from now
    assert set_topics(recorder, ['pma/state', 'pma/pressure']).successful
    assert '/pma/pressure' in recorder.subscribed, 'a PMA topic is presubscribed at once'


def test_a_start_sent_again_under_its_request_id_answers_for_the_bag_it_opened(recorder,
                                                                              tmp_path):
    """A client resends a start whose answer it did not get (lost to a new client in
    discovery): the resend must not finish the bag the first one opened and open another."""
    first = start(recorder, tmp_path / 'a', request_id='a1')
    assert first.success, first.message
    opened = recorder.bag
    again = start(recorder, tmp_path / 'a', request_id='a1')     # the same request again
    assert again.success, again.message
    assert recorder.bag is opened and again.bag_path == first.bag_path
    other = start(recorder, tmp_path / 'b', request_id='b2')
    assert other.success and recorder.bag is not opened
    assert other.bag_path == str(tmp_path / 'b')
    unnamed = [start(recorder, tmp_path / name) for name in ('c', 'd')]
    assert [answer.bag_path for answer in unnamed] == [str(tmp_path / 'c'),
                                                       str(tmp_path / 'd')]
    assert start(recorder, tmp_path / 'e', request_id='').success
    assert recorder.bag.path == tmp_path / 'e', 'an empty request_id is always a new bag'
    recorder.finish_bag()
    assert start(recorder, tmp_path / 'f', request_id='b2').bag_path == str(tmp_path / 'f'), \
        'a finished bag is not answered for'


def test_bad_topic_names_are_refused_with_the_reason(context, recorder, tmp_path):
    """Regression: topics = ['bad topic!'] was accepted (and a bag started with it would
    have failed in rcl)."""
    refused = set_topics(recorder, ['pma/state', 'bad topic!'])
    assert not refused.successful
    assert refused.reason.startswith("topics: 'bad topic!' is not a valid topic name: topic "
                                     'name must not contain characters'), refused.reason
    assert 'at /' not in refused.reason, "rcl's source location is left out"
    assert not set_topics(recorder, []).successful
    assert recorder.get_parameter('topics').value == DEFAULT_TOPICS
    answer = start(recorder, tmp_path / 'c', topics=['a//b'])
    assert not answer.success and 'repeated' in answer.message, answer.message
    assert recorder.bag is None and not (tmp_path / 'c').exists()
    with pytest.raises(ParameterException) as at_start:   # node_or_exit: one line, no start
        Recorder(RecordOptions(), ['1st'], context=context)
    assert refusal_reason(at_start.value) == ("topics: '1st' is not a valid topic name: "
                                              'topic name token must not start with a number')


def test_a_refused_start_is_answered_and_the_recorder_stays_ok(recorder, tmp_path):
    """Regression: a ~/start to a path holding a bag (the caller's error) left the recorder
    on ERROR in /diagnostics until the next good bag, and `pma status` failed meanwhile."""
    assert start(recorder, tmp_path / 'a').success
    recorder.finish_bag()
    for path in (tmp_path / 'a', '/proc/nope'):
        answer = start(recorder, path)
        assert not answer.success and str(path) in answer.message, answer.message
        status, values = recorder.status()
        assert (status.level, status.message) == (DiagnosticStatus.OK, 'idle (no bag open)')
        assert values['state'] == 'idle' and status.hardware_id == str(tmp_path / 'a')
    # A refused start leaves the open bag recording (it used to be finished first).
    assert start(recorder, tmp_path / 'b').success
    assert not start(recorder, tmp_path / 'a').success
    assert recorder.bag is not None and recorder.bag.path == tmp_path / 'b'
    assert recorder.status()[0].level == DiagnosticStatus.OK
    # A recording that fails while running is still an ERROR.
    recorder.fail(recorder.bag, 'No space left on device')
    status, _ = recorder.status()
    assert (status.level, status.message) == (DiagnosticStatus.ERROR, 'No space left on device')


def test_pause_is_the_open_bags_and_a_new_bag_starts_recording(recorder, tmp_path):
    """The pause lives in the bag's session; while idle the recorder keeps the last one."""
    assert recorder.read_seq is fast_state_seq, 'the offset read passed its start-up check'
    assert recorder.set_paused(True) and recorder.paused and not recorder.set_paused(True)
    assert start(recorder, tmp_path / 'a').success and not recorder.paused
    assert recorder.set_paused(True) and recorder.bag.paused
    assert recorder.status()[1]['state'] == 'paused'
    recorder.finish_bag()
    assert recorder.paused and not recorder.set_paused(True)
    assert recorder.set_paused(False) and not recorder.paused


@pytest.mark.parametrize('value', ['nan', 'inf'])
def test_a_split_duration_that_is_not_a_number_is_refused_at_parsing(value):
    """Regression: `nan` passed `< 0`, and BagWriter's int(nan * 1e9) ended the recorder."""
    with pytest.raises(SystemExit) as refused:
        parse_args(['-o', 'b', '--max-bag-duration', value])
    assert refused.value.code == 2
