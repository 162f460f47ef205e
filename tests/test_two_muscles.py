"""Two muscles side by side: /left and /right rigs, each its own fake_arduino, driver_node and
model_node, started as real processes the way pma_bringup.launch.py starts them (namespace
remap plus port). A setpoint for the left muscle must move the left rig only, and each model
must follow, and answer for, its own muscle: nothing crosses between namespaces.
"""

from __future__ import annotations

import threading

import pytest
from std_msgs.msg import Float64

from pma_interfaces.msg import PmaPrediction, PmaState
from pma_interfaces.srv import PressureForLength
from support.ros import SpinningNode, publish_until, shutdown, wait_until

pytestmark = pytest.mark.integration

SIDES = ('left', 'right')
SETPOINT_PA = 300_000.0
AT_REST_PA = 20_000.0          # the sensor's noise and offset stay well below this


@pytest.fixture(scope='module')
def probe():
    node = SpinningNode('two_muscles_probe')
    yield node
    node.close()
    shutdown()


@pytest.fixture
def rigs(procs, tmp_path):
    """Start both rigs; return when both drivers are active and both models ready."""
    drivers, models = [], []
    for seed, side in enumerate(SIDES, start=1):
        link = tmp_path / f'pma_{side}'
        procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(link), '--seed', str(seed),
                       name=f'fake_arduino_{side}').wait_for_line('device at')
        drivers.append(procs.ros2_run('pma_driver', 'driver_node', name=f'driver_{side}',
                                      ros_args=['-r', f'__ns:=/{side}', '-p', f'port:={link}']))
        models.append(procs.ros2_run('pma_model', 'model_node', name=f'model_{side}',
                                     ros_args=['-r', f'__ns:=/{side}']))
    for proc in drivers:
        proc.wait_for_line('active: publishing', timeout=30)
    for proc in models:
        proc.wait_for_line('model_node ready', timeout=30)


class Streams:
    """PmaState and PmaPrediction of both namespaces, as the probe receives them."""

    def __init__(self, node):
        self.lock = threading.Lock()
        self.states = {side: [] for side in SIDES}
        self.predictions = {side: [] for side in SIDES}
        self.subs = []
        for side in SIDES:
            self.subs.append(node.create_subscription(
                PmaState, f'/{side}/pma/state', self._keep(self.states[side]), 100))
            self.subs.append(node.create_subscription(
                PmaPrediction, f'/{side}/pma/prediction', self._keep(self.predictions[side]),
                100))

    def _keep(self, into: list):
        def keep(msg) -> None:
            with self.lock:
                into.append(msg)
        return keep

    def snapshot(self, kind: str, side: str) -> list:
        with self.lock:
            return list(getattr(self, kind)[side])


def test_setpoint_on_left_moves_left_only_and_each_model_follows_its_own(rigs, probe):
    node = probe.node
    streams = Streams(node)
    for side in SIDES:
        wait_until(lambda side=side: len(streams.snapshot('states', side)) >= 10, 20,
                   f'/{side}/pma/state')
        wait_until(lambda side=side: len(streams.snapshot('predictions', side)) >= 10, 20,
                   f'/{side}/pma/prediction')
    for side in SIDES:
        assert all(abs(s.gauge_pressure_pa) < AT_REST_PA
                   for s in streams.snapshot('states', side)), f'{side} not at rest at start'

    setpoint = node.create_publisher(Float64, '/left/pma/pressure_setpoint', 10)
    wait_until(lambda: setpoint.get_subscription_count() > 0, 10,
               'left driver subscribed to its setpoint')
    start = {side: len(streams.snapshot('states', side)) for side in SIDES}
    publish_until(setpoint, Float64(data=SETPOINT_PA),
                  lambda: streams.snapshot('states', 'left')[-1].gauge_setpoint_pa
                  == SETPOINT_PA, 10, 'left device asked for the setpoint')
    wait_until(lambda: streams.snapshot('states', 'left')[-1].gauge_pressure_pa
               > SETPOINT_PA - 50_000.0, 30, 'left muscle inflated')
    wait_until(lambda: streams.snapshot('predictions', 'left')[-1].gauge_pressure_pa
               > SETPOINT_PA - 50_000.0, 10, 'left model following the left muscle')
    # The inflation takes well under a second; watch the right rig for 2 s more.
    wait_until(lambda: len(streams.snapshot('states', 'right')) >= start['right'] + 40, 10,
               'right rig streaming on')
    left = streams.snapshot('states', 'left')[start['left']:]
    right = streams.snapshot('states', 'right')[start['right']:]
    assert left[-1].gauge_setpoint_pa == SETPOINT_PA
    assert left[-1].length_m < left[0].length_m - 0.02, 'the left muscle contracted'
    assert all(s.gauge_setpoint_pa == 0.0 for s in right), 'setpoint crossed to the right rig'
    assert max(s.gauge_pressure_pa for s in right) < AT_REST_PA, 'right rig pressure rose'
    right_predictions = streams.snapshot('predictions', 'right')
    assert max(p.gauge_pressure_pa for p in right_predictions) < AT_REST_PA, (
        'the right model saw the left muscle')
    # Each prediction is made for a sample of its own rig (header copied from that PmaState).
    left_stamps = {(s.header.stamp.sec, s.header.stamp.nanosec)
                   for s in streams.snapshot('states', 'left')}
    assert (streams.snapshot('predictions', 'left')[-1].header.stamp.sec,
            streams.snapshot('predictions', 'left')[-1].header.stamp.nanosec) in left_stamps

    # Both services answer, each from its own muscle's state: at 300 kPa the left muscle is
    # shorter than 28 cm, so reaching 28 cm means deflating; the right one at rest must inflate.
    request = PressureForLength.Request
    answers = {side: probe.call(PressureForLength, f'/{side}/pressure_for_length',
                                request(length_m=0.28, branch=request.BRANCH_AUTO),
                                idempotent=True) for side in SIDES}
    for side, answer in answers.items():
        assert answer.success, (side, answer.message)
        assert 0.0 < answer.gauge_pressure_pa < SETPOINT_PA
    assert answers['left'].branch == request.BRANCH_DECREASING
    assert answers['right'].branch == request.BRANCH_INCREASING

    # No un-namespaced copy of anything: the graph has only /left/... and /right/...
    services = {name for name, _ in node.get_service_names_and_types()}
    assert '/pressure_for_length' not in services
    assert node.get_publishers_info_by_topic('/pma/state') == []
    # Subscriptions go with the probe node (destroying them under the spinning executor races).
