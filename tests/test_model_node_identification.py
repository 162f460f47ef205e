"""model_node learns which muscle it has, says so, and a restart resumes from what it said.

A real model_node process over DDS; the probe plays the driver, publishing PmaState from the
simulated `wide` muscle family along a path with reversals (pma_sim.paths), with the
rig's sensor noise and the sample's simulated time in the header.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml

from pma_common import names
from pma_model.identification import CORRECTION_KNOTS_PA
from pma_sim import paths
from pma_sim.registry import muscle_family
from support.ros import SpinningNode, shutdown, wait_until

pytestmark = pytest.mark.integration


@pytest.fixture(scope='module')
def probe():
    node = SpinningNode('identification_probe')
    yield node
    node.close()
    shutdown()


def publish_run(probe, rate_hz=400.0, duration_s=60.0):
    """The wide muscle along random reversals, published 8x faster than it happened."""
    from pma_interfaces.msg import PmaState

    path = paths.ramp_path(paths.random_turns(duration_s, seed=4), seed=4)
    run = paths.simulate(muscle_family('wide'), path, seed=4)
    publisher = probe.node.create_publisher(PmaState, names.STATE, 50)
    wait_until(lambda: publisher.get_subscription_count() >= 1, 20, 'model_node subscribed')
    start = time.monotonic()
    for seq, (t, p, length) in enumerate(zip(run.time_s, run.measured_pressure_pa,
                                             run.measured_length_m, strict=True)):
        msg = PmaState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), round((t % 1.0) * 1e9)
        msg.header.frame_id = 'pma_link'
        msg.seq = seq
        msg.gauge_pressure_pa, msg.length_m = float(p), float(length)
        publisher.publish(msg)
        delay = start + seq / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    return run


def test_it_learns_publishes_and_a_restart_resumes(procs, probe, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from pma_interfaces.msg import ModelParams

    latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE)
    procs.ros2_run('pma_model', 'model_node').wait_for_line('model_node ready', 30)
    published, sub_params = probe.collect(ModelParams, names.MODEL_PARAMS, latched)
    diagnostics, sub_diag = probe.collect(DiagnosticArray, '/diagnostics')
    try:
        wait_until(lambda: published, 20, 'the latched parameters')
        first = published[0]
        assert first.memory == 'mix' and first.identification_enabled
        assert list(first.mix_rules) == ['identify', 'play']
        assert list(first.mix_weights) == [0.5, 0.5]
        assert (first.play_share_rising, first.play_share_falling) == (0.5, 0.5)
        assert (first.play_share_slope_rising, first.play_share_slope_falling) == (0.0, 0.0)
        assert list(first.branch_correction_m) == [0.0] * len(CORRECTION_KNOTS_PA)
        assert list(first.branch_difference_m) == [0.0] * len(CORRECTION_KNOTS_PA)
        run = publish_run(probe)
        count = run.time_s.size
        wait_until(lambda: published[-1].samples_learned >= 0.95 * count, 20,
                   'model_params with what it learned')
        learned = published[-1]
        print(f'\nlearned from {learned.samples_learned} of {count} samples: play shares '
              f'{learned.play_share_rising:.2f} / {learned.play_share_falling:.2f} (slopes '
              f'{learned.play_share_slope_rising:+.2f} / '
              f'{learned.play_share_slope_falling:+.2f}), '
              f'correction mm {np.round(np.array(learned.branch_correction_m) * 1e3, 2)}, '
              f'difference mm {np.round(np.array(learned.branch_difference_m) * 1e3, 2)}')
        assert list(learned.branch_correction_pressures_pa) == list(CORRECTION_KNOTS_PA)
        assert np.max(np.abs(learned.branch_correction_m)) > 5e-4   # the sigmoid is wrong
        assert len(learned.branch_difference_m) == len(CORRECTION_KNOTS_PA)
        assert (learned.play_share_rising, learned.play_share_falling) != (0.5, 0.5)
        assert (learned.play_share_slope_rising, learned.play_share_slope_falling) != (0.0, 0.0)
        assert len(learned.creep_gains) == len(learned.creep_time_constants_s) == 2
        print(f'mix weights {list(learned.mix_weights)}, play rule correction mm '
              f'{np.round(np.array(learned.play_rule_correction_m) * 1e3, 2)}')
        assert list(learned.mix_weights) != [0.5, 0.5]
        assert sum(learned.mix_weights) == pytest.approx(1.0)
        assert np.max(np.abs(learned.play_rule_correction_m)) > 5e-4
        assert len(learned.play_rule_creep_gains) == 2
        assert len(published) < 60     # republished at most once a second while learning
        values = yaml.safe_load(learned.parameters_yaml)['/**']['ros__parameters']
        assert values['identification']['play_share_rising'] == learned.play_share_rising
        assert values['identification']['play_share_slope_falling'] == \
            learned.play_share_slope_falling
        wait_until(lambda: any(kv.key == 'samples_learned' for a in diagnostics
                               for s in a.status for kv in s.values), 10, 'diagnostics')
        keys = {kv.key for a in diagnostics for s in a.status for kv in s.values}
        assert {'play_share_rising', 'play_share_falling', 'play_share_slope_rising',
                'play_share_slope_falling', 'branch_correction_mm',
                'branch_difference_mm', 'creep_gains', 'mix_weights', 'play_rule_correction_mm',
                'play_rule_difference_mm', 'play_rule_creep_gains',
                'first_loading_term_mm', 'local_offset_mm'} <= keys
        # The node's own mix learned a local offset from the rig's lengths.
        assert any(float(kv.value) != 0.0 for a in diagnostics for s in a.status
                   for kv in s.values if kv.key == 'local_offset_mm')
        # The run travels far past one loading: its term has ended and left the filter.
        first_loading = [kv.value for a in diagnostics for s in a.status for kv in s.values
                         if kv.key == 'first_loading_term_mm']
        assert first_loading[-1] == 'ended'
    finally:
        probe.node.destroy_subscription(sub_params)
        probe.node.destroy_subscription(sub_diag)

    saved = tmp_path / 'learned.yaml'
    saved.write_text(learned.parameters_yaml)
    resumed = procs.ros2_run('pma_model', 'model_node', name='resumed_model', ros_args=[
        '-r', '__ns:=/resumed', '--params-file', str(saved)])
    resumed.wait_for_line('model_node ready', 30)
    again, sub_again = probe.collect(ModelParams, '/resumed/pma/model_params', latched)
    try:
        wait_until(lambda: again, 20, 'the resumed node parameters')
        start = again[-1]
        assert start.play_share_rising == learned.play_share_rising
        assert start.play_share_falling == learned.play_share_falling
        assert start.play_share_slope_rising == learned.play_share_slope_rising
        assert start.play_share_slope_falling == learned.play_share_slope_falling
        assert list(start.branch_correction_m) == list(learned.branch_correction_m)
        assert list(start.branch_difference_m) == list(learned.branch_difference_m)
        assert list(start.creep_gains) == list(learned.creep_gains)
        assert list(start.play_rule_correction_m) == list(learned.play_rule_correction_m)
        assert list(start.play_rule_difference_m) == list(learned.play_rule_difference_m)
        assert list(start.play_rule_creep_gains) == list(learned.play_rule_creep_gains)
        assert list(start.mix_weights) == list(learned.mix_weights)
        assert start.samples_learned == 0
    finally:
        probe.node.destroy_subscription(sub_again)
