"""Online identification: the learned correction, the shares, creep, drift, restart.

Truths here are built from the model's own pieces (a known share, a known correction, a
known creep), so the test can say what the right answer is; the simulated muscle families
(tests/test_minor_loops.py) test the same machinery against muscles it does not contain.
"""

import copy
import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_model import identification
from pma_model.correction import (
    CORRECTION_KNOTS_PA,
    CorrectedBranch,
    correction_caps,
    knot_sensitivity,
    monotone_correction,
)
from pma_model.identification import (
    IdentificationSettings,
    OnlineModel,
    run_online,
    virgin_knot_weights,
)
from pma_model.memory import HysteresisModel
from pma_model.params import ModelParams, ParamsError, default_params

pytestmark = pytest.mark.in_process

KPA = 1000.0
RATE_HZ = 50.0


def random_path(seed=0, turns=60, step_pa=3_000.0):
    rng = np.random.default_rng(seed)
    points = [0.0]
    for k in range(turns):
        points.append(rng.uniform(points[-1], 500e3) if k % 2 == 0
                      else rng.uniform(0.0, points[-1]))
    points.append(0.0)
    return path_through(points, step_pa)


def path_through(points, step_pa):
    """(time_s, pressure): a ramp to each turning point, then a 1 s hold there."""
    pieces = []
    for a, b in itertools.pairwise(points):
        pieces += [np.linspace(a, b, max(2, round(abs(b - a) / step_pa)))[1:],
                   np.full(round(RATE_HZ), b)]
    pressure = np.concatenate(pieces)
    return np.arange(pressure.size) / RATE_HZ, pressure


def online(**identification):
    """The defaults with the 'identify' rule alone (the 'mix' memory runs it beside 'play':
    test_mix.py)."""
    params = default_params()
    return replace(params, memory='identify',
                   identification=replace(params.identification, **identification))


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


SMOOTH_BUMP = tuple(0.002 * math.sin(math.pi * p / 500e3) - 0.001 for p in CORRECTION_KNOTS_PA)


# --- the correction -------------------------------------------------------------------------

def _model_after(path_pa, offsets, shares, memory):
    knots = len(CORRECTION_KNOTS_PA)
    increasing, decreasing = default_params().branches()
    model = HysteresisModel(CorrectedBranch(increasing, tuple(offsets[:knots])),
                            CorrectedBranch(decreasing, tuple(offsets[knots:])),
                            memory=memory, play_shares=tuple(shares))
    for p_pa in path_pa:
        model.update(float(p_pa))
    return model


@pytest.mark.parametrize('memory', ['identify', 'madelung', 'play', 'switch'])
def test_the_length_gradient_is_the_derivative_through_every_turning_point(memory):
    # What the filter learns the knots and shares from: d length / d (both branches' knots,
    # the two play shares), carried along the turning-point stack. Checked against central
    # differences of whole replays, on nested paths with noise (deep stacks, wiped loops).
    rng = np.random.default_rng(3)
    knots = len(CORRECTION_KNOTS_PA)
    offsets, shares = rng.normal(0.0, 0.0005, 2 * knots), np.array([0.3, 0.7])
    turns = [0, 400e3, 150e3, 330e3, 220e3, 290e3, 100e3, 480e3, 260e3, 310e3, 30e3, 200e3]
    path = np.concatenate([np.linspace(a, b, 40)[1:] for a, b in itertools.pairwise(turns)])
    path = np.maximum(path + rng.normal(0.0, 300.0, path.size), 0.0)
    step = 1e-7
    for stop in rng.integers(5, path.size, 8):
        model = _model_after(path[:stop], offsets, shares, memory)
        analytic = model.length_gradient(knot_sensitivity)
        numeric = np.zeros(2 * knots + 2)
        for j in range(numeric.size):
            nudge = np.zeros(numeric.size)
            nudge[j] = step
            up = _model_after(path[:stop], offsets + nudge[:-2], shares + nudge[-2:], memory)
            down = _model_after(path[:stop], offsets - nudge[:-2], shares - nudge[-2:], memory)
            numeric[j] = (up.length_m - down.length_m) / (2 * step)
        assert np.max(np.abs(analytic - numeric)) < 1e-6, (stop, analytic, numeric)
        if memory == 'identify' and len(model.turning_points) >= 2:
            # Pinned to turning points that came from the other branch: not its own weights.
            own = slice(0, knots) if model.rising else slice(knots, 2 * knots)
            other = slice(knots, 2 * knots) if model.rising else slice(0, knots)
            assert np.abs(numeric[other]).max() > 0.05
            assert np.abs(numeric[own]).sum() != pytest.approx(1.0, abs=0.01)


@settings(max_examples=50, deadline=None)
@given(values=st.lists(st.floats(-0.005, 0.005), min_size=len(CORRECTION_KNOTS_PA),
                       max_size=len(CORRECTION_KNOTS_PA)),
       form=st.sampled_from(['sigmoid', 'hill']), fraction=st.floats(0.0, 1.0))
def test_corrected_branches_stay_monotone_and_invert_in_closed_form(values, form, fraction):
    branches = replace(default_params(), branch_form=form).branches()
    grid = np.linspace(0.0, 600e3, 1201)
    for base in branches:
        offsets = monotone_correction(values, correction_caps(base))
        corrected = CorrectedBranch(base, offsets)
        lengths = corrected.length(grid)
        assert np.all(np.diff(lengths) <= 1e-12)
        assert np.allclose(corrected.length(np.array(CORRECTION_KNOTS_PA)),
                           base.length(np.array(CORRECTION_KNOTS_PA)) + offsets, atol=1e-12)
        assert corrected.length(123e3) == pytest.approx(float(corrected.length(
            np.array([123e3]))[0]), abs=1e-15)   # scalar and array paths agree
        low, high = corrected.length_range(500e3)
        target = low + fraction * (high - low)
        pressure = corrected.pressure(target, 500e3)
        if np.any(np.isclose(lengths, target, atol=1e-9) & (np.gradient(lengths) == 0.0)):
            continue   # a flat stretch: any pressure on it is right
        assert float(corrected.length(pressure)) == pytest.approx(target, abs=1e-9)


def test_a_corrected_branch_remembers_lengths_without_changing_them():
    # It keeps the lengths it computed at single pressures (the online step asks for the
    # same few again and again), up to a bound, then starts again: each answer must be the
    # one a branch that remembers nothing gives, before and after the bound.
    increasing, _ = default_params().branches()
    offsets = monotone_correction(SMOOTH_BUMP, correction_caps(increasing))
    remembering = CorrectedBranch(increasing, offsets)
    pressures = [float(p) for p in np.random.default_rng(3).uniform(0.0, 520e3, 700)]
    for p_pa in pressures + pressures[::-1]:   # past the bound, then what was forgotten
        assert remembering.length(p_pa) == CorrectedBranch(increasing, offsets).length(p_pa)
    assert 0 < len(remembering._known_lengths) <= 256
    assert CorrectedBranch(increasing, offsets) == remembering   # not part of its value


def test_the_correction_can_make_the_sigmoid_flat_in_the_dead_zone():
    # The paper's sigmoid falls 3.5 mm between 0 and 50 kPa, where the muscle is flat.
    increasing, _ = default_params().branches()
    caps = correction_caps(increasing)
    fall = increasing.length(0.0) - increasing.length(50e3)
    assert caps[0] == pytest.approx(fall)
    flat = monotone_correction([0.0, 0.01] + [0.0] * (len(CORRECTION_KNOTS_PA) - 2), caps)
    corrected = CorrectedBranch(increasing, flat)
    assert np.ptp(corrected.length(np.linspace(0, 50e3, 11))) < 1e-12
    assert corrected.pressure(float(corrected.length(0.0))) == 0.0   # the least pressure


# --- learning -------------------------------------------------------------------------------

def corrections(bump=SMOOTH_BUMP):
    """A known correction of both default branches, monotone on each."""
    caps = np.minimum(*(correction_caps(branch) for branch in default_params().branches()))
    correction = monotone_correction(bump, caps)
    return correction, correction


def truth_with(shares=(0.5, 0.5), correction=None):
    branches = default_params().branches()
    if correction is not None:
        branches = tuple(CorrectedBranch(b, c) for b, c in zip(branches, correction,
                                                                strict=True))
    return HysteresisModel(*branches, memory='identify', play_shares=shares)


def test_it_learns_the_play_shares_of_each_direction():
    time_s, pressure = random_path(1)
    truth = truth_with(shares=(0.9, 0.1)).predict(pressure)
    noisy = truth + np.random.default_rng(2).normal(0.0, 2e-4, truth.size)
    model = online(length_noise_m=2e-4).build_online()
    run_online(model, pressure, noisy, time_s)
    learned = model.learned()
    # This path reverses from the major loop (origin depth 1, median): the shares there.
    assert learned.share_at(True, 1.0) == pytest.approx(0.9, abs=0.1)
    assert learned.share_at(False, 1.0) == pytest.approx(0.1, abs=0.1)


def nested_path(seed=0, nests=14, step_pa=3_000.0):
    """Nests of three loops shrinking toward mid-pressure: reversals all across the loop."""
    rng = np.random.default_rng(seed)
    points = [0.0]
    for _ in range(nests):
        high, low = rng.uniform(350e3, 500e3), rng.uniform(0.0, 150e3)
        for _ in range(3):
            points += [high, low]
            high, low = high - rng.uniform(30e3, 80e3), low + rng.uniform(30e3, 80e3)
        points.append(0.0)
    return path_through(points, step_pa)


def test_it_learns_how_the_share_changes_across_the_loop():
    # A truth that holds after a full excursion and follows Madelung after a short one on
    # the way up (slope +0.8), the other way round on the way down (-0.8).
    time_s, pressure = nested_path(1)
    truth_model = HysteresisModel(*default_params().branches(), memory='identify',
                                  play_shares=(0.5, 0.5), share_slopes=(0.8, -0.8))
    truth = truth_model.predict(pressure)
    noisy = truth + np.random.default_rng(2).normal(0.0, 2e-4, truth.size)
    model = online(length_noise_m=2e-4).build_online()
    predicted = run_online(model, pressure, noisy, time_s)
    learned = model.learned()
    # Measured: rising 0.45 + 0.84 (depth - 0.5); falling 0.33 - 0.38 (depth - 0.5): the
    # falling curves of this path differ little between the shapes (errors 0.03 mm).
    assert learned.play_share_slope_rising == pytest.approx(0.8, abs=0.2)
    assert learned.play_share_slope_falling < -0.2
    assert rms((predicted - truth)[truth.size // 2:]) < 1e-4


def test_a_share_slope_that_would_take_a_share_outside_0_to_1_is_refused():
    IdentificationSettings(play_share_rising=0.75, play_share_slope_rising=0.5)
    with pytest.raises(ValueError, match='play_share_slope_rising'):
        IdentificationSettings(play_share_rising=0.75, play_share_slope_rising=0.6)
    with pytest.raises(ValueError, match='play_share_slope_falling'):
        IdentificationSettings(play_share_falling=0.2, play_share_slope_falling=-0.5)
    with pytest.raises(ValueError, match='play_share_slope_falling'):
        IdentificationSettings(play_share_slope_falling=math.nan)


def learn_branches(correction):
    """A truth with these (increasing, decreasing) corrections, measured with 0.5 mm noise
    along a random path: (what was learned, RMS error frozen, RMS error learning), the
    errors over the second half."""
    time_s, pressure = random_path(3)
    truth = truth_with(correction=correction).predict(pressure)
    noise = np.random.default_rng(4).normal(0.0, 5e-4, truth.size)
    frozen = online(enabled=False).build_online()
    learning = online(length_noise_m=5e-4).build_online()
    before = run_online(frozen, pressure, truth + noise, time_s) - truth
    after = run_online(learning, pressure, truth + noise, time_s) - truth
    second_half = slice(truth.size // 2, None)
    return learning.learned(), rms(before[second_half]), rms(after[second_half])


def test_it_learns_a_branch_correction_and_the_error_falls_to_the_noise():
    correction = corrections()
    learned, before, after = learn_branches(correction)
    print(f'\nfrozen {before * 1e3:.3f} mm, learned {after * 1e3:.3f} mm')
    assert after < 0.25 * before
    assert after < 3e-4
    assert np.allclose(learned.branch_correction_m, correction[0], atol=8e-4)


def test_it_learns_where_the_two_branches_miss_differently():
    """The paper's two sigmoids miss a muscle in different places (on the simulated
    families up to 3.4 mm apart at a knot): a truth whose branches need opposite corrections
    is learned as a mean and an increasing-minus-decreasing difference, and the error falls
    to the noise."""
    mean = np.array(corrections()[0])
    difference = np.array([0.003 * math.sin(2 * math.pi * p / 500e3) for p in CORRECTION_KNOTS_PA])
    caps = [correction_caps(branch) for branch in default_params().branches()]
    truth_offsets = (monotone_correction(mean + 0.5 * difference, caps[0]),
                     monotone_correction(mean - 0.5 * difference, caps[1]))
    learned, before, after = learn_branches(truth_offsets)
    print(f'\nfrozen {before * 1e3:.3f} mm, learned {after * 1e3:.3f} mm; difference mm '
          f'{np.round(np.array(learned.branch_difference_m) * 1e3, 2)}')
    assert after < 0.25 * before
    assert after < 3e-4
    wanted = np.subtract(*truth_offsets)
    assert np.corrcoef(learned.branch_difference_m, wanted)[0, 1] > 0.9
    mean, difference = (np.array(v) for v in (learned.branch_correction_m,
                                             learned.branch_difference_m))
    # The increasing branch is learned at every knot (measured: within 0.54 mm, at 50 kPa;
    # 0.32 mm at 100 kPa before the knot at 75 kPa, which shares the few samples this path
    # has of that branch at 50-100 kPa; 0.11 mm before the virgin term, which takes a share
    # of the first loading, when this path sees that branch at 50-100 kPa mostly; 0.29 mm
    # with the regressor used before 2026-11-26, and a 2.6x larger prediction error).
    assert np.abs(mean + 0.5 * difference - truth_offsets[0]).max() < 6e-4
    # The decreasing one up to what no sample shows: every falling curve of this path is
    # that branch rescaled between two turning points (the last one heading for 0 Pa), which
    # an error affine in the branch's own length does not change. Modulo that, it is learned
    # (measured: within 0.1 mm but at 500 kPa, 0.33 mm, rarely reached).
    error = mean - 0.5 * difference - truth_offsets[1]
    lengths = default_params().branches()[1].length(np.array(CORRECTION_KNOTS_PA))
    affine = np.column_stack([np.ones_like(lengths), lengths])
    unseen = affine @ np.linalg.lstsq(affine, error, rcond=None)[0]
    assert np.abs(error - unseen).max() < 5e-4
    assert np.abs(error - unseen)[:-1].max() < 2e-4


def virgin_start(time_s, pressure, offset_m=0.003, scale_pa=200e3):
    """A truth (corrections() on the default branches) whose first loading is offset_m
    longer, fading with the pressure travelled like exp(-(travel / scale_pa)^2): no shape
    the virgin term's knots contain. Noisy (0.5 mm), as learn_branches."""
    travel = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(pressure)))])
    truth = truth_with(correction=corrections()).predict(pressure) + \
        offset_m * np.exp(-(travel / scale_pa) ** 2)
    return truth, truth + np.random.default_rng(4).normal(0.0, 5e-4, truth.size)


def test_a_rested_muscles_first_loading_is_not_learned_as_its_branches(monkeypatch):
    # The Bouc-Wen muscle starts 5 mm longer than its loop (pma_sim.bouc_wen);
    # learned as the rising branch, that first loading misleads every later pass at those
    # pressures. The same model without the virgin term (its end moved to 0) is the
    # comparison.
    time_s, pressure = random_path(3)
    truth, measured = virgin_start(time_s, pressure)
    wanted = np.array(corrections()[0])
    errors, learned = {}, {}
    for term in (True, False):
        if not term:
            monkeypatch.setattr(identification, 'VIRGIN_END_PA', 0.0)
        model = online(length_noise_m=5e-4).build_online()
        predicted = run_online(model, pressure, measured, time_s)
        errors[term] = predicted - truth
        learned[term] = np.array(model.learned().branch_correction_m)
        assert model.virgin_term_m == 0.0       # gone after 500 kPa of travel
    low = slice(0, 3)      # 0-100 kPa: the knots the first loading is measured at
    off_by = {term: (learned[term] - wanted)[low] for term in learned}
    print(f'\nlow knots off by (mm): with the term {np.round(off_by[True] * 1e3, 2)}, '
          f'without {np.round(off_by[False] * 1e3, 2)}')
    assert np.abs(learned[True] - wanted).max() < 8e-4
    assert np.abs(off_by[False]).max() > 2 * np.abs(off_by[True]).max()
    later = time_s > 20.0
    assert rms(errors[True][later]) < 0.8 * rms(errors[False][later])


@settings(deadline=None)
@given(travel=st.floats(0.0, 2e6))
def test_the_virgin_term_fades_to_nothing_over_one_loading(travel):
    weights = virgin_knot_weights(travel)
    assert weights.shape == (len(identification.VIRGIN_TRAVEL_KNOTS_PA),)
    assert np.all(weights >= 0.0)
    last_knot, end = identification.VIRGIN_TRAVEL_KNOTS_PA[-1], identification.VIRGIN_END_PA
    if travel <= last_knot:
        assert weights.sum() == pytest.approx(1.0)        # a hat basis: no term lost
    elif travel < end:
        assert weights.sum() == pytest.approx((end - travel) / (end - last_knot))
    else:
        assert not weights.any()


def test_a_model_resumed_at_run_time_keeps_the_pressure_travelled():
    # A parameter change builds a new model that continues the old one's history: a muscle
    # that has travelled past the first loading is not rested again.
    time_s, pressure = random_path(3, turns=4)
    truth, measured = virgin_start(time_s, pressure)
    old = online(length_noise_m=5e-4).build_online()
    run_online(old, pressure[:40], measured[:40], time_s[:40])
    assert old.virgin_term_m > 2e-4             # learning the first loading, 120 kPa into it
    run_online(old, pressure, measured, time_s)
    new = online(length_noise_m=5e-4).build_online()
    new.resume_from(old)
    assert new.virgin_term_m == 0.0
    new.step(float(pressure[-1]) + 50e3, float(truth[-1]), float(time_s[-1]) + 0.02)
    assert new.virgin_term_m == 0.0


def test_it_learns_creep_and_predicts_the_length_still_moving_in_a_hold():
    time_s, pressure = random_path(5, step_pa=5_000.0)
    static = truth_with().predict(pressure)
    lagged = static[0]
    truth = np.empty_like(static)
    for i, value in enumerate(static):          # share 0.3 of each change arrives with 1 s lag
        lagged = value + (lagged - value) * math.exp(-1.0 / RATE_HZ)
        truth[i] = value + 0.3 * (lagged - value)
    learning, frozen = online().build_online(), online(enabled=False).build_online()
    after = run_online(learning, pressure, truth, time_s) - truth
    before = run_online(frozen, pressure, truth, time_s) - truth
    late = slice(truth.size // 2, None)
    assert rms(after[late]) < 0.2 * rms(before[late])
    assert sum(learning.learned().creep_gains) == pytest.approx(0.3, abs=0.1)


def creeping_model(gains, end_pa=150e3):
    """A model with known creep, stopped at the end of a ramp down: the lags still behind."""
    model = online(enabled=False, creep_gains=gains).build_online()
    time_s, pressure = path_through([0.0, 400e3, end_pa], 5_000.0)
    for t_s, p_pa in zip(time_s[:-round(RATE_HZ)], pressure[:-round(RATE_HZ)], strict=True):
        model.step(float(p_pa), math.nan, float(t_s))
    return model


def length_at_once(model, pressure_pa):
    """The length the model predicts if the pressure were there now (the lags not moved)."""
    return copy.deepcopy(model).step(pressure_pa, math.nan, model._time).length_m


@pytest.mark.parametrize('target_m', [0.250, 0.265, 0.285])
def test_aimed_through_creep_the_inverse_makes_the_length_now(target_m):
    """The plain inverse is where the length settles, seconds later; aimed through
    settled_aim_m it is the length now (what a controller wants), exactly."""
    model = creeping_model((0.2, 0.1))
    aim = model.settled_aim_m(target_m, max_creep_share=0.9)
    answer = model.pressure_for_length(aim)
    assert answer.success, answer.message
    assert length_at_once(model, answer.gauge_pressure_pa) == pytest.approx(target_m, abs=1e-9)
    plain = model.pressure_for_length(target_m).gauge_pressure_pa
    assert abs(length_at_once(model, plain) - target_m) > 2e-4      # creep is in the way


def test_the_aim_leads_for_no_more_creep_than_allowed_and_none_without_creep():
    # Gains (0.2, 0.1) held to a share of 0.15 lead as gains (0.1, 0.05) do: the lags are
    # the same (they follow the static length, not the gains).
    capped = creeping_model((0.2, 0.1)).settled_aim_m(0.26, max_creep_share=0.15)
    assert capped == pytest.approx(creeping_model((0.1, 0.05)).settled_aim_m(0.26, 0.9),
                                   abs=1e-12)
    assert abs(capped - 0.26) > 1e-4
    assert creeping_model((0.0, 0.0)).settled_aim_m(0.26, 0.9) == 0.26
    assert creeping_model((-0.1, 0.0)).settled_aim_m(0.26, 0.9) == 0.26
    assert math.isnan(creeping_model((0.2, 0.1)).settled_aim_m(math.nan, 0.9))


def test_a_restart_resumes_what_was_learned():
    correction = corrections()
    time_s, pressure = random_path(6)
    truth = truth_with(shares=(0.8, 0.2), correction=correction).predict(pressure)
    first = online().build_online()
    run_online(first, pressure, truth, time_s)
    saved = online().with_learned(first.learned())
    reloaded = ModelParams.from_yaml(saved.to_yaml())
    assert reloaded == saved and reloaded.identification.learned_anything
    fresh, resumed = online().build_online(), reloaded.build_online()
    early = slice(0, truth.size // 10)
    error_fresh = run_online(fresh, pressure, truth, time_s) - truth
    error_resumed = run_online(resumed, pressure, truth, time_s) - truth
    assert rms(error_resumed[early]) < 0.5 * rms(error_fresh[early])


def test_a_restart_saves_the_same_numbers_again_to_the_last_bit():
    # Numbers saved at a bound (a branch correction kept monotone or within its limit) come
    # back as mean +/- half the difference, which can miss the bound by an ulp; before that
    # counted as meeting it, 16 of these 100 drifted by an ulp on every restart.
    rng = np.random.default_rng(0)
    for _ in range(100):
        knots = len(CORRECTION_KNOTS_PA)
        params = online(branch_correction_m=tuple(rng.uniform(-0.004, 0.004, knots)),
                        branch_difference_m=tuple(rng.uniform(-0.004, 0.004, knots)))
        saved = params.build_online().learned()
        again = replace(params, identification=saved).build_online().learned()
        assert (again.branch_correction_m, again.branch_difference_m) == \
            (saved.branch_correction_m, saved.branch_difference_m)


def test_bad_samples_neither_predict_nor_teach():
    model = online().build_online()
    time_s, pressure = random_path(7, turns=4)
    run_online(model, pressure[:200], truth_with().predict(pressure[:200]), time_s[:200])
    learned, count = model.learned(), model.samples_learned
    nan = model.step(math.nan, 0.28, time_s[200])
    assert math.isnan(nan.length_m) and model.samples_learned == count
    model.step(pressure[200], math.nan, time_s[200])     # no echo: predict, do not learn
    assert model.samples_learned == count
    model.step(pressure[201], 0.5, time_s[201])           # 20 cm off: an outlier
    assert model.samples_learned == count and model.samples_rejected == 1
    assert model.learned() == learned


def test_settings_are_validated_and_named_in_params():
    with pytest.raises(ValueError, match=r'play_share_rising must be within 0\.\.1'):
        IdentificationSettings(play_share_rising=1.5)
    knots = len(CORRECTION_KNOTS_PA)
    with pytest.raises(ValueError, match=f'branch_correction_m must have {knots} values'):
        IdentificationSettings(branch_correction_m=(0.0,) * 3)
    with pytest.raises(ParamsError, match=r'identification\.creep_gains values must be'):
        ModelParams.from_ros_parameters({'identification.creep_gains': [0.0, 3.0]})
    with pytest.raises(ParamsError, match=r'identification\.branch_correction_m must be a list'):
        ModelParams.from_ros_parameters({'identification.branch_correction_m': 0.0})


def test_the_prediction_never_jumps():
    # The memory is continuous; learning moves the prediction by its updates: up to ~2 mm
    # while the first noisy samples (1.7 mm) arrive, a fraction of a millimetre after that.
    # On 1 kPa steps the length may also move by the branch slope (~0.3 mm per kPa at
    # most). The paper's switch jumps by the loop width, ~5 mm.
    time_s, pressure = random_path(8, step_pa=1_000.0)
    truth = truth_with(shares=(0.9, 0.1), correction=corrections()).predict(pressure)
    noisy = truth + np.random.default_rng(9).normal(0.0, 1.7e-3, truth.size)
    predicted = run_online(online().build_online(), pressure, noisy, time_s)
    increasing = default_params().branches()[0]
    slope = max(increasing.slope_m_per_pa(p) for p in np.linspace(0, 500e3, 101))
    steps = np.abs(np.diff(predicted)) - slope * np.abs(np.diff(pressure))
    assert steps.max() < 2.5e-3
    assert steps[time_s[1:] > 20.0].max() < 5e-4


def test_identification_off_is_the_memory_model_alone():
    time_s, pressure = random_path(10, turns=10)
    params = online(enabled=False)
    plain = params.build_model().predict(pressure)
    model = params.build_online()
    # Equal to rounding: one sample at a time goes through math, the array through numpy.
    # A length learned from the 3 mm offset would be a million times beyond the tolerance.
    np.testing.assert_allclose(run_online(model, pressure, plain + 0.003, time_s), plain,
                               rtol=0.0, atol=1e-12)
    assert isinstance(model, OnlineModel) and model.samples_learned == 0


def test_a_noisy_hold_neither_moves_the_prediction_nor_teaches_nonsense():
    # A long hold in miniature: 250 kPa above the last turn, read through the 10-bit sensor
    # (611 Pa steps, 1.25 kPa noise), the HC-SR04's 1.7 mm noise on the length. Every noise
    # reversal enters the memory and closes again; the reported branch does not flip (the
    # deadband), learning adds next to nothing to the jitter and learns no nonsense.
    rng = np.random.default_rng(11)
    time_s, pressure = random_path(12, turns=6)
    truth = truth_with().predict(pressure)
    level = pressure[-1] + 250e3
    hold = 611.0 * np.round((level + rng.normal(0.0, 1.25e3, 3000)) / 611.0)
    path = np.concatenate([np.linspace(pressure[-1], level, 50), hold])
    times = time_s[-1] + (1 + np.arange(path.size)) / RATE_HZ
    expected = truth_with().predict(np.concatenate([pressure, path]))[pressure.size:]
    jitter = {}
    for learn in (True, False):
        model = online(enabled=learn).build_online()
        run_online(model, pressure, truth + rng.normal(0.0, 1.7e-3, truth.size), time_s)
        measured = expected + rng.normal(0.0, 1.7e-3, path.size)
        steps = [model.step(*sample) for sample in zip(path[:100], measured[:100], times[:100],
                                                       strict=True)]
        before = model.learned()    # the ramp taught what it could; now only noise
        steps += [model.step(*sample) for sample in zip(path[100:], measured[100:],
                                                        times[100:], strict=True)]
        predicted = [step.length_m for step in steps]
        branches = {step.branch for step in steps[100:]}
        jitter[learn] = float(np.ptp(predicted[550:]))
        assert len(branches) == 1 and len(model.model.turning_points) < 40
        after = model.learned()
        # A hold on a scanning curve still says something about the share, but one pressure
        # cannot tell the share from the knots' error there: with seeds 0-7 of the length
        # noise (a /tmp script, 2026-11-27) the shares moved by at most 0.30, toward the
        # truth's 0.5 or away from it, with or without the virgin term (an earlier form of
        # this test asked for "toward" and met it on this seed by luck: seeds 6 and 7 moved
        # away by 0.2 and 0.3). With the knot at 75 kPa (2026-11-29) this short path leaves
        # the shares elsewhere before the hold (the rising one 0.14-0.85 over seeds 0-7 and
        # 11, against 0.29-0.81), and the hold moves them by up to 0.60 (seed 2: 0.25 ->
        # 0.85; this seed: 0.14 -> 0.50), but to where it did before: 0.18-0.85 after it,
        # against 0.20-0.86. Nonsense runs to 0 or 1. The correction stays about where it
        # was. Knots next to the held one, barely seen, wander with the noise: over this
        # hold and seeds 0-7 of the same test the mean correction moved at most 1.06 mm at a
        # knot (0.72 mm before the branch difference was learned too); nonsense moves several.
        for name in ('play_share_rising', 'play_share_falling'):
            assert 0.1 < getattr(after, name) < 0.9, name
            assert abs(getattr(after, name) - getattr(before, name)) < 0.65, name
        for name in ('branch_correction_m', 'branch_difference_m'):
            assert np.max(np.abs(np.subtract(getattr(after, name),
                                             getattr(before, name)))) < 1.5e-3, name
    print(f'\njitter over the hold: {jitter[False] * 1e3:.2f} mm frozen, '
          f'{jitter[True] * 1e3:.2f} mm learning')
    assert jitter[True] < jitter[False] + 2e-4
