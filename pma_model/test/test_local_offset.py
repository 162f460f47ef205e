"""LocalOffset: learns a residual the memory leaves, keeps it at a hold, forgets it with travel."""

import math

import numpy as np
import pytest

from pma_model.adaptation import AdaptationSettings
from pma_model.local_offset import FADE_PA, PLAY_PA, LocalOffset

pytestmark = pytest.mark.in_process

NOISE_M = 0.0017
OUTLIER_M = AdaptationSettings().outlier_m   # 1 cm


def travelled(local: LocalOffset, start_pa: float, end_pa: float, *, residual_m=math.nan,
              steps: int = 100, rng=None) -> None:
    """Ramp the pressure, learning a constant residual (plus sensor noise) on the way."""
    for p_pa in np.linspace(start_pa, end_pa, steps):
        local.advance(float(p_pa))
        if math.isfinite(residual_m):
            noise = rng.normal(0.0, NOISE_M) if rng is not None else 0.0
            local.learn(0.3 + residual_m + noise, 0.3)


def test_a_residual_the_memory_leaves_is_learned_from_the_sensors_noise():
    local = LocalOffset(NOISE_M, OUTLIER_M)
    travelled(local, 0.0, 300e3, residual_m=0.002, steps=600, rng=np.random.default_rng(1))
    # Most of it: while pressure travels, the offset also fades (1.33 mm measured).
    assert 0.001 < local.offset_m < 0.002


def hold(local: LocalOffset, pressure_pa: float, rng, *, residual_m=math.nan,
         samples: int = 5000) -> list[float]:
    """100 s at 50 Hz, the pressure reading noisy by 1.3 kPa; the offsets on the way."""
    offsets = []
    for _ in range(samples):
        local.advance(pressure_pa + rng.normal(0.0, 1.3e3))
        if math.isfinite(residual_m):
            local.learn(0.3 + residual_m + rng.normal(0.0, NOISE_M), 0.3)
        offsets.append(local.offset_m)
    return offsets


def test_a_noisy_hold_is_no_travel():
    rng = np.random.default_rng(2)
    local = LocalOffset(NOISE_M, OUTLIER_M)
    travelled(local, 0.0, 300e3, residual_m=0.002, steps=600, rng=rng)
    before = local.offset_m
    hold(local, local._play_pa, rng)
    assert local.offset_m > 0.95 * before


def test_at_a_hold_it_averages_the_lengths_and_does_not_chase_their_noise():
    rng = np.random.default_rng(3)
    local = LocalOffset(NOISE_M, OUTLIER_M)
    travelled(local, 0.0, 300e3, residual_m=0.002, steps=600, rng=rng)
    offsets = hold(local, local._play_pa, rng, residual_m=0.004)   # the sensor reads 2 mm more
    assert local.offset_m == pytest.approx(0.004, abs=0.0005)
    assert np.std(offsets[-1000:]) < 0.1 * NOISE_M


def test_travel_forgets_it_as_the_inverse_expects():
    local = LocalOffset(NOISE_M, OUTLIER_M)
    travelled(local, 0.0, 300e3, residual_m=0.002, steps=600)
    learned = local.offset_m
    expected = local.at(150e3)
    travelled(local, 300e3, 150e3)             # no lengths on the way: only the fade
    assert local.offset_m == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(learned * math.exp(-(150e3 - PLAY_PA) / FADE_PA),
                                     rel=1e-3)
    assert local.at(local._play_pa) == local.offset_m


@pytest.mark.parametrize('measured', [math.nan, math.inf, 0.3 + 0.02])
def test_lengths_it_cannot_use_teach_it_nothing(measured):
    local = LocalOffset(NOISE_M, OUTLIER_M)
    travelled(local, 0.0, 200e3, residual_m=0.001, steps=300)
    before = (local.offset_m, local.variance_m2)
    local.advance(200e3)
    local.learn(measured, 0.3)
    assert (local.offset_m, local.variance_m2) == before
