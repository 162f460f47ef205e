"""The online model's predictions and inverse stay what they were before it was made faster.

data/online_reference.npz holds what the model computed *before* issue 47's speed work:
generated with the code of commit fe8fd9f (the identification and mix of 2026-11-29) by

    python tests/test_online_equivalence.py --write

run on that commit's pma_model (this file's `reference_runs`, then unchanged code). Every
later change to the model's speed must give the same predictions to 1e-6 m and the same
inverse answers to 1 Pa on these recorded paths, for every memory rule; a change meant to
alter the model's accuracy regenerates the file and says so (docs/model.md §7).

The paths: the simulated rig's muscles (pma_sim) on seeded reversal-rich pressure
paths at 50 Hz, measured through the rig's sensor models (noise, NaN echoes). Here in tests/,
not in pma_model/test: pma_sim depends on pma_model, so pma_model's own tests do not use it.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pma_model.params import default_params
from pma_sim import paths
from pma_sim.registry import muscle_family

pytestmark = pytest.mark.in_process

DATA = Path(__file__).resolve().parent / 'data' / 'online_reference.npz'
RULES = ('mix', 'identify', 'play', 'madelung', 'switch')
# (family, path kind, seed, branch form, adaptation on)
CASES = (('narrow', 'random', 1, 'sigmoid', False),
         ('asymmetric', 'nested', 2, 'sigmoid', True),
         ('creep', 'sines', 3, 'hill', False),
         ('wide', 'random', 4, 'hill', True))
SECONDS = 16.0
TARGETS_M = (0.250, 0.262, 0.275, 0.288, 0.297)


def _run(family: str, kind: str, seed: int):
    muscle = muscle_family(family)
    if kind == 'sines':
        path = paths.smooth_path('sines', SECONDS, seed=seed)
    else:
        turns = (paths.random_turns if kind == 'random' else paths.nested_turns)(
            SECONDS, seed=seed)
        path = paths.ramp_path(turns, seed=seed)
    n = min(path.time_s.size, round(SECONDS * 50))
    path = paths.PressurePath(path.time_s[:n], path.pressure_pa[:n], path.turns_pa,
                              path.reversal_times_s)
    return paths.simulate(muscle, path, seed=seed)


def reference_runs() -> dict[str, np.ndarray]:
    """{case/rule: predictions}, {case/rule/static: memory lengths}, {case/rule/inverse:
    AUTO and explicit-branch inverse pressures at TARGETS_M, at the middle and the end}."""
    out = {}
    for family, kind, seed, form, drift in CASES:
        run = _run(family, kind, seed)
        base = default_params()
        for rule in RULES:
            params = replace(base, branch_form=form, memory=rule,
                             adaptation=replace(base.adaptation, enabled=drift))
            online = params.build_online()
            key = f'{family}-{kind}-{seed}-{form}-{int(drift)}/{rule}'
            lengths, statics, inverses = [], [], []
            middle = run.time_s.size // 2
            for i, (p, length, t) in enumerate(zip(run.measured_pressure_pa,
                                                   run.measured_length_m, run.time_s,
                                                   strict=True)):
                prediction = online.step(float(p), float(length), float(t))
                lengths.append(prediction.length_m)
                statics.append(prediction.static_length_m)
                if i in (middle, run.time_s.size - 1):
                    for target in TARGETS_M:
                        for branch in (0, 1, 2):
                            answer = online.pressure_for_length(target, branch)
                            inverses.append(answer.gauge_pressure_pa if answer.success
                                            else -1.0)
            out[key] = np.array(lengths)
            out[f'{key}/static'] = np.array(statics)
            out[f'{key}/inverse'] = np.array(inverses)
    return out


@pytest.fixture(scope='module')
def reference():
    with np.load(DATA) as data:
        return dict(data)


@pytest.fixture(scope='module')
def current():
    return reference_runs()


def test_the_reference_covers_every_rule_and_case(reference):
    assert sorted(reference) == sorted(reference_runs_keys())


def reference_runs_keys() -> list[str]:
    keys = []
    for family, kind, seed, form, drift in CASES:
        for rule in RULES:
            key = f'{family}-{kind}-{seed}-{form}-{int(drift)}/{rule}'
            keys += [key, f'{key}/static', f'{key}/inverse']
    return keys


@pytest.mark.parametrize('rule', RULES)
def test_predictions_are_todays_to_a_micrometre(reference, current, rule):
    for key in reference_runs_keys():
        if key.split('/')[1] != rule or key.endswith(('/static', '/inverse')):
            continue
        old, new = reference[key], current[key]
        assert old.shape == new.shape, key
        assert np.array_equal(np.isnan(old), np.isnan(new)), key
        finite = np.isfinite(old)
        worst = float(np.max(np.abs(old[finite] - new[finite])))
        assert worst <= 1e-6, f'{key}: predictions moved by {worst:.3g} m'
        static_old, static_new = reference[f'{key}/static'], current[f'{key}/static']
        finite = np.isfinite(static_old)
        assert float(np.max(np.abs(static_old[finite] - static_new[finite]))) <= 1e-6, key


@pytest.mark.parametrize('rule', RULES)
def test_inverse_answers_are_todays_to_a_pascal(reference, current, rule):
    for key in reference_runs_keys():
        if key.split('/')[1] != rule or not key.endswith('/inverse'):
            continue
        old, new = reference[key], current[key]
        assert np.array_equal(old < 0, new < 0), f'{key}: refusals differ'
        worst = float(np.max(np.abs(old - new)))
        assert worst <= 1.0, f'{key}: inverse moved by {worst:.3g} Pa'


if __name__ == '__main__':
    if sys.argv[1:] != ['--write']:
        sys.exit('usage: test_online_equivalence.py --write  (writes the reference from the '
                 'code as it is: only ever from the unmodified model)')
    DATA.parent.mkdir(exist_ok=True)
    np.savez_compressed(DATA, **reference_runs())
    print(f'wrote {DATA}')
