"""model_node as a real process: the stream, the inverse service, parameters, params file."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest

from pma_model.params import default_params
from support.ros import SpinningNode, shutdown, wait_until

HELPERS = Path(__file__).parent / 'helpers'
pytestmark = pytest.mark.integration


@pytest.fixture(scope='module')
def probe():
    node = SpinningNode('model_probe')
    yield node
    node.close()
    shutdown()


def _call(probe, client, request, timeout=10.0):
    future = client.call_async(request)
    wait_until(future.done, timeout, 'service response')
    return future.result()


def _collect(probe, msg_type, topic, qos=10):
    received = []
    lock = threading.Lock()

    def on_msg(msg):
        with lock:
            received.append(msg)

    sub = probe.node.create_subscription(msg_type, topic, on_msg, qos)
    return received, sub


def test_service_refuses_bad_requests_then_answers(procs, probe):
    from pma_interfaces.srv import PressureForLength

    procs.ros2_run('pma_model', 'model_node').wait_for_line('model_node ready')
    client = probe.node.create_client(PressureForLength, 'pressure_for_length')
    try:
        assert client.wait_for_service(timeout_sec=20)
        req = PressureForLength.Request
        auto = _call(probe, client, req(length_m=0.27, branch=req.BRANCH_AUTO))
        assert not auto.success and 'no pma/state sample' in auto.message
        bad_requests = [
            (req(length_m=math.nan, branch=1), 'finite'),
            (req(length_m=math.inf, branch=1), 'finite'),
            (req(length_m=-math.inf, branch=2), 'finite'),
            (req(length_m=0.0, branch=1), 'positive'),
            (req(length_m=-0.1, branch=2), 'positive'),
            (req(length_m=0.27, branch=7), 'unknown branch'),
            (req(length_m=0.20, branch=1), 'not reachable'),
            (req(length_m=0.31, branch=2), 'not reachable'),
        ]
        for request, words in bad_requests:
            response = _call(probe, client, request)
            assert not response.success, request
            assert words in response.message, (request, response.message)
        out_of_range = _call(probe, client, req(length_m=0.20, branch=1))
        assert 0.24 < out_of_range.min_length_m < out_of_range.max_length_m <= 0.3006
        assert f'{out_of_range.min_length_m:.6g}' in out_of_range.message

        # Still serving, and right: the default increasing branch is the paper's fit.
        increasing = default_params().increasing.sigmoid
        for pressure_pa in (100e3, 250e3, 400e3):
            target = float(increasing.length(pressure_pa))
            answer = _call(probe, client, req(length_m=target, branch=req.BRANCH_INCREASING))
            assert answer.success, answer.message
            assert answer.branch == req.BRANCH_INCREASING
            assert math.isclose(answer.gauge_pressure_pa, pressure_pa, abs_tol=1.0)
        # An explicit branch is that major branch, whatever the state (here: at rest).
        decreasing = default_params().decreasing.sigmoid
        target = float(decreasing.length(200e3))
        answer = _call(probe, client, req(length_m=target, branch=req.BRANCH_DECREASING))
        assert answer.success and answer.branch == req.BRANCH_DECREASING, answer.message
        assert math.isclose(answer.gauge_pressure_pa, 200e3, abs_tol=1.0)
        assert 'decreasing major branch' in answer.message
    finally:
        probe.node.destroy_client(client)


def test_every_state_gets_a_prediction_with_its_header(procs, probe):
    from pma_interfaces.msg import PmaPrediction, PmaState
    from pma_interfaces.srv import PressureForLength

    procs.ros2_run('pma_model', 'model_node').wait_for_line('model_node ready')
    predictions, sub_p = _collect(probe, PmaPrediction, 'pma/prediction')
    states, sub_s = _collect(probe, PmaState, 'pma/state')
    try:
        wait_until(lambda: probe.node.count_publishers('pma/prediction') >= 1, 20,
                   'model_node publisher')
        procs.python(HELPERS / 'rig_stand_in.py', '--rate', '100',
                     '--nan-every', '25').wait_for_line('ready')
        def stamps(messages):
            return {(m.header.stamp.sec, m.header.stamp.nanosec) for m in list(messages)}

        # Both subscriptions match the stand-in at their own pace: wait for an overlap.
        wait_until(lambda: len(stamps(predictions) & stamps(states)) >= 200, 30,
                   '200 samples seen both as state and as prediction')
        by_stamp = {(s.header.stamp.sec, s.header.stamp.nanosec): s for s in list(states)}
        matched = broken = 0
        for prediction in list(predictions):
            key = (prediction.header.stamp.sec, prediction.header.stamp.nanosec)
            if key in by_stamp:
                state = by_stamp[key]
                matched += 1
                if math.isnan(state.gauge_pressure_pa):
                    # a broken reading still gets its prediction: NaN, nothing made up
                    broken += 1
                    assert math.isnan(prediction.gauge_pressure_pa)
                    assert math.isnan(prediction.predicted_length_m)
                    assert math.isnan(prediction.residual_m)
                    continue
                assert prediction.gauge_pressure_pa == state.gauge_pressure_pa
                assert prediction.measured_length_m == state.length_m
                assert math.isclose(prediction.residual_m,
                                    state.length_m - prediction.predicted_length_m,
                                    abs_tol=1e-12)
                assert prediction.header.frame_id == state.header.frame_id
        assert matched >= 150 and broken >= 5
        # The stand-in publisher holds ~250 kPa: the prediction is the model's length there.
        last = predictions[-1]
        assert 0.24 < last.predicted_length_m < 0.28
        assert last.branch in (PmaPrediction.BRANCH_INCREASING, PmaPrediction.BRANCH_DECREASING)

        client = probe.node.create_client(PressureForLength, 'pressure_for_length')
        assert client.wait_for_service(timeout_sec=20)
        req = PressureForLength.Request
        longer = _call(probe, client, req(length_m=0.28, branch=req.BRANCH_AUTO))
        assert longer.success and longer.branch == req.BRANCH_DECREASING, longer.message
        assert longer.gauge_pressure_pa < 250e3
        shorter = _call(probe, client, req(length_m=0.25, branch=req.BRANCH_AUTO))
        assert shorter.success and shorter.branch == req.BRANCH_INCREASING, shorter.message
        assert shorter.gauge_pressure_pa > 250e3
        probe.node.destroy_client(client)
    finally:
        probe.node.destroy_subscription(sub_p)
        probe.node.destroy_subscription(sub_s)


def test_parameters_are_validated_as_a_whole_and_published(procs, probe, tmp_path):
    from rcl_interfaces.srv import SetParametersAtomically
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile

    from pma_interfaces.msg import ModelParams

    params_file = tmp_path / 'refit.yaml'
    procs.ros2_run('pma_model', 'model_node',
                   ros_args=['-p', f'params_file:={params_file}']).wait_for_line(
        'model_node ready')
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    published, sub = _collect(probe, ModelParams, 'pma/model_params', latched)
    client = probe.node.create_client(SetParametersAtomically,
                                      'model_node/set_parameters_atomically')
    try:
        wait_until(lambda: published, 20, 'latched model parameters')
        assert published[-1].form == 'sigmoid' and published[-1].memory == 'identify'
        assert client.wait_for_service(timeout_sec=20)

        def set_atomically(**values):
            request = SetParametersAtomically.Request(parameters=[
                Parameter(name, value=value).to_parameter_msg()
                for name, value in values.items()])
            return _call(probe, client, request).result

        bad = set_atomically(**{'memory': 'switch', 'increasing.sigmoid.a': -1.0})
        assert not bad.successful and 'increasing.sigmoid' in bad.reason
        units_slip = set_atomically(max_gauge_pressure_pa=500.0)
        assert not units_slip.successful
        assert len(published) == 1, 'a rejected change must not republish the model'
        # Node-level parameters are not the model's business: accepted, model untouched.
        assert set_atomically(use_sim_time=False).successful
        assert len(published) == 1

        good = set_atomically(memory='switch', branch_form='hill')
        assert good.successful, good.reason
        wait_until(lambda: len(published) >= 2, 10, 'republished model parameters')
        assert (published[-1].form, published[-1].memory) == ('hill', 'switch')

        # Hot reload: a refit writes the params file; the node picks it up.
        default_params().with_branches(
            default_params().increasing.sigmoid, default_params().decreasing.sigmoid,
        ).save_yaml(params_file)
        wait_until(lambda: published[-1].form == 'sigmoid', 10, 'params file reload')
        assert 'increasing' in published[-1].parameters_yaml
        params_file.write_text('not: [valid')
        procs.procs[-1].wait_for_line('params file not loaded', timeout=10)
        assert procs.procs[-1].alive()
    finally:
        probe.node.destroy_client(client)
        probe.node.destroy_subscription(sub)
