"""The compiled online step (kernel.online_step, kernel.mix_step) predicts and learns what the
Python step (OnlineModel.reference_step, RuleMix.reference_step) does, sample by sample, on
random pressure, length and time sequences: every branch form and rule, learning on and off,
drift on and off, through the end of the virgin term, with the state read in between.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_model import identification, kernel, memory
from pma_model.detector import BRANCH_AUTO
from pma_model.mix import RuleMix
from pma_model.params import default_params

TOLERANCE_M = 1e-9
RULES = ('mix', 'identify', 'play', 'madelung', ('madelung', 'play'), ('identify', 'switch'),
         ('identify', 'play', 'madelung'))


def build(rule, form: str, *, learning: bool, drift: bool):
    """An online model of `rule` (a name, or a tuple: a mix of those rules)."""
    params = replace(default_params(), branch_form=form)
    params = replace(params, adaptation=replace(params.adaptation, enabled=drift),
                     identification=replace(params.identification, enabled=learning))
    if isinstance(rule, tuple):
        return RuleMix.of_rules(lambda name: replace(params, memory=name).build_online(),
                                rule, learning=learning)
    return replace(params, memory=rule).build_online()


def sequence(turns_kpa, noise_kpa: float, offset_m: float, seed: int, form: str):
    """(pressures, lengths, times): ramps through the turns with noise on the pressure, the
    lengths of a muscle offset_m longer than the model with the sensor's noise, a few NaN
    echoes and outliers, and times at 50 Hz with jitter, repeats and pauses."""
    rng = np.random.default_rng(seed)
    pressures = np.concatenate([np.linspace(a, b, 14)[1:] for a, b in
                                zip((0.0, *turns_kpa), turns_kpa, strict=False)]) * 1e3
    pressures += rng.uniform(-noise_kpa, noise_kpa, pressures.size) * 1e3
    truth = replace(default_params(), branch_form=form, memory='identify').build_model()
    lengths = truth.predict(pressures) + offset_m + rng.normal(0.0, 1.7e-3, pressures.size)
    lengths[rng.random(pressures.size) < 0.03] = math.nan
    lengths[rng.random(pressures.size) < 0.02] += 0.05
    steps = rng.choice([0.02, 0.02, 0.02, 0.021, 0.0, 1.5], pressures.size)
    return pressures, lengths, np.cumsum(steps)


def assert_same_prediction(compiled, reference, where) -> None:
    for name in ('length_m', 'static_length_m', 'offset_m', 'gain', 'local_offset_m'):
        a, b = getattr(compiled, name), getattr(reference, name)
        assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= TOLERANCE_M, \
            (where, name, a, b)
    assert compiled.branch == reference.branch, where


def assert_same_state(compiled, reference) -> None:
    """What was learned, the counts, the weights and the inverse, as the Python step has them."""
    for a, b in zip(compiled.experts, reference.experts, strict=True):
        mine, theirs = a.learned().learned_values(), b.learned().learned_values()
        for name, value in theirs.items():
            assert np.allclose(mine[name], value, rtol=0.0, atol=TOLERANCE_M), name
    assert compiled.samples_learned == reference.samples_learned
    assert compiled.samples_rejected == reference.samples_rejected
    assert [e.commits for e in compiled.experts] == [e.commits for e in reference.experts]
    assert compiled.first_loading_ended == reference.first_loading_ended
    assert abs(compiled.virgin_term_m - reference.virgin_term_m) <= TOLERANCE_M
    weights = compiled.weights_by_rule()
    for rule, weight in reference.weights_by_rule().items():
        assert abs(weights[rule] - weight) <= 1e-9
    for a, b in zip(compiled.experts, reference.experts, strict=True):
        mine, theirs = a.model.turning_points, b.model.turning_points
        assert len(mine) == len(theirs)
        assert np.allclose(np.reshape(mine, (-1, 2)), np.reshape(theirs, (-1, 2)), rtol=0.0,
                           atol=TOLERANCE_M)
    for target_m in (0.25, 0.27, 0.29):
        a = compiled.pressure_for_length(target_m, BRANCH_AUTO)
        b = reference.pressure_for_length(target_m, BRANCH_AUTO)
        assert a.success == b.success
        assert a.gauge_pressure_pa == pytest.approx(b.gauge_pressure_pa, abs=1e-3, nan_ok=True)


def run_both(rule, form, *, learning, drift, pressures, lengths, times, peeks=(),
             untimed=()):
    """Steps a compiled and a Python model alike, comparing each prediction; at `peeks` the
    compiled one's state is read (its memory model, what it learned, its inverse), which must
    not change what it does next."""
    compiled = build(rule, form, learning=learning, drift=drift)
    reference = build(rule, form, learning=learning, drift=drift)
    for i, (p_pa, length_m, t_s) in enumerate(zip(pressures.tolist(), lengths.tolist(),
                                                  times.tolist(), strict=True)):
        t = None if i in untimed else t_s
        assert_same_prediction(compiled.step(p_pa, length_m, t),
                               reference.reference_step(p_pa, length_m, t), (i, p_pa))
        if i in peeks:
            compiled.experts[0].learned()
            compiled.pressure_for_length(0.27)
            _ = compiled.experts[i % len(compiled.experts)].model.turning_points
    assert_same_state(compiled, reference)
    return compiled


@settings(max_examples=60, deadline=None)
@given(rule=st.sampled_from(RULES), form=st.sampled_from(('sigmoid', 'hill')),
       learning=st.booleans(), drift=st.booleans(),
       turns_kpa=st.lists(st.floats(min_value=-5.0, max_value=520.0), min_size=2, max_size=7),
       noise_kpa=st.sampled_from((0.0, 2.0, 12.0)),
       offset_m=st.sampled_from((0.0, 2e-3, -1.5e-3)), seed=st.integers(0, 1000),
       peeks=st.sets(st.integers(0, 90), max_size=3),
       untimed=st.sets(st.integers(0, 90), max_size=2),
       nan_at=st.sets(st.integers(0, 90), max_size=2))
def test_the_compiled_step_is_the_python_step(rule, form, learning, drift,  # noqa: PLR0917
                                              turns_kpa, noise_kpa, offset_m, seed, peeks,
                                              untimed, nan_at):
    pressures, lengths, times = sequence(turns_kpa, noise_kpa, offset_m, seed, form)
    pressures[[i for i in nan_at if i < pressures.size]] = math.nan
    run_both(rule, form, learning=learning, drift=drift, pressures=pressures,
             lengths=lengths, times=times, peeks=peeks, untimed=untimed)


@pytest.mark.parametrize('form', ['sigmoid', 'hill'])
@pytest.mark.parametrize('rule', ['mix', 'identify', 'play'])
def test_through_the_end_of_the_virgin_term_with_drift(rule, form):
    """Two full loops (the term ends after 500 kPa of travel), drift learning."""
    pressures, lengths, times = sequence((500.0, 0.0, 450.0, 100.0, 300.0), 3.0, 1e-3, 7, form)
    online = run_both(rule, form, learning=True, drift=True, pressures=pressures,
                      lengths=lengths, times=times)
    assert online.first_loading_ended
    assert all(e.compiled for e in online.experts)
    # The filter without its virgin term keeps the layout the compiled step was warmed up
    # with (kernel.warm_up), so no process compiles a second signature when the term ends.
    for expert in online.experts:
        assert expert._filter_now.covariance.flags['C_CONTIGUOUS']


@pytest.mark.parametrize('rule', ['mix', 'identify'])
def test_a_full_turning_point_stack_forgets_its_oldest_loop_alike(rule, monkeypatch):
    monkeypatch.setattr(memory, 'MAX_TURNING_POINTS', 6)
    monkeypatch.setattr(identification, 'MAX_TURNING_POINTS', 6)
    turns = (400.0, 50.0, 380.0, 70.0, 360.0, 90.0, 340.0, 110.0, 320.0, 130.0, 300.0)
    pressures, lengths, times = sequence(turns, 0.0, 0.0, 3, 'sigmoid')
    online = run_both(rule, 'sigmoid', learning=True, drift=False, pressures=pressures,
                      lengths=lengths, times=times)
    assert len(online.experts[0].model.turning_points) <= 6


def test_the_state_taken_over_at_run_time_steps_on_alike():
    """resume_from (a parameter change at run time) hands the compiled state over."""
    pressures, lengths, times = sequence((300.0, 100.0, 250.0), 2.0, 1e-3, 5, 'hill')
    old = build('mix', 'hill', learning=True, drift=True)
    for p_pa, length_m, t_s in zip(pressures, lengths, times, strict=True):
        old.step(float(p_pa), float(length_m), float(t_s))
    compiled = build('mix', 'sigmoid', learning=True, drift=False)
    reference = build('mix', 'sigmoid', learning=True, drift=False)
    compiled.resume_from(old)
    reference.resume_from(old)
    for k, (p_pa, length_m) in enumerate(zip(pressures[::-1], lengths, strict=True)):
        t_s = float(times[-1]) + 0.02 * (k + 1)
        assert_same_prediction(compiled.step(float(p_pa), float(length_m), t_s),
                               reference.reference_step(float(p_pa), float(length_m), t_s), k)
    assert_same_state(compiled, reference)


def test_only_the_rules_with_a_compiled_step_take_it():
    assert build('identify', 'sigmoid', learning=True, drift=False).compiled
    assert not build('switch', 'sigmoid', learning=True, drift=False).compiled
    # Drift alone learning: a second memory model measures the doubt (Python only).
    assert not build('play', 'sigmoid', learning=False, drift=True).compiled
    mix = build('mix', 'sigmoid', learning=True, drift=False)
    mix.step(1e5, 0.28, 0.0)
    assert mix._kernel_arrays() is not None
    assert len(mix.last_predictions) == 2
    assert kernel.RULE_IDENTIFY == identification.KERNEL_RULES['identify']


@pytest.mark.parametrize('rule', ['mix', 'identify'])
def test_the_inverse_between_steps_reads_the_state_each_step_left(rule):
    """The inverse and the aim read the compiled step's packed state (its path kept until the
    next step moves it): after every step they answer as the Python model's."""
    pressures, lengths, times = sequence((300.0, 120.0, 260.0), 2.0, 1e-3, 11, 'sigmoid')
    compiled = build(rule, 'sigmoid', learning=True, drift=True)
    reference = build(rule, 'sigmoid', learning=True, drift=True)
    for i, (p_pa, length_m, t_s) in enumerate(zip(pressures.tolist(), lengths.tolist(),
                                                  times.tolist(), strict=True)):
        compiled.step(p_pa, length_m, t_s)
        reference.reference_step(p_pa, length_m, t_s)
        target_m = 0.26 + 0.02 * (i % 3) / 2
        for _ in range(2):   # the second from what the first kept
            a = compiled.pressure_for_length(target_m, BRANCH_AUTO)
            b = reference.pressure_for_length(target_m, BRANCH_AUTO)
            assert a.success == b.success, i
            assert a.gauge_pressure_pa == pytest.approx(b.gauge_pressure_pa, abs=1e-3,
                                                        nan_ok=True), i
        assert compiled.settled_aim_m(0.27, 0.5) == pytest.approx(
            reference.settled_aim_m(0.27, 0.5), abs=TOLERANCE_M)
