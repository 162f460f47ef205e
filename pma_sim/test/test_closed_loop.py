"""run_closed_loop: the simulated device in the loop, with the host's command delay."""

import numpy as np
import pytest

from pma_sim.closed_loop import run_closed_loop

pytestmark = pytest.mark.in_process


def first_rise_s(command_delay_s: float) -> float:
    """When the gauge pressure first rises after a 300 kPa step commanded at t = 1 s."""
    trace = run_closed_loop(lambda t_s, _p, _l: 300e3 if t_s >= 1.0 else 0.0, 2.0,
                            rate_hz=50, command_delay_s=command_delay_s).arrays()
    rising = (trace['t_s'] > 1.0) & (trace['pressure_pa'] > 20e3)
    return float(trace['t_s'][np.argmax(rising)])


def test_a_delayed_setpoint_reaches_the_device_that_much_later():
    immediate, delayed = first_rise_s(0.0), first_rise_s(0.2)
    assert 1.0 < immediate < 1.2, immediate
    assert delayed - immediate == pytest.approx(0.2, abs=0.03)


def test_a_negative_delay_is_refused():
    with pytest.raises(ValueError, match='command_delay_s'):
        run_closed_loop(lambda *_: 0.0, 1.0, command_delay_s=-0.1)
