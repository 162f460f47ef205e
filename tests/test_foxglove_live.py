"""The live view: foxglove_live forwards PMA topics to a Foxglove WebSocket client, unchanged.

The bridge runs as `ros2 run pma_bringup foxglove_live` does; a protocol-level client
(pma_bringup.foxglove_client, the Foxglove WebSocket protocol as the app speaks it) subscribes to
the advertised channels and decodes each message twice: with rclpy (the class the advertised
schema name names) and with rosbags from the advertised `ros2msg` schema text alone, as the
Foxglove app does. Publishers are real processes: a stand-in whose values follow from the
sequence number (every value and the order are checked, through publisher restarts, one with
other QoS, by two viewers at once: one offering only the subprotocol `foxglove.websocket.v1`, as
PlotJuggler and older Lichtblick do, one only `foxglove.sdk.v1`), and the real chain on the
simulated rig (driver, model, controller), compared
with what a plain subscriber receives and checked against the layout's topics and paths.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import signal
import socket
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import deserialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from helpers.live_publisher import prediction_fields, state_fields
from pma_bag.record import message_class
from pma_bringup.foxglove_client import FoxgloveClient, Received
from pma_common import names
from pma_interfaces.msg import PmaState
from support.domains import another_domain
from support.procs import ROOT, children_of, running
from support.ros import SpinningNode, shutdown, wait_until

pytestmark = pytest.mark.integration

HELPERS = ROOT / 'tests' / 'helpers'
LAYOUT = ROOT / 'pma_bringup' / 'foxglove' / 'pma_testbed.json'
URL = re.compile(r'ws://\S+')
STATE, PREDICTION = '/pma/state', '/pma/prediction'
OLD, SDK = 'foxglove.websocket.v1', 'foxglove.sdk.v1'


def start_bridge(procs, *ros_args: str, name: str = 'foxglove_live'):
    bridge = procs.ros2_run('pma_bringup', 'foxglove_live', name=name,
                            ros_args=['-p', 'port:=0', *ros_args])
    url = URL.search(bridge.wait_for_line('ws://', 30)).group(0)
    return bridge, url


class Decoder:
    """Both decodings of a channel's payloads: rclpy, and rosbags from the schema text."""

    def __init__(self, channel: dict):
        assert channel['encoding'] == 'cdr' and channel['schemaEncoding'] == 'ros2msg'
        self.name = channel['schemaName']
        self.cls = message_class(self.name)
        self.store = get_typestore(Stores.EMPTY)
        self.store.register(get_types_from_msg(channel['schema'], self.name))

    def __call__(self, message: Received):
        return (deserialize_message(message.payload, self.cls),
                self.store.deserialize_cdr(message.payload, self.name))


def check_pairs(client: FoxgloveClient, seqs: list[int],
                predicted: list[int] | None = None) -> None:
    """Every state of `seqs` and prediction of `predicted` (default: the same) arrived, in
    order, with its values, once."""
    predicted = seqs if predicted is None else predicted
    decode = {topic: Decoder(client.channel_for(topic)) for topic in (STATE, PREDICTION)}
    states = [decode[STATE](m) for m in client.received(STATE)]
    predictions = [decode[PREDICTION](m) for m in client.received(PREDICTION)]
    assert [s.seq for s, _ in states] == seqs
    assert [p.header.frame_id for p, _ in predictions] == [f'seq{k}' for k in predicted]
    for (state, independent), seq in zip(states, seqs, strict=True):
        for key, value in state_fields(seq).items():
            assert getattr(state, key) == value and getattr(independent, key) == value, key
    for (prediction, independent), seq in zip(predictions, predicted, strict=True):
        for key, value in prediction_fields(seq).items():
            assert getattr(prediction, key) == value == getattr(independent, key), key
        assert independent.header.frame_id == f'seq{seq}'
    for topic in (STATE, PREDICTION):
        log_times = [m.log_time_ns for m in client.received(topic)]
        assert log_times == sorted(log_times), f'{topic}: log times out of order'


def publish(procs, tmp_path, first: int, count: int, *extra: str, go: bool = False):
    args = ['--first-seq', str(first), '--count', str(count), '--rate', '100', *extra]
    if go:
        args += ['--go-file', str(tmp_path / 'go')]
    return procs.python(HELPERS / 'live_publisher.py', *args, name=f'publisher{first}')


def test_values_and_order_survive_publisher_restarts(procs, tmp_path):
    """Both kinds of viewer at once: each gets every value, in order, on the same channels."""
    bridge, url = start_bridge(procs)
    clients = [FoxgloveClient(url, subprotocols=[OLD]), FoxgloveClient(url, subprotocols=[SDK])]
    try:
        assert [c.subprotocol for c in clients] == [OLD, SDK]
        for client in clients:
            assert client.wait(lambda c: c.server_info, 10, 'serverInfo')['capabilities'] \
                == [], 'read-only: no publish, services or parameters for clients'
            client.follow([STATE, PREDICTION])
        first = publish(procs, tmp_path, 0, 200, go=True)
        channels = {t: clients[0].channel_for(t, 20)['id'] for t in (STATE, PREDICTION)}
        for client in clients:
            assert {t: client.channel_for(t, 20)['id'] for t in channels} == channels
            assert client.channel_for(STATE)['schemaName'] == 'pma_interfaces/msg/PmaState'
        assert clients[0].channel_for(STATE) == clients[1].channel_for(STATE)
        time.sleep(0.3)          # our subscribe request reaches the server
        (tmp_path / 'go').touch()
        first.wait_for_line('published 200', 30)
        expected = list(range(200))
        for client in clients:
            client.wait(lambda c: len(c.received(PREDICTION)) >= 200, 10, '200 pairs')
            check_pairs(client, expected)

        # The publisher is gone; a new one starts where it left off, same QoS: same channels.
        first.popen.wait(10)
        second = publish(procs, tmp_path, 1000, 200)
        second.wait_for_line('published 200', 30)
        expected += list(range(1000, 1200))
        for client in clients:
            client.wait(lambda c: len(c.received(PREDICTION)) >= 400, 10, '400 pairs')
            check_pairs(client, expected)

        # Killed mid-stream (no goodbye to DDS), then back with best-effort QoS: the bridge
        # subscribes again to match it, on the same channels.
        third = publish(procs, tmp_path, 2000, 10_000)
        third.wait_for_line('publishing', 30)
        time.sleep(0.5)
        third.signal(signal.SIGKILL)
        third.popen.wait(10)
        bridge_output_before = len(bridge.output)
        fourth = publish(procs, tmp_path, 5000, 200, '--best-effort')
        fourth.wait_for_line('published 200', 30)
        assert 'subscribing again' in bridge.output[bridge_output_before:]
        time.sleep(0.5)
        for client in clients:
            check_the_restarts(client, expected, channels)
    finally:
        for client in clients:
            client.close()


def check_the_restarts(client: FoxgloveClient, expected: list[int], channels: dict) -> None:
    """The killed publisher's part and the best-effort one, as one viewer received them."""
    decode = Decoder(client.channel_for(STATE))
    seqs = [decode(m)[0].seq for m in client.received(STATE)]
    third_part = [k for k in seqs if 2000 <= k < 5000]
    best_effort = [k for k in seqs if k >= 5000]
    assert third_part == list(range(2000, 2000 + len(third_part))) and third_part
    assert best_effort == sorted(best_effort) and len(set(best_effort)) == len(best_effort)
    assert len(best_effort) >= 190, f'{len(best_effort)} of 200 best-effort samples'
    # SIGKILL may land between a state and its prediction: the last state of the killed
    # publisher may come without one, nothing else may.
    third_predicted = [int(p.header.frame_id[3:]) for p, _ in
                       map(Decoder(client.channel_for(PREDICTION)),
                           client.received(PREDICTION))
                       if 2000 <= int(p.header.frame_id[3:]) < 5000]
    assert third_predicted == third_part[:len(third_predicted)]
    assert len(third_part) - len(third_predicted) <= 1, (third_part, third_predicted)
    check_pairs(client, expected + third_part + best_effort,
                expected + third_predicted + best_effort)
    assert {t: client.channel_for(t)['id'] for t in (STATE, PREDICTION)} == channels
    assert not client.unadvertised


def test_a_viewer_gets_the_subprotocol_it_lists_first(procs):
    """foxglove.websocket.v1 and foxglove.sdk.v1 are the same protocol: either, or both in
    either order, is answered with the first listed; a client offering neither is refused as
    before (HTTP 400)."""
    _bridge, url = start_bridge(procs)
    for offered in ([OLD], [SDK], [OLD, SDK], [SDK, OLD], ['x.unknown', OLD, SDK]):
        with connect(url, subprotocols=offered, open_timeout=10) as ws:
            assert ws.subprotocol == next(o for o in offered if o in (OLD, SDK)), offered
            info = json.loads(ws.recv(timeout=10))
            assert info['op'] == 'serverInfo' and info['capabilities'] == []
    for offered in (['foxglove.websocket.v2'], None):
        with pytest.raises(InvalidStatus) as refused:
            connect(url, subprotocols=offered, open_timeout=10)
        assert refused.value.response.status_code == 400


def bridge_resources(pid: int) -> tuple[int, int]:
    """(threads, open file descriptors) of a process."""
    return len(os.listdir(f'/proc/{pid}/task')), len(os.listdir(f'/proc/{pid}/fd'))


def test_viewers_coming_and_going_leave_no_connection_or_thread_behind(procs):
    """400 connections to 127.0.0.1, 16 at a time, as viewers and broken clients make them:
    WebSocket sessions closed properly or reset, bare connects, half a request, and 20 that
    stall in the request (closed by the bridge after its handshake timeout). Afterwards the
    bridge has the threads and descriptors it had, and still serves a viewer."""
    bridge, url = start_bridge(procs)
    pid = bridge.popen.pid
    host, port = '127.0.0.1', int(url.rsplit(':', 1)[1])
    request = (f'GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n'
               'Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n'
               f'Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {OLD}\r\n\r\n')
    with connect(url, subprotocols=[OLD], open_timeout=10) as ws:   # the server's threads up
        ws.recv(timeout=10)
    time.sleep(1.0)
    threads0, fds0 = bridge_resources(pid)
    handshake_threads = [t for t in os.listdir(f'/proc/{pid}/task')
                         if Path(f'/proc/{pid}/task/{t}/comm').read_text().strip()
                         == 'fg-handshake']
    assert len(handshake_threads) == 1

    def viewer(k: int) -> None:
        with connect(url, subprotocols=[OLD] if k % 2 else [SDK], open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))['op'] == 'serverInfo'

    def reset(k: int) -> None:          # upgraded, then gone without a close frame (RST)
        sock = socket.create_connection((host, port), timeout=10)
        sock.sendall(request.encode())
        assert sock.recv(4096).startswith(b'HTTP/1.1 101')
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack('ii', 1, 0))
        sock.close()

    def bare(k: int) -> None:
        socket.create_connection((host, port), timeout=10).close()

    def half(k: int) -> None:
        with socket.create_connection((host, port), timeout=10) as sock:
            sock.sendall(request[:k % 60 + 1].encode())

    stalled = [socket.create_connection((host, port), timeout=10) for _ in range(20)]
    for sock in stalled:
        sock.sendall(b'GET / HTTP/1.1\r\n')
    started = time.monotonic()
    kinds = [viewer] * 160 + [reset] * 80 + [bare] * 70 + [half] * 70
    with ThreadPoolExecutor(16) as pool:
        list(pool.map(lambda k: kinds[k](k), range(len(kinds)), timeout=120))
    churn_s = time.monotonic() - started
    threads1, _ = bridge_resources(pid)
    assert threads1 <= threads0 + 2, (threads0, threads1)
    # The stalled ones are closed by the bridge (HANDSHAKE_TIMEOUT_S = 10 s), not by us.
    for sock in stalled:
        sock.settimeout(20)
        assert sock.recv(100) == b'', 'a stalled request is closed by the bridge'
        sock.close()
    wait_until(lambda: bridge_resources(pid)[1] <= fds0, 15,
               f'the bridge back to {fds0} descriptors')
    wait_until(lambda: bridge_resources(pid)[0] <= threads0, 30,
               f'the bridge back to {threads0} threads')
    client = FoxgloveClient(url, subprotocols=[OLD])
    try:
        assert client.wait(lambda c: c.server_info, 10, 'serverInfo')
    finally:
        client.close()
    assert churn_s < 60, f'{len(kinds)} connections took {churn_s:.1f} s'


@pytest.fixture(scope='module')
def rig(module_procs, tmp_path_factory):
    """The simulated rig, driver, model and controller, and the bridge next to them."""
    port = tmp_path_factory.mktemp('rig') / 'pma0'
    fake = module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port),
                                 '--seed', '3')
    fake.wait_for_line('device at', 20)
    module_procs.ros2_run('pma_driver', 'driver_node',
                          ros_args=['-p', f'port:={port}', '-p', 'sample_rate_hz:=50.0'])
    module_procs.ros2_run('pma_model', 'model_node')
    module_procs.ros2_run('pma_control', 'length_controller')
    bridge, url = start_bridge(module_procs)
    return bridge, url


def test_the_rig_reaches_a_viewer_as_a_plain_subscriber_sees_it(rig):
    _bridge, url = rig
    probe = SpinningNode('live_view_probe')
    lock = threading.Lock()
    seen: dict[int, PmaState] = {}

    def on_state(msg: PmaState) -> None:
        with lock:
            seen[msg.seq] = msg

    probe.node.create_subscription(PmaState, names.STATE, on_state, qos_profile_sensor_data)
    client = FoxgloveClient(url)
    try:
        # The probe is a new participant; the bridge has long been subscribed. Compare only
        # once the probe gets states too, or a slow discovery (CI: 91 shared of 150) counts
        # as a difference between the two.
        wait_until(lambda: len(seen) >= 5, 30, 'the probe receiving states')
        client.follow([STATE, PREDICTION, '/pma/control_state', '/diagnostics'])
        client.wait(lambda c: len(c.received(PREDICTION)) >= 100, 60, '100 predictions')
        wait_until(lambda: len(client.received(STATE)) >= 150, 30, '150 states')
        decode_state = Decoder(client.channel_for(STATE))
        states = [decode_state(m)[0] for m in client.received(STATE)]
        seqs = [s.seq for s in states]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
        assert seqs[-1] - seqs[0] + 1 == len(seqs), 'the bridge lost states on the way'
        with lock:
            both = [s for s in states if s.seq in seen]
            assert len(both) >= 100
            for state in both:          # the same bytes: the same values, NaN included
                twin = seen[state.seq]
                assert state.header.stamp == twin.header.stamp
                for key in ('gauge_pressure_pa', 'length_m', 'gauge_setpoint_pa'):
                    a, b = getattr(state, key), getattr(twin, key)
                    assert a == b or (math.isnan(a) and math.isnan(b)), key
        decode_prediction = Decoder(client.channel_for(PREDICTION))
        def stamp(msg) -> tuple[int, int]:
            return msg.header.stamp.sec, msg.header.stamp.nanosec

        stamps = {stamp(s) for s in states}
        predictions = [decode_prediction(m)[0] for m in client.received(PREDICTION)]
        # Those made while the viewer also had the states (its two subscriptions start apart).
        during = [p for p in predictions if stamp(states[0]) <= stamp(p) <= stamp(states[-1])]
        assert len(during) >= 50
        matched = [p for p in during if stamp(p) in stamps]
        assert len(matched) >= 0.9 * len(during), 'predictions answer the states seen'
        assert all(0.2 < p.predicted_length_m < 0.35 for p in predictions)
    finally:
        client.close()
        probe.close()
        shutdown()


def load_layout_checks():
    """pma_bringup/test/test_layout.py's path resolution, to apply to what the bridge says."""
    path = ROOT / 'pma_bringup' / 'test' / 'test_layout.py'
    spec = importlib.util.spec_from_file_location('pma_layout_checks', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_layout_names_what_the_running_rig_advertises(rig):
    """Every topic of the layout is advertised, and each path resolves in the advertised schema;
    a viewer subscribing late to latched pma/model_params still gets it."""
    _bridge, url = rig
    checks = load_layout_checks()
    layout = json.loads(LAYOUT.read_text())
    topics = {path.partition('.')[0] for _, path, _ in checks.layout_paths(layout)}
    client = FoxgloveClient(url)
    try:
        advertised = {topic: client.channel_for(topic, 30) for topic in sorted(topics)}
        schemas = {topic: (c['schemaName'], c['schema']) for topic, c in advertised.items()}
        assert checks.check_paths(layout, schemas) == topics
        expected = checks.published_topics()
        assert {t: c['schemaName'] for t, c in advertised.items()} == {
            t: expected[t] for t in topics}

        client.follow(['/pma/model_params'])
        params = client.wait(lambda c: c.received('/pma/model_params'), 10,
                             'the latched pma/model_params')
        decoded, _ = Decoder(client.channel_for('/pma/model_params'))(params[0])
        assert decoded.form and decoded.memory
    finally:
        client.close()


def test_a_second_bridge_on_a_taken_port_says_so(rig, procs):
    _bridge, url = rig
    port = url.rsplit(':', 1)[1]
    second = procs.ros2_run('pma_bringup', 'foxglove_live', name='second',
                            ros_args=['-r', '__node:=foxglove_live_2', '-p', f'port:={port}'])
    assert second.popen.wait(30) == 1
    assert 'Address already in use' in second.output and 'port:=' in second.output


def test_a_port_that_is_not_a_number_is_refused_in_one_line(procs):
    bridge = procs.ros2_run('pma_bringup', 'foxglove_live', name='bad_port',
                            ros_args=['-r', '__node:=foxglove_live_3', '-p', 'port:=abc'])
    assert bridge.popen.wait(30) == 2
    assert "bad parameter, not started: port must be of type INTEGER, got 'abc' (STRING)" \
        in bridge.output and 'Traceback' not in bridge.output


# The demo test's own deadlines: its URL, 20 states and predictions through the viewer, its
# stop. With two test workers and the in-process tests beside it, the demo's six children take
# a minute or more to start (106 and 140 s for the whole test in one local run); pytest-timeout
# must come after these, so a slow run fails where it was, not wherever 180 s fell (CI: inside
# a decode after every wait had been met).
DEMO_URL_S, DEMO_STREAM_S, DEMO_STOP_S = 60, 90, 60


@pytest.mark.timeout(DEMO_URL_S + DEMO_STREAM_S + DEMO_STOP_S + 60)
@pytest.mark.parametrize('stop_signal', [signal.SIGINT, signal.SIGHUP],
                         ids=['ctrl-c', 'terminal-closed'])
def test_the_demo_prints_a_working_url_and_the_layout(procs, tmp_path, stop_signal):
    """`make demo` runs this executable: while it runs, its URL serves the rig's topics.

    The demo runs its own rig, so it gets a domain of its own: in this module's domain the
    `rig` fixture's driver would answer the demo's Sweep goals too (seen: a major loop failed
    with the other driver's empty result), and its states would reach the demo's viewer.
    Stopped by a Ctrl-C or a closed terminal (SIGHUP, which used to end the demo at once and
    leave its six children running), it stops every child first.
    """
    demo = procs.ros2_run('pma_bringup', 'demo', '--runs-dir', str(tmp_path), '--live-port',
                          '0', '--hold-s', '0.3', name='demo',
                          env={'ROS_DOMAIN_ID': str(another_domain())})
    client, started = None, time.monotonic()
    try:
        url = URL.search(demo.wait_for_line('live view: ws://', DEMO_URL_S)).group(0)
        print(f'demo: its URL after {time.monotonic() - started:.1f} s')
        layout = demo.wait_for_line('its layout: ', 5).split('its layout: ')[1].split('  (')[0]
        assert json.loads(open(layout).read()) == json.loads(LAYOUT.read_text())
        client = FoxgloveClient(url)
        client.follow([STATE, PREDICTION])
        client.wait(lambda c: min(len(c.received(t)) for t in (STATE, PREDICTION)) >= 20,
                    DEMO_STREAM_S, '20 states and 20 predictions')
        print(f'demo: 20 states and predictions after {time.monotonic() - started:.1f} s')
        decode = Decoder(client.channel_for(STATE))   # one: each compiles its decoder
        states = [decode(m)[0] for m in client.received(STATE)]
        assert all(0.2 < s.length_m < 0.35 for s in states)
    finally:
        if client is not None:
            client.close()
        # The demo's children run in their own sessions: only the demo itself stops them, so
        # it gets the signal and the time to do so (the fixture's escalation is shorter).
        children = children_of(demo.popen.pid)
        demo.signal(stop_signal)
        stopping = time.monotonic()
        code = demo.popen.wait(DEMO_STOP_S)
        print(f'demo: stopped {time.monotonic() - stopping:.1f} s after the signal')
        left_running = [pid for pid in children if running(pid)]
        for pid in left_running:             # not to burden the tests that follow
            os.kill(pid, signal.SIGKILL)
    assert code == 130, demo.output[-2000:]
    assert 'interrupted: stopping every process' in demo.output
    assert len(children) >= 6, children       # the rig, the model, recorder, controller, view
    assert not left_running, demo.output[-2000:]
