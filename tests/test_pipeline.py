"""The whole pipeline on the simulated rig, every piece a real process over real DDS.

fake_arduino -> driver_node -> model_node, the paper's sweep through the Sweep action with
its own bag; then the bag in three readers, replayed into a second model_node, refitted,
and the refit loaded back. What the issues' "done when" lines ask, in one module so the
sweep (the slow part) runs once.
"""

from __future__ import annotations

import csv
import itertools
import json
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader

from pma_bag import BagReader
from pma_common import names
from pma_interfaces.action import Sweep
from pma_interfaces.msg import ModelParams, PmaPrediction, PmaState
from support.procs import INSTALL
from support.ros import SpinningNode, shutdown, wait_for_action_server, wait_until

pytestmark = pytest.mark.integration

TABLE1 = Path(__file__).resolve().parents[1] / 'pma_model' / 'pma_model' / 'data' / \
    'paper_table1.csv'
SENSOR_ACCURACY_M = 0.003       # HC-SR04, about +/-3 mm (the figure)
RATE_HZ = 50
STATE = 'pma_interfaces/msg/PmaState'


@dataclass
class Hold:
    """One step of the staircase, reduced to its settled second half."""

    setpoint_pa: float
    increasing: bool
    pressure_pa: float
    measured_m: float
    predicted_m: float


class Stream:
    """PmaState and PmaPrediction as another process sees them."""

    def __init__(self, node, namespace: str = ''):
        self.lock = threading.Lock()
        self.states: list[PmaState] = []
        self.predictions: list[PmaPrediction] = []
        self.params: list[ModelParams] = []
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._subs = [
            node.create_subscription(PmaState, f'{namespace}/pma/state',
                                     self._keep(self.states), 1000),
            node.create_subscription(PmaPrediction, f'{namespace}/pma/prediction',
                                     self._keep(self.predictions), 1000),
            node.create_subscription(ModelParams, f'{namespace}/pma/model_params',
                                     self._keep(self.params), latched),
        ]

    def _keep(self, into: list):
        def keep(msg) -> None:
            with self.lock:
                into.append(msg)
        return keep

    def count(self, what: str) -> int:
        with self.lock:
            return len(getattr(self, what))


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


@pytest.fixture(scope='module')
def probe():
    node = SpinningNode('pipeline_probe')
    yield node
    node.close()
    shutdown()


@pytest.fixture(scope='module')
def swept(module_procs, probe, tmp_path_factory):
    """Rig + driver + model; one full 0 -> 500 -> 0 kPa sweep recorded by the action."""
    work = tmp_path_factory.mktemp('pipeline')
    port = work / 'ttyPMA'
    fake = module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', port, '--seed', '3')
    fake.wait_for_line('fake_arduino: device at', 20)
    # Online identification off, here and in the replay: a learning model's predictions
    # depend on every sample it has seen, so a replay that joins after the live model
    # started could not reproduce them bit for bit (docs/model.md, "Online identification").
    model = module_procs.ros2_run('pma_model', 'model_node',
                                  ros_args=['-p', 'identification.enabled:=false'])
    model.wait_for_line('model_node ready', 30)
    # The Sweep records here: zstd chunks, a new file every 8 s, as a long experiment would.
    recorder = module_procs.ros2_run('pma_bag', 'record', '--idle', '--compression', 'zstd',
                                     '--max-bag-duration', '8')
    recorder.wait_for_line('recorder: idle', 30)
    live = Stream(probe.node)
    driver = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=[
        '-p', f'port:={port}', '-p', f'sample_rate_hz:={float(RATE_HZ)}'])
    driver.wait_for_line('active: publishing', 30)
    wait_until(lambda: live.count('predictions') >= 10, 30, 'live predictions')

    client = ActionClient(probe.node, Sweep, names.SWEEP)
    wait_for_action_server(client)
    bag = work / 'sweep_bag'
    goal = Sweep.Goal(max_gauge_pressure_pa=500e3, step_pa=50e3, hold_s=1.0, cycles=1,
                      record=True, bag_path=str(bag), note='pipeline test, muscle m1')
    with live.lock:
        first_state = len(live.states)
    handle = probe.send_goal(client, goal, timeout=20)
    assert handle.accepted
    result_future = probe.in_executor(handle.get_result_async)
    wait_until(result_future.done, 240, 'sweep result')
    result = result_future.result().result
    client.destroy()
    assert result.success, result.message
    assert result.bag_path == str(bag)
    with live.lock:
        last_state = stamp_ns(live.states[-1])

    def predicted_up_to_the_last_state() -> bool:
        with live.lock:
            return any(stamp_ns(p) >= last_state for p in live.predictions[-50:])

    # Every sample must get its prediction, not at once: at a recorded sweep's end they
    # trailed the states by up to 0.9 s (the bag closing; latency is bench_model_node's).
    wait_until(predicted_up_to_the_last_state, 10, 'the prediction of the last state')
    with live.lock:
        states = [s for s in live.states[first_state:] if stamp_ns(s) <= last_state]
        predictions = list(live.predictions)
    return {'work': work, 'bag': bag, 'states': states, 'predictions': predictions,
            'live': live, 'driver': driver, 'result': result}


def holds(states: list[PmaState], predictions: list[PmaPrediction]) -> list[Hold]:
    """Each staircase step: consecutive samples with one device setpoint, settled half."""
    predicted = {stamp_ns(p): p.predicted_length_m for p in predictions}
    steps = []
    for setpoint, group in itertools.groupby(states, key=lambda s: s.gauge_setpoint_pa):
        samples = list(group)
        steps.append((setpoint, samples[len(samples) // 2:]))
    peak = max(range(len(steps)), key=lambda i: steps[i][0])
    out = []
    for index, (setpoint, settled) in enumerate(steps):
        pairs = [(s, predicted[stamp_ns(s)]) for s in settled if stamp_ns(s) in predicted]
        if len(pairs) < 5:
            continue
        out.append(Hold(setpoint, index <= peak,
                        float(np.mean([s.gauge_pressure_pa for s, _ in pairs])),
                        float(np.mean([s.length_m for s, _ in pairs])),
                        float(np.mean([p for _, p in pairs]))))
    return out


def table1() -> dict[tuple[float, bool], float]:
    with open(TABLE1, newline='', encoding='utf-8') as stream:
        rows = list(csv.DictReader(stream))
    table = {}
    for row in rows:
        pressure_pa = float(row['pressure_kpa']) * 1e3
        table[pressure_pa, True] = float(row['length_increasing_cm']) / 100
        table[pressure_pa, False] = float(row['length_decreasing_cm']) / 100
    return table


def test_sweep_through_the_driver_yields_the_loop_of_table_1(swept):
    steps = holds(swept['states'], swept['predictions'])
    table = table1()
    errors = {True: [], False: []}
    for step in steps:
        key = (step.setpoint_pa, step.increasing)
        if key in table:
            errors[step.increasing].append(step.measured_m - table[key])
    assert len(errors[True]) >= 10 and len(errors[False]) >= 9, steps
    every = np.array(errors[True] + errors[False])
    rmse, worst = float(np.sqrt(np.mean(every ** 2))), float(np.max(np.abs(every)))
    print(f'\nsweep via driver_node vs Table 1: RMSE {rmse * 100:.3f} cm, '
          f'max {worst * 100:.3f} cm over {every.size} holds')
    assert worst < SENSOR_ACCURACY_M, errors
    # Hysteresis, not noise: at 200 kPa the decreasing branch is 3.6 mm shorter in Table 1.
    mid = [s for s in steps if s.setpoint_pa == 200e3]
    up, down = (next(s.measured_m for s in mid if s.increasing is d) for d in (True, False))
    assert up - down > 0.002


def test_live_predictions_follow_the_measured_length_on_both_branches(swept):
    predictions = swept['predictions']
    branches = {p.branch for p in predictions}
    assert branches == {PmaPrediction.BRANCH_INCREASING, PmaPrediction.BRANCH_DECREASING}
    steps = holds(swept['states'], predictions)
    report = []
    for increasing in (True, False):
        errors = np.array([s.predicted_m - s.measured_m for s in steps
                           if s.increasing is increasing])
        rmse, worst = float(np.sqrt(np.mean(errors ** 2))), float(np.max(np.abs(errors)))
        report.append(f'{"increasing" if increasing else "decreasing"}: RMSE '
                      f'{rmse * 100:.3f} cm, max {worst * 100:.3f} cm ({errors.size} holds)')
        # The paper's sigmoid (the default) misses the 0-50 kPa dead zone by up to ~4 mm on
        # Table 1 itself; everywhere else it is within the sensor's accuracy.
        assert rmse < SENSOR_ACCURACY_M, report
        assert worst < 2 * SENSOR_ACCURACY_M, report
    print('\nlive predictions vs measured (hold means): ' + '; '.join(report))
    # Every sample got a prediction with its own header (stamps line up one to one).
    stamps = {stamp_ns(s) for s in swept['states']}
    predicted = {stamp_ns(p) for p in predictions}
    assert len(stamps - predicted) <= 2, 'predictions missing for live samples'


def test_the_sweep_bag_opens_in_four_readers(swept):
    """Split into several zstd-compressed files with the run's metadata, and read as one bag,
    every message once, by our reader, rosbags, mcap + mcap_ros2 and `pma_bag info`."""
    bag = swept['bag']
    metadata = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    files = [bag / name for name in metadata['relative_file_paths']]
    assert len(files) >= 2 and all(f.is_file() for f in files), files
    custom = metadata['custom_data']
    assert custom['note'] == 'pipeline test, muscle m1'
    assert custom['sweep.step_pa'] == '50000.0' and custom['device.firmware'] == 'fake_arduino'
    assert custom['lost_messages'] == '0'
    with BagReader(bag) as reader:
        ours = [deserialize_message(m.data, PmaState).seq
                for m in reader.messages(['/pma/state'])]
        topics = set(reader.topics)
        assert reader.compressions == {'zstd'}
    assert {'/pma/state', '/pma/pressure', '/pma/range', '/pma/prediction',
            '/pma/model_params', '/diagnostics'} <= topics
    assert len(ours) >= swept['result'].sample_count * 0.9
    assert ours == list(range(ours[0], ours[0] + len(ours))), 'every sample once, none missing'
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == '/pma/state']
        theirs = [reader.deserialize(raw, STATE).seq for _, _, raw in
                  reader.messages(connections)]
    assert theirs == ours
    mcaps = []
    for path in files:
        with open(path, 'rb') as stream:
            decoded = make_reader(stream, decoder_factories=[DecoderFactory()])
            mcaps += [m.seq for _, _, _, m in
                      decoded.iter_decoded_messages(topics=['/pma/state'])]
    assert mcaps == ours
    counts = {t['topic_metadata']['name']: t['message_count']
              for t in metadata['topics_with_message_count']}
    assert counts['/pma/state'] == len(ours)
    info = subprocess.run([str(INSTALL / 'pma_bag' / 'lib' / 'pma_bag' / 'info'), str(bag)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert info.returncode == 0, info.stderr
    assert 'pipeline test, muscle m1' in info.stdout and 'zstd' in info.stdout


@pytest.fixture(scope='module')
def replayed(swept, module_procs, probe):
    """The bag's pma/state replayed into a second model_node in the namespace /replayed."""
    model = module_procs.ros2_run('pma_model', 'model_node', name='replayed_model',
                                  ros_args=['-r', '__ns:=/replayed',
                                            '-p', 'identification.enabled:=false'])
    model.wait_for_line('model_node ready', 30)
    stream = Stream(probe.node, '/replayed')
    wait_until(lambda: stream.count('params') >= 1, 20, 'replayed model parameters')
    player = module_procs.ros2_run('pma_bag', 'play', swept['bag'], '--start-paused',
                                   '--topics', names.STATE,
                                   '--remap', '/pma/state:=/replayed/pma/state')
    player.wait_for_line('play: playing', 30)
    wait_until(lambda: probe.node.count_publishers('/replayed/pma/state') >= 1, 20,
               'the player on /replayed/pma/state')
    from std_srvs.srv import Trigger
    # The graph shows the player before its writer has matched model_node's best-effort
    # reader, and nothing outside the two processes can see that match: step the bag one
    # message at a time until a prediction comes back, then play on. Only those first
    # messages (the bag starts with a 0 kPa hold) can be lost; the test checks that.
    for _ in range(40):
        stepped = probe.call(Trigger, '/player/play_next', timeout=10)
        assert stepped.success, stepped.message
        try:
            wait_until(lambda: stream.count('predictions') > 0, 0.5, 'a first prediction')
            break
        except TimeoutError:
            continue
    probe.call(Trigger, '/player/resume', timeout=10)
    player.wait_for_line('play: done', timeout=180)
    assert player.popen.wait(10) == 0, player.output
    with BagReader(swept['bag']) as reader:
        expected = reader.topics['/pma/state'].message_count
    settled = [-1, time.monotonic()]

    def all_in_or_quiet() -> bool:
        # This process also follows the live streams, so it may be behind: wait for every
        # prediction, or for 3 s without a new one.
        count = stream.count('predictions')
        if count != settled[0]:
            settled[:] = [count, time.monotonic()]
        return count >= expected or time.monotonic() - settled[1] > 3.0

    wait_until(all_in_or_quiet, 60, 'the last predictions of the replay')
    return {'model': model, 'stream': stream}


def test_replay_into_model_node_reproduces_the_live_predictions(swept, replayed):
    with BagReader(swept['bag']) as reader:
        recorded = {stamp_ns(p): p for p in (deserialize_message(m.data, PmaPrediction)
                                             for m in reader.messages(['/pma/prediction']))}
        replayed_states = [deserialize_message(m.data, PmaState)
                           for m in reader.messages(['/pma/state'])]
        state_count = len(replayed_states)
    stream = replayed['stream']
    with stream.lock:
        again = list(stream.predictions)
    # The recorder subscribes each topic as discovery finds its publisher, as `ros2 bag
    # record` does, and the sweep starts stepping only once all are subscribed: so the bag
    # may begin with states whose predictions were not yet matched, but only in that lead-in
    # at 0 kPa, and the last state's prediction may land after the recorder stopped.
    lead_in = next(i for i, state in enumerate(replayed_states) if state.gauge_setpoint_pa > 0)
    unrecorded = [i for i, state in enumerate(replayed_states)
                  if stamp_ns(state) not in recorded]
    assert all(i < lead_in or i >= state_count - 3 for i in unrecorded), unrecorded
    assert all(replayed_states[i].gauge_pressure_pa < 20e3 for i in unrecorded), unrecorded
    assert state_count - lead_in >= 20 * RATE_HZ, (lead_in, state_count)
    matched = [(recorded[stamp_ns(p)], p) for p in again if stamp_ns(p) in recorded]
    got = {stamp_ns(p) for p in again}
    missing = [i for i, state in enumerate(replayed_states) if stamp_ns(state) not in got]
    # Only the first samples may be missing (the player's writer matching model_node's
    # best-effort reader), and only while the muscle was still at rest.
    assert missing == list(range(len(missing))), f'lost later: {missing[-20:]}'
    assert all(replayed_states[i].gauge_pressure_pa < 20e3 for i in missing)
    swept_matched = sum(1 for a, _ in matched
                        if stamp_ns(a) >= stamp_ns(replayed_states[lead_in]))
    assert swept_matched >= state_count - lead_in - 3, (swept_matched, state_count, lead_in)
    differences = np.array([abs(a.predicted_length_m - b.predicted_length_m)
                            for a, b in matched])
    branches_agree = np.mean([a.branch == b.branch for a, b in matched])
    identical = float(np.mean(differences == 0.0))
    print(f'\nreplayed vs live predictions: {len(matched)} of {state_count} samples matched, '
          f'{100 * identical:.1f} % identical, max |difference| {differences.max():.3g} m, '
          f'branches agree {100 * branches_agree:.2f} %')
    # Same inputs in the same order, same model: the same numbers, except while the live
    # model's memory still holds the noise loops it saw at rest before the bag started
    # (micrometres, wiped out by the first pressure step).
    assert differences.max() < 5e-5
    assert identical >= 0.95
    assert branches_agree >= 0.99
    assert all(a.gauge_pressure_pa == b.gauge_pressure_pa for a, b in matched)


def test_refit_of_the_bag_writes_params_that_model_node_loads(swept, replayed, module_procs,
                                                             probe):
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    work, bag = swept['work'], swept['bag']
    out = work / 'refit'
    refit = module_procs.ros2_run('pma_model', 'refit', bag, '--json', out / 'report.json',
                                  '--params-out', out / 'params.yaml', '--plots', out / 'plots')
    assert refit.popen.wait(120) == 0, refit.output
    report = json.loads((out / 'report.json').read_text())
    for branch in ('increasing', 'decreasing'):
        models = report['branches'][branch]['models']
        assert {'sigmoid_fixed_c', 'sigmoid_free_c', 'hill', 'bouc_wen',
                'bouc_wen_nonlinear'} <= set(models)
        for name, entry in models.items():
            assert {'mae_cm', 'mse_cm2', 'rmse_cm', 'max_cm', 'r2', 'r', 'aic', 'aicc', 'bic',
                    'n', 'k'} <= set(entry['metrics']), name
        hill = models['hill']['metrics']
        # The simulated rig follows Table 1; the Hill branch fits it within the sensor noise.
        assert hill['rmse_cm'] < 0.3 and hill['r2'] > 0.99, hill
    assert sorted(p.name for p in (out / 'plots').glob('*.png')) == \
        ['comparison.png', 'loop.png', 'residuals.png', 'timeseries.png']

    written = yaml.safe_load((out / 'params.yaml').read_text())['/**']['ros__parameters']
    stream = replayed['stream']
    before = stream.count('params')
    answer = probe.call(SetParameters, '/replayed/model_node/set_parameters',
                        SetParameters.Request(parameters=[Parameter(
                            'params_file', value=str(out / 'params.yaml')).to_parameter_msg()]))
    assert all(r.successful for r in answer.results), answer
    wait_until(lambda: stream.count('params') > before, 15, 'model_node reloading the refit')
    replayed['model'].wait_for_line('loaded model parameters from', 10)
    with stream.lock:
        active = stream.params[-1]
    form = written['branch_form']
    assert active.form == form
    loaded = yaml.safe_load(active.parameters_yaml)['/**']['ros__parameters']
    for key in ('increasing', 'decreasing'):
        for field, value in written[key][form].items():
            assert loaded[key][form][field] == pytest.approx(value, rel=1e-9), (key, field)
