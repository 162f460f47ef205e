"""The controller's 0.1 Hz target on muscles its defaults were not chosen on.

pma_control's own tests run the simulator's families; these are held out
(support.muscle_families): the paper's Bouc-Wen model, and muscles creeping more slowly and
more than `creep` does (30 % of each change lagged by 1.5-2 s), where a feedforward that
inverts only the settled curves lags a 0.1 Hz sine by the creep (2.1-2.3 % of stroke before
it aimed through the learned creep; docs/control.md). bench_control.py runs the same on six
device seeds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pma_control.controller import ControllerSettings, LengthController
from pma_driver.sim.closed_loop import run_closed_loop
from pma_driver.sim.device import DeviceConfig, Rig
from pma_model.params import default_params
from support.muscle_families import BOUC_WEN, STROKE_M, muscle_for

SINE_HZ = 0.1


def sine_rmse_m(family: str, seed: int) -> float:
    """ff_fb on a 0.1 Hz sine 25 <-> 29.5 cm, against the true length, after one period."""
    control = LengthController(default_params().build_online(), ControllerSettings())

    def reference(t_s: float) -> float:
        return 0.2725 - 0.0225 * math.cos(2 * math.pi * SINE_HZ * t_s)

    def step(t_s, pressure_pa, length_m):
        control.set_target(reference(t_s))
        return control.update(t_s, pressure_pa, length_m).command_pa

    config = DeviceConfig(rate_hz=20, heartbeat_check=False, seed=seed)
    trace = run_closed_loop(step, 32.0, config=config,
                            rig=Rig(config, muscle_for(family))).arrays()
    after = trace['t_s'] > 1.0 / SINE_HZ
    error = trace['true_length_m'][after] - [reference(t) for t in trace['t_s'][after]]
    return float(np.sqrt(np.mean(error ** 2)))


@pytest.mark.parametrize(('family', 'seed'), [
    ('creep:narrow:0.3:2.0', 11), ('creep:narrow:0.3:2.0', 12), ('creep:wide:0.3:1.5', 11),
    ('creep:wide:0.3:1.5', 12), (BOUC_WEN, 11)])
def test_a_0_1_hz_sine_is_tracked_within_2_percent_of_the_stroke(family, seed):
    # Device seed 12 (sensor noise, valve timing): 2.27 and 2.04 % before the aim.
    assert sine_rmse_m(family, seed) <= 0.02 * STROKE_M
