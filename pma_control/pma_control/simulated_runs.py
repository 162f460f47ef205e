"""The length controller on a simulated muscle family, in simulated time (ROS-free).

Shared by tests/test_control_on_held_out_muscles.py and bench/bench_control.py, so that
every muscle family of pma_sim.registry, of either set of pma_sim.splits, reaches the
controller the same way in both. It lives in pma_control, not pma_sim, because it runs the
controller: the simulator does not depend on the controller (pma_control's tests use the
simulator).
"""

from __future__ import annotations

import math

import numpy as np

from pma_control.controller import ControllerSettings, LengthController
from pma_model.params import default_params
from pma_sim.closed_loop import run_closed_loop
from pma_sim.device import DeviceConfig, Rig
from pma_sim.registry import muscle_family

SINE_LOW_M, SINE_HIGH_M = 0.25, 0.295    # the tracked sine: 25 <-> 29.5 cm, from the low end


def track(mode: str, family: str, profile, duration_s: float, *, seed: int, rate_hz: int = 20,
          command_delay_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time, true length, target) of the shipped controller in `mode` following
    `profile(t_s)` on `family`'s muscle (any registered family), starting from
    the shipped model with nothing learned."""
    control = LengthController(default_params().build_online(), ControllerSettings(mode=mode))

    def step(t_s, pressure_pa, length_m):
        control.set_target(profile(t_s))
        return control.command(t_s, pressure_pa, length_m).command_pa

    config = DeviceConfig(rate_hz=rate_hz, heartbeat_check=False, seed=seed)
    rig = Rig(config, muscle_family(family))
    trace = run_closed_loop(step, duration_s, config=config, rig=rig,
                            command_delay_s=command_delay_s).arrays()
    return trace['t_s'], trace['true_length_m'], np.array([profile(t) for t in trace['t_s']])


def sine_profile(frequency_hz: float):
    """The target of the tracking runs: a sine between SINE_LOW_M and SINE_HIGH_M."""
    middle, amplitude = (SINE_LOW_M + SINE_HIGH_M) / 2, (SINE_HIGH_M - SINE_LOW_M) / 2
    return lambda t: middle - amplitude * math.cos(2 * math.pi * frequency_hz * t)


def sine_error_m(t_s, true_m, target_m, frequency_hz: float) -> np.ndarray:
    """True minus target length after the first period (the start is a step, not tracking)."""
    after = t_s > 1.0 / frequency_hz
    return true_m[after] - target_m[after]
