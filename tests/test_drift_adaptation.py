"""Drift adaptation on every simulated muscle family (docs/model.md §5).

The issue: with adaptation on, the old adapter learned the memory rule's error after each
reversal as if it were drift, and minor-loop errors grew. Now drift is learned only where
the memory is sure, slowly, and apart from the shape the identification learns. On a
drift-free muscle adaptation must cost (almost) nothing; on one whose rest length creeps by
+1.5 mm and whose stroke grows by 8 % (from 60 s on, time constant 30 s, as a muscle warming
up) it must bring the error back to the noise floor within two minutes: what a perfect drift
correction would leave (pma_sim.evaluation.perfectly_corrected; the stroke is 8 %
longer, so the same shape error is 1.08x the drift-free one in metres).
"""

from __future__ import annotations

import pytest

from pma_sim.evaluation import (
    BOUC_WEN,
    IDENTIFY,
    LEARNED_RULES,
    MIX,
    Config,
    Scenario,
    perfectly_corrected,
    score,
)
from pma_sim.registry import FAMILY_NAMES

pytestmark = [pytest.mark.in_process, pytest.mark.slow]

DRIFT_START_S = 60.0
DURATION_S = 300.0
RECOVERED = (DRIFT_START_S + 120.0, DURATION_S)   # from two minutes after the drift began
# The default memory (the mix of identify and play), learning, with adaptation off and on.
OFF, ON = Config(MIX, True, False), Config(MIX, True, True)


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_adaptation_costs_nothing_without_drift(family):
    for kind in ('nested', 'random'):
        scenario = Scenario(family, kind)
        off, on = score(scenario, OFF), score(scenario, ON)
        print(f'\n{family}/{kind}: adaptation off {off.rmse_pct:.2f} / {off.max_pct:.2f} %, '
              f'on {on.rmse_pct:.2f} / {on.max_pct:.2f} % (RMSE / max of stroke)')
        assert on.rmse_m <= 1.05 * off.rmse_m
        # The RLS adapter this replaced more than doubled the worst error (7 -> 17 % of
        # stroke). A single sample's worst error moves by tenths of a millimetre with any
        # change to the learning, hence the 0.5 mm (creep/random, seed 1: 2.12 against
        # 1.87 mm at t = 36 s, 1.13x; both below the 2.40 mm adaptation on gave before the
        # exact regressor of 2026-11-26).
        assert on.max_m <= 1.1 * off.max_m + 5e-4


@pytest.mark.parametrize('rule', [*LEARNED_RULES, IDENTIFY], ids=lambda rule: rule.memory)
def test_adaptation_costs_nothing_with_any_learned_rule_on_the_bouc_wen_muscle(rule):
    """Not only the default: any rule a user may choose, on the Bouc-Wen muscle (tuning set).

    Drift used to start with a prior as wide as the shape's, and the shape was kept out of
    the directions drift moves the knots in. On the Bouc-Wen muscle (7 mm longer at rest
    than Table 1's fit) that made the filter explain the misfit as drift and balance every
    local correction elsewhere: with the play rule the knots zigzagged to their limits and
    adaptation on erred 20.1 mm where off erred 3.4 mm (2.4x the RMSE). Drift now starts at
    0 and only its random walk moves it.
    """
    scenario = Scenario(BOUC_WEN, 'nested', 3)
    off, on = score(scenario, Config(rule.memory, True, False)), \
        score(scenario, Config(rule.memory, True, True))
    print(f'\n{rule.memory}: adaptation off {off.rmse_pct:.2f} / {off.max_pct:.2f} %, '
          f'on {on.rmse_pct:.2f} / {on.max_pct:.2f} % (RMSE / max of stroke)')
    assert on.rmse_m <= 1.05 * off.rmse_m
    assert on.max_m <= 1.1 * off.max_m + 5e-4


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_adaptation_brings_a_drifting_muscle_back_to_the_noise_floor(family):
    clean = Scenario(family, 'random', 1, DURATION_S)
    drifting = Scenario(family, 'random', 1, DURATION_S, DRIFT_START_S)
    drift_free = score(clean, ON, window_s=RECOVERED)
    # The noise floor of the drifted muscle: the model's drift-free predictions through the
    # true drift (its stroke grew 8 %, and a shape error with it).
    floor = perfectly_corrected(drifting, ON, window_s=RECOVERED)
    recovered = score(drifting, ON, window_s=RECOVERED)
    ignored = score(drifting, OFF, window_s=(DRIFT_START_S + 30.0, DRIFT_START_S + 120.0))
    tracked = score(drifting, ON, window_s=(DRIFT_START_S + 30.0, DRIFT_START_S + 120.0))
    print(f'\n{family}: drift-free {drift_free.rmse_pct:.2f} %, perfectly corrected '
          f'{floor.rmse_pct:.2f} %, drifting and adapted {recovered.rmse_pct:.2f} % (from 2 '
          f'min after the drift began); while drifting {ignored.rmse_pct:.2f} % without '
          f'adaptation, {tracked.rmse_pct:.2f} % with')
    assert recovered.rmse_m <= 1.1 * floor.rmse_m
    assert tracked.rmse_m < ignored.rmse_m
