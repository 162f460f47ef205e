"""Online drift adaptation on a drifting simulated rig (docs/model.md §5).

The truth is the rig's Preisach muscle, whose rest length then creeps by +1.5 mm and whose
stroke grows by 8 % over the first third of a run of 120 random reversals (temperature,
fatigue: the drift the paper names as its open problem), measured with 0.2 mm of noise.
The model (the shipped defaults, fitted to Table 1) never matches a Preisach muscle
exactly, so "the noise floor" here is the model's own error on the same rig without drift:
adaptation must bring the drifted error back down to it.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from pma_driver.sim.muscle import PreisachMuscle
from pma_model.adaptation import AdaptationSettings, DriftAdapter
from pma_model.params import default_params

SHIFT_M, GAIN, NOISE_M = 0.0015, 1.08, 0.0002


def rms_mm(error) -> float:
    return float(np.sqrt(np.mean(np.square(error)))) * 1000


@pytest.fixture(scope='module')
def drifting_rig():
    rng = np.random.default_rng(7)
    turns = [0.0, *rng.uniform(0.0, 500e3, 120), 0.0]
    path = np.concatenate([np.linspace(a, b, max(2, int(abs(b - a) / 5e3)))[1:]
                           for a, b in itertools.pairwise(turns)])
    muscle = PreisachMuscle()
    steady = np.array([muscle.update(p) for p in path])
    rest = muscle.params.rest_length_m
    creep = np.minimum(1.0, np.arange(path.size) / (path.size / 3))
    drifted = rest + creep * SHIFT_M + (1 + creep * (GAIN - 1)) * (steady - rest)
    measured = drifted + rng.normal(0.0, NOISE_M, path.size)
    return path, steady, drifted, measured


@pytest.mark.parametrize('form', ['sigmoid', 'hill'])
def test_adaptation_brings_the_drifted_error_back_to_the_models_floor(drifting_rig, form):
    path, steady, drifted, measured = drifting_rig
    params = replace(default_params(), branch_form=form)
    frozen = params.build_model().predict(path)
    settings = replace(params.adaptation, enabled=True)   # default forgetting 0.99
    adapter = DriftAdapter(params.build_model().rest_length_m, settings)
    adapted = np.empty(path.size)
    for i, (model_length, measurement) in enumerate(zip(frozen, measured, strict=True)):
        adapted[i] = adapter.correct_then_learn(model_length, measurement)
    settled = slice(path.size // 2, None)
    floor = rms_mm(frozen[settled] - steady[settled])
    drifting = rms_mm(frozen[settled] - drifted[settled])
    recovered = rms_mm(adapted[settled] - drifted[settled])
    print(f'\n{form}: model error without drift {floor:.3f} mm; with drift, frozen '
          f'{drifting:.3f} mm, adapted {recovered:.3f} mm (shift {adapter.shift_m * 1e3:.2f} '
          f'mm, gain {adapter.gain:.3f}; {path.size} samples, noise {NOISE_M * 1e3:.1f} mm)')
    assert drifting > 1.25 * floor            # the drift is visible above the model's error
    assert recovered < 1.02 * floor           # and adaptation takes it away again
    assert adapter.samples_rejected == 0
    assert isinstance(settings, AdaptationSettings)
