"""Drift adaptation: brings a drifting rig back to the noise floor, and stays bounded."""

import itertools
import math

import numpy as np
import pytest

from pma_model.adaptation import AdaptationSettings, DriftAdapter
from pma_model.params import default_params

SHIFT_M, GAIN, NOISE_M = 0.0015, 1.08, 0.0002  # +1.5 mm rest length, x1.08 stroke, 0.2 mm


def random_reversal_path(rng, reversals=120, step_pa=5_000.0):
    turns = np.concatenate(([0.0], rng.uniform(0.0, 500e3, reversals)))
    pieces = [np.linspace(a, b, max(2, int(abs(b - a) / step_pa)))[1:]
              for a, b in itertools.pairwise(turns)]
    return np.concatenate(pieces)


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


def test_drifting_rig_is_brought_back_to_the_noise_floor():
    rng = np.random.default_rng(2024)
    params = default_params()
    pressures = random_reversal_path(rng)
    base = params.build_model().predict(pressures)
    reference = params.build_model().rest_length_m
    # The drift grows over the first third of the run, then stays.
    ramp = np.minimum(1.0, np.arange(base.size) / (base.size / 3))
    truth = reference + ramp * SHIFT_M + (1 + ramp * (GAIN - 1)) * (base - reference)
    measured = truth + rng.normal(0.0, NOISE_M, base.size)

    adapter = DriftAdapter(reference, AdaptationSettings(enabled=True, forgetting=0.99))
    adapted = np.empty(base.size)
    for i, (model_length, measurement) in enumerate(zip(base, measured, strict=True)):
        adapted[i] = adapter.correct_then_learn(model_length, measurement)

    settled = slice(base.size // 2, None)
    before = rms(base[settled] - truth[settled])
    after = rms(adapted[settled] - truth[settled])
    print(f'\ndrift RMSE vs truth: frozen {before * 100:.4f} cm, adapted {after * 100:.4f} cm '
          f'(noise {NOISE_M * 100:.3f} cm, {base.size} samples)')
    assert before > 1e-3
    assert after < 0.5 * NOISE_M  # below the sensor noise: the drift is gone
    assert adapter.shift_m == pytest.approx(SHIFT_M, abs=2e-4)
    assert adapter.gain == pytest.approx(GAIN, abs=0.01)
    assert adapter.samples_rejected == 0
    assert adapter.correct(0.27) == pytest.approx(adapter.offset_m + adapter.gain * 0.27)
    assert adapter.uncorrect(adapter.correct(0.26)) == pytest.approx(0.26)


def test_nan_measurements_are_ignored():
    adapter = DriftAdapter(0.30)
    for bad_pair in ((0.27, math.nan), (math.nan, 0.27), (0.27, math.inf)):
        assert adapter.update(*bad_pair) is False
    assert (adapter.shift_m, adapter.gain, adapter.samples_used) == (0.0, 1.0, 0)
    assert adapter.samples_rejected == 3


def test_a_bad_sensor_cannot_run_it_away():
    settings = AdaptationSettings(enabled=True, max_shift_m=0.002, min_gain=0.9, max_gain=1.1)
    adapter = DriftAdapter(0.30, settings)
    rng = np.random.default_rng(1)
    # A sensor that reads 4 mm short at rest and far too short under pressure...
    for _ in range(5_000):
        model_length = 0.30 - rng.uniform(0.0, 0.05)
        adapter.update(model_length, model_length - 0.004 - 0.3 * (0.30 - model_length))
    assert -0.002 <= adapter.shift_m <= 0.002 and 0.9 <= adapter.gain <= 1.1
    assert adapter.gain == pytest.approx(1.1)  # wants 1.3: held at the limit
    assert adapter.samples_rejected > 0  # the worst samples are outliers even then
    # ...and one that is stuck far away is rejected as an outlier, sample after sample.
    stuck = DriftAdapter(0.30, settings)
    for _ in range(1_000):
        assert stuck.update(0.27, 0.35) is False
    assert (stuck.shift_m, stuck.gain) == (0.0, 1.0)


def test_long_hold_without_excitation_does_not_wind_up_the_covariance():
    adapter = DriftAdapter(0.30, AdaptationSettings(forgetting=0.95))
    initial = np.diag(adapter._covariance).copy()
    for _ in range(20_000):  # holding at rest: the gain is not observable
        adapter.update(0.30, 0.3001)
    assert np.all(np.diag(adapter._covariance) <= initial * (1 + 1e-12))
    assert adapter.shift_m == pytest.approx(0.0001, abs=1e-6)
    assert adapter.gain == pytest.approx(1.0)


def test_settings_are_validated():
    for bad in ({'forgetting': 1.5}, {'forgetting': math.nan}, {'max_shift_m': 0.0},
                {'min_gain': 1.2}, {'max_gain': 0.9}, {'outlier_m': -1.0}, {'enabled': 1}):
        with pytest.raises(ValueError, match=next(iter(bad)).split('_')[0]):
            AdaptationSettings(**bad)
    with pytest.raises(ValueError, match='reference_length_m'):
        DriftAdapter(math.nan)
