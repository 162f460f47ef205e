"""The compiled formulas (kernel.py): the path it builds is the one the classes built, the mix's
inverse along it and on the major branches gives what the search in Python gives, to the bit,
and the kernel runs where numba has nowhere to keep its cache.
"""

import math
import os
import shutil
import subprocess
import sys
from dataclasses import astuple, replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_model import kernel
from pma_model.branches import HillBranch, SigmoidBranch
from pma_model.correction import (
    CORRECTION_KNOTS_PA,
    CorrectedBranch,
    correction_caps,
    monotone_correction,
)
from pma_model.curves import ScanningCurve
from pma_model.detector import BRANCH_AUTO, BRANCH_DECREASING, BRANCH_INCREASING
from pma_model.memory import HysteresisModel
from pma_model.mix import RuleMix
from pma_model.params import default_params
from pma_model.rules import MEMORY_RULES

RULE_SETS = (('identify', 'play'), ('madelung', 'play'), ('identify', 'switch'),
             ('identify', 'play', 'madelung', 'switch'))


def driven_mix(rules, form: str, *, drift: bool, turns_kpa, offset_m: float, excess: float,
               seed: int) -> RuleMix:
    """A mix of `rules` on `form` branches that learned (identification, drift when `drift`,
    the local offset) along ramps through `turns_kpa` from a muscle `offset_m` longer than
    the model, its rules' losses `excess` temperatures apart."""
    params = replace(default_params(), branch_form=form)
    params = replace(params, adaptation=replace(params.adaptation, enabled=drift))
    mix = RuleMix.of_rules(lambda rule: replace(params, memory=rule).build_online(), rules)
    truth = replace(params, memory='identify').build_model()
    rng = np.random.default_rng(seed)
    pressures = np.concatenate([np.linspace(a, b, 12)[1:] for a, b in
                                zip((0.0, *turns_kpa), turns_kpa, strict=False)]) * 1e3
    lengths = truth.predict(pressures) + offset_m + rng.normal(0.0, 3e-4, pressures.size)
    for k, (p_pa, length_m) in enumerate(zip(pressures, lengths, strict=True)):
        mix.step(float(p_pa), float(length_m), k * 0.02)
    losses = np.zeros(len(rules))
    losses[1:] = excess * mix.temperature_m2s * np.arange(1, len(rules))
    mix.losses_m2s = losses
    return mix


def assert_the_same(mix: RuleMix, target_m: float, branch: int = BRANCH_AUTO) -> None:
    """The same answer, every field to the bit (NaN as NaN): along the path (AUTO) or on
    one direction's major branches."""
    compiled = mix.pressure_for_length(target_m, branch)
    searched = mix.searched_pressure_for_length(target_m, branch == BRANCH_INCREASING,
                                                path=branch == BRANCH_AUTO)
    assert [np.float64(v).tobytes() if isinstance(v, float) else v for v in
            astuple(compiled)] == [np.float64(v).tobytes() if isinstance(v, float) else v
                                   for v in astuple(searched)], (target_m, compiled, searched)


def targets_around(mix: RuleMix) -> list[float]:
    """Lengths inside both directions' reach, at and beyond its ends, and far outside."""
    here = mix.settled_length_m
    ends = []
    for probe in (here - 1.0, here + 1.0):   # each direction's refusal names its range
        answer = mix.searched_pressure_for_length(probe, True)
        ends += [answer.min_length_m, answer.max_length_m]
    low, high = min(ends), max(ends)
    return [*np.linspace(low - 1e-3, high + 1e-3, 23).tolist(), *ends,
            *(end + d for end in ends for d in (-2e-12, 2e-12, -1e-9, 1e-9)), here,
            here + 1e-6, here - 1e-6, 0.05, 0.5]


@settings(max_examples=30)
@given(rules=st.sampled_from(RULE_SETS), form=st.sampled_from(('sigmoid', 'hill')),
       drift=st.booleans(),
       turns_kpa=st.lists(st.floats(min_value=0.0, max_value=500.0), min_size=1, max_size=9),
       offset_m=st.sampled_from((0.0, 2e-3, -1.5e-3)),
       excess=st.floats(min_value=0.0, max_value=15.0), seed=st.integers(0, 3),
       local=st.booleans())
def test_the_compiled_inverse_is_the_search_in_python(rules, form, drift, turns_kpa,  # noqa: PLR0917
                                                      offset_m, excess, seed, local):
    mix = driven_mix(rules, form, drift=drift, turns_kpa=turns_kpa, offset_m=offset_m,
                     excess=excess, seed=seed)
    if not local:   # no local offset to fade along the path
        mix.without_local_offset()
    for target_m in targets_around(mix):
        for branch in (BRANCH_AUTO, BRANCH_INCREASING, BRANCH_DECREASING):
            assert_the_same(mix, target_m, branch)


@pytest.mark.parametrize('form', ['sigmoid', 'hill'])
def test_stacks_rising_paths_a_held_band_and_a_local_offset(form):
    """Nested reversals leave a deep stack; the last move down leaves a rising path ahead
    (a reversal) and the band holding; the muscle's offset leaves a local offset."""
    mix = driven_mix(('identify', 'play'), form, drift=True,
                     turns_kpa=(500, 100, 400, 150, 350, 200, 300, 250, 280), offset_m=2e-3,
                     excess=1.0, seed=0)
    state = mix.experts[0].model.path_state()
    assert len(state.turning_points) >= 6 and state.rising
    assert mix.local_offset_m != 0.0
    for target_m in targets_around(mix):
        assert_the_same(mix, target_m)
    mix.step(270e3, math.nan, 10.0)   # falling now: rising targets need a reversal
    assert not mix.experts[0].model.path_state().rising
    for target_m in targets_around(mix):
        assert_the_same(mix, target_m)


def test_the_kernel_keeps_the_branch_table_until_a_commit_makes_new_branches():
    mix = driven_mix(('identify', 'play'), 'sigmoid', drift=False, turns_kpa=(300, 100),
                     offset_m=0.0, excess=1.0, seed=0)
    mix.pressure_for_length(0.27)
    kept = mix._branch_table[1]
    mix.pressure_for_length(0.28)
    assert mix._branch_table[1] is kept
    for e in mix.experts:   # a commit: new corrected branches
        e.model.relearn(CorrectedBranch(e.increasing, (1e-4,) * len(CORRECTION_KNOTS_PA)),
                        CorrectedBranch(e.decreasing, (-1e-4,) * len(CORRECTION_KNOTS_PA)))
    mix.pressure_for_length(0.27)
    assert mix._branch_table[1] is not kept
    assert_the_same(mix, 0.27)


def reference_path(model: HysteresisModel, rising: bool) -> list:
    """The path as the classes built it before kernel.path_segments did (rules.py's
    future_segments and PlayRule.path_segments, kept here as the reference)."""
    limit_pa = model.max_gauge_pressure_pa if rising else 0.0
    if model.memory == 'play':
        major = model.major(rising)
        meets_pa = float(major.inverse_unchecked(model.length_m))
        if math.isnan(meets_pa):
            meets_pa = model.pressure_pa
        join_pa = max(model.pressure_pa, meets_pa) if rising else min(model.pressure_pa,
                                                                         meets_pa)
        return [(ScanningCurve(major), join_pa, limit_pa)]
    stack = list(model.turning_points)
    if rising != model.rising:
        stack.append((model.pressure_pa, model.length_m))
    segments = []
    p_from = model.pressure_pa
    while True:
        curve = model._curve(rising, stack)
        p_to = stack[-2][0] if len(stack) >= 2 else limit_pa
        final = len(stack) < 2 or ((p_to >= limit_pa) if rising else (p_to <= limit_pa))
        if final:
            p_to = limit_pa
        segments.append((curve, p_from, p_to))
        if final:
            return segments
        del stack[-2:]
        p_from = p_to


@settings(max_examples=60)
@given(rule=st.sampled_from(tuple(MEMORY_RULES)), form=st.sampled_from(('sigmoid', 'hill')),
       pressures_kpa=st.lists(st.floats(min_value=0.0, max_value=500.0), min_size=0,
                              max_size=40),
       offsets=st.lists(st.floats(min_value=-0.01, max_value=0.01), min_size=2, max_size=2),
       shares=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
       slopes=st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0)))
def test_the_compiled_path_is_the_one_the_classes_built(rule, form, pressures_kpa, offsets,  # noqa: PLR0917
                                                       shares, slopes):
    increasing, decreasing = replace(default_params(), branch_form=form).branches()
    knots = len(CORRECTION_KNOTS_PA)
    increasing, decreasing = (  # learned corrections: each branch's own, kept monotone
        CorrectedBranch(b, monotone_correction([d * math.cos(k) for k in range(knots)],
                                               correction_caps(b)))
        for b, d in ((increasing, offsets[0]), (decreasing, offsets[1])))
    model = HysteresisModel(increasing, decreasing, memory=rule, play_shares=shares,
                            share_slopes=slopes)
    for p_kpa in pressures_kpa:
        model.update(1e3 * p_kpa)
    for rising in (True, False):
        assert model.path_segments(rising) == reference_path(model, rising)


@given(p_pa=st.floats(min_value=-1e5, max_value=2e6),
       branch=st.sampled_from((SigmoidBranch(0.3, 0.2, 1e-5, 6.0),
                               HillBranch(0.3, 0.06, 2e5, 2.0),
                               HillBranch(0.29, 0.05, 1.5e5, 1.0))))
def test_a_row_gives_its_branch_and_the_inverse_inverts_it(p_pa, branch):
    corrected = CorrectedBranch(branch, monotone_correction(
        [1e-3 * math.sin(k) for k in range(len(CORRECTION_KNOTS_PA))],
        correction_caps(branch)))
    for b in (branch, corrected):
        length = kernel.branch_length(b.kernel_row, p_pa)
        assert length == b.length(p_pa) == pytest.approx(float(b.length(np.array([p_pa]))[0]),
                                                         abs=1e-15)
        if 1e3 <= p_pa <= 1e6 and b.slope_m_per_pa(p_pa) > 1e-9:
            assert kernel.branch_pressure(b.kernel_row, length) == pytest.approx(p_pa, rel=1e-6)


@pytest.mark.parametrize('length_m', [math.nan, math.inf, -math.inf, 0.0, 0.3, 0.5, -1.0])
def test_inverses_without_a_real_answer_are_nan_not_errors(length_m):
    for branch in (SigmoidBranch(0.3, 0.2, 1e-5, 6.0), HillBranch(0.3, 0.06, 2e5, 2.0)):
        pressure = kernel.branch_pressure(branch.kernel_row, length_m)
        assert math.isnan(pressure) or 0.0 <= pressure < math.inf
        if not 0.3 * 0.8 < length_m <= 0.3:
            assert math.isnan(pressure)


def _import_kernel(tmp_path: Path, cache_dir: str, home: Path, pycache_blocked: bool):
    """Import a copy of kernel.py in a new Python (nothing else of pma_model: it imports
    none) and call a compiled function; (caching, its answer)."""
    package = tmp_path / 'copy' / 'pma_model'
    package.mkdir(parents=True)
    source = Path(kernel.__file__)
    shutil.copy(source.parent / '__init__.py', package)
    shutil.copy(source, package)
    if pycache_blocked:   # a file where numba would make the cache beside the source
        (package / '__pycache__').write_text('')
    env = dict(os.environ, PYTHONPATH=str(tmp_path / 'copy'), NUMBA_CACHE_DIR=cache_dir,
               HOME=str(home), XDG_CACHE_HOME=str(home / '.cache'), PYTHONDONTWRITEBYTECODE='1')
    script = ('from pma_model import kernel\n'
              'print(kernel.CACHING, kernel.sigmoid_length(0.3, 0.2, 1e-5, 6.0, 1e5))\n')
    done = subprocess.run([sys.executable, '-c', script], env=env, capture_output=True,
                          text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    caching, answer = done.stdout.split()
    return caching == 'True', float(answer)


def test_with_no_writable_cache_directory_the_kernel_compiles_in_memory(tmp_path):
    blocked = tmp_path / 'blocked'
    blocked.write_text('')   # a file: no directory can be made under it, not even by root
    caching, answer = _import_kernel(tmp_path, str(blocked / 'numba'), blocked, True)
    assert not caching
    assert answer == SigmoidBranch(0.3, 0.2, 1e-5, 6.0).length(1e5)


def test_with_a_cache_directory_the_compiled_code_is_kept_there(tmp_path):
    cache = tmp_path / 'numba-cache'
    blocked = tmp_path / 'blocked'
    blocked.write_text('')
    caching, answer = _import_kernel(tmp_path, str(cache), blocked, True)
    assert caching
    assert answer == SigmoidBranch(0.3, 0.2, 1e-5, 6.0).length(1e5)
    assert any(path.suffix == '.nbi' for path in cache.rglob('*'))


def test_the_warm_up_runs_what_the_model_calls():
    kernel.warm_up()   # tools/setup.sh's: it must not fail on the default parameters
