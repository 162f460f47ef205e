"""The controller's 0.1 Hz target on muscles beyond the simulator's own four.

pma_control's own tests run the simulator's families; these are the others of the tuning set
(pma_sim.splits; the validation set's are run by bench_control.py --set validation only to
report): the paper's Bouc-Wen model, and muscles creeping more slowly and
more than `creep` does (30 % of each change lagged by 1.5-2 s), where a feedforward that
inverts only the settled curves lags a 0.1 Hz sine by the creep (2.1-2.3 % of stroke before
it aimed through the learned creep; docs/control.md). bench_control.py runs the same on six
device seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from pma_control.simulated_runs import sine_error_m, sine_profile, track
from pma_sim.evaluation import BOUC_WEN, STROKE_M

pytestmark = pytest.mark.in_process

SINE_HZ = 0.1


def sine_rmse_m(family: str, seed: int) -> float:
    """ff_fb on a 0.1 Hz sine 25 <-> 29.5 cm, against the true length, after one period."""
    error = sine_error_m(*track('ff_fb', family, sine_profile(SINE_HZ), 32.0, seed=seed),
                         SINE_HZ)
    return float(np.sqrt(np.mean(error ** 2)))


@pytest.mark.parametrize(('family', 'seed'), [
    ('creep:narrow:0.3:2.0', 11), ('creep:narrow:0.3:2.0', 12), ('creep:wide:0.3:1.5', 11),
    ('creep:wide:0.3:1.5', 12), (BOUC_WEN, 11)])
def test_a_0_1_hz_sine_is_tracked_within_2_percent_of_the_stroke(family, seed):
    # Device seed 12 (sensor noise, valve timing): 2.27 and 2.04 % before the aim.
    assert sine_rmse_m(family, seed) <= 0.02 * STROKE_M
