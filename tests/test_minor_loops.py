"""Minor loops on every simulated muscle family: the issue's acceptance (docs/model.md §3).

Each family (pma_sim.families) reproduces Table 1, so the major loop cannot tell them
apart; they differ after reversals. The model starts from the shipped defaults (sigmoid
branches fitted to Table 1, no memory data) and runs online along nested and random
reversal paths of three minutes, seeing the sensors' readings; scores count from the third
reversal on, against the true length (pma_sim.evaluation). The acceptance is
the default memory's, the mix of identify and play (MIXED).
`bench/bench_memory_families.py` prints the full table (both branch forms, two seeds).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pma_common import protocol
from pma_common.calibration import PressureCalibration
from pma_common.sweep import plan_sweep
from pma_model.identification import run_online
from pma_model.memory import HysteresisModel
from pma_model.params import default_params
from pma_sim.bouc_wen import bouc_wen_fit
from pma_sim.device import DeviceConfig, SimDevice
from pma_sim.evaluation import (
    BOUC_WEN,
    LEARNED_RULES,
    MIXED,
    MIXED_WITHOUT_LOCAL_OFFSET,
    PAPER,
    PATH_KINDS,
    STATIC_RULES,
    Config,
    Scenario,
    oracle_error_near_m,
    oracle_score,
    predict,
    return_point_oracle,
    score,
    simulate,
    worst_moment_s,
)
from pma_sim.families import CreepParams
from pma_sim.friction import DEFAULT_WIDEST_BAND
from pma_sim.generalized_play import DEFAULT_BULGE
from pma_sim.paths import SMOOTH_KINDS
from pma_sim.registry import (
    FAMILY_NAMES,
    FRICTION,
    GENERALIZED_PLAY,
    creep_variant,
    duhem_variant_scales_pa,
    friction_widest_band,
    generalized_play_bulge,
    muscle_family,
    rate_dependent,
    table1_fit_errors_m,
)

# The module fixture runs every scenario once (about 90 s of one core, more when the
# workers outnumber the cores); pyproject's 180 s is for hangs, not for this.
pytestmark = [pytest.mark.in_process, pytest.mark.slow, pytest.mark.timeout(600)]

NESTED_TURNS_KPA = (0, 350, 150, 300, 200, 250, 0, 500, 100, 400, 250, 500, 0, 200, 50, 450,
                    300, 350, 0, 250, 150, 220, 180, 500, 380, 460, 420, 0)
REVERSALS_PA = (350e3, 150e3, 300e3, 200e3, 500e3, 100e3, 250e3)


def scores(family: str, config: Config) -> dict[str, object]:
    return {kind: score(Scenario(family, kind), config) for kind in PATH_KINDS}


@pytest.fixture(scope='module', autouse=True)
def table():
    """Print what the tests below judge (so a failure shows the whole picture)."""
    lines = ['\nRMSE / max error, % of stroke, from the third reversal on (sigmoid branches)']
    # What the tests judge; bench_memory_families adds `identify` alone and the Hill form.
    for family, config in itertools.product(FAMILY_NAMES, (PAPER, *STATIC_RULES,
                                                           *LEARNED_RULES, MIXED)):
        cells = '   '.join(f'{kind} {s.rmse_pct:5.2f} / {s.max_pct:5.2f}'
                           for kind, s in scores(family, config).items())
        lines.append(f'  {family:10s} {config.label:22s} {cells}')
    print('\n'.join(lines))


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_the_default_memory_beats_the_papers_switch_in_rmse(family):
    ours, paper = scores(family, MIXED), scores(family, PAPER)
    for kind in PATH_KINDS:
        assert ours[kind].rmse_m <= 0.9 * paper[kind].rmse_m, kind


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_the_default_memorys_max_error_is_at_most_0_7_of_the_switch(family):
    # On the Duhem muscle (asymmetric) too since the knot at 75 kPa (2026-11-29): nested
    # 0.68x, random 0.59x (nested/seed 1 erred 0.70x before, at 25.7 s, early, while its
    # falling share was being learned). Its minor loops do not close: after a nest of small
    # loops inside a long fall it is millimetres longer than before the nest, and a model
    # with return-point memory (which the issue requires) comes back to its own length.
    # Over seeds 1-8 at 50 Hz the mix misses on 2 of its 16 runs (random/seeds 3 and 4),
    # both where even the muscle itself made to keep return-point memory errs over 0.7x the
    # switch's max (the oracle tests below; docs/model.md §3.1).
    ours, paper = scores(family, MIXED), scores(family, PAPER)
    for kind in PATH_KINDS:
        assert ours[kind].max_m <= 0.7 * paper[kind].max_m, kind


@pytest.mark.parametrize('family', ['narrow', 'wide', GENERALIZED_PLAY, FRICTION])
def test_the_return_point_oracle_is_the_muscle_itself_where_loops_close(family):
    # A yardstick for the muscles without the property only if exact on those with it.
    for kind in PATH_KINDS:
        scenario = Scenario(family, kind)
        gap = np.abs(return_point_oracle(scenario) - simulate(scenario).length_m)
        assert np.max(gap) < 1e-9, kind


@pytest.mark.parametrize('family', ['asymmetric', BOUC_WEN])
def test_the_muscles_without_return_point_memory_leave_their_oracle(family):
    # Seed 1, nested / random: asymmetric 2.7 / 3.5 mm, bouc-wen 0.8 / 0.9 mm.
    for kind in PATH_KINDS:
        scenario = Scenario(family, kind)
        gap = np.abs(return_point_oracle(scenario) - simulate(scenario).length_m)
        assert np.max(gap) > 0.0005, kind


def test_the_oracle_refuses_a_muscle_whose_state_depends_on_time():
    with pytest.raises(ValueError, match='rate-independent'):
        return_point_oracle(Scenario('creep'))
    with pytest.raises(ValueError, match='without drift'):
        return_point_oracle(Scenario('narrow', drift_start_s=60.0))


def test_the_noise_free_pressure_diagnosis_feeds_the_models_the_true_pressure():
    # bench_memory_families --noise-free-pressure: how much of a miss the pressure reading's
    # noise makes. At a hold the true pressure does not move, so neither may the switch's
    # prediction (it learns nothing); read from the sensor, it follows the noise.
    measured = Scenario('narrow', 'random', seed=1, duration_s=60.0, rate_hz=20.0)
    noise_free = Scenario('narrow', 'random', seed=1, duration_s=60.0, rate_hz=20.0,
                          noise_free_pressure=True)
    run = simulate(noise_free)
    held = np.flatnonzero(np.diff(run.pressure_pa) == 0.0) + 1   # same pressure as before
    assert held.size > 50
    for scenario, moves in ((noise_free, False), (measured, True)):
        steps = np.abs(np.diff(predict(scenario, PAPER)))[held - 1]
        assert (np.max(steps) > 1e-4) == moves, scenario.label


def test_a_duhem_variant_is_named_by_its_approach_scales():
    assert duhem_variant_scales_pa('duhem:30:60') == (30e3, 60e3)
    assert duhem_variant_scales_pa('asymmetric') is None
    for bad in ('duhem:30', 'duhem:a:b', 'duhem:0:60', 'duhem:30:60:90'):
        with pytest.raises(ValueError, match='duhem'):
            duhem_variant_scales_pa(bad)


def test_on_the_duhem_muscle_even_the_exact_muscle_with_return_point_memory_misses_the_max():
    # Why the mark above is expected to stay: on random/seed 3 the Duhem muscle, knowing its
    # own state at every turning point, errs 0.92x the switch's max (4.0 mm at t = 165.7 s),
    # only by keeping return-point memory, and the mix errs most (0.87x) at that moment.
    # Over seeds 1-8 three of the five runs that miss do so where the oracle misses too
    # (bench_memory_families.py --against-switch).
    scenario = Scenario('asymmetric', 'random', seed=3)
    paper = score(scenario, PAPER)
    assert oracle_score(scenario).max_m > 0.7 * paper.max_m
    assert oracle_error_near_m(scenario, worst_moment_s(scenario, MIXED)) > 0.7 * paper.max_m


@pytest.mark.parametrize(('family', 'at_most'), [
    ('asymmetric', 0.9), (BOUC_WEN, 0.85), ('narrow', 1.05), ('wide', 1.15), ('creep', 1.03)])
def test_the_local_offset_helps_where_loops_do_not_close_and_costs_little_where_they_do(
        family, at_most):
    # What the rules leave near the current pressure (pma_model.local_offset), RMSE with it
    # over without, seed 1 (nested, random; docs/model-history.md, "The mix's local offset"):
    # 0.77x, 0.85x on the Duhem muscle and 0.78x, 0.78x on Bouc-Wen, the two without
    # return-point memory; 0.97x, 1.02x on narrow, 0.95x, 1.00x on creep; wide pays most,
    # 1.00x, 1.12x (seeds 1-8: 1.03x).
    for kind in PATH_KINDS:
        scenario = Scenario(family, kind)
        ratio = score(scenario, MIXED).rmse_m / score(scenario, MIXED_WITHOUT_LOCAL_OFFSET).rmse_m
        assert ratio <= at_most, (kind, ratio)


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_the_default_memory_is_never_much_worse_than_the_best_fixed_rule(family):
    ours = scores(family, MIXED)
    for kind in PATH_KINDS:
        best = min(scores(family, config)[kind].rmse_m
                   for config in (PAPER, *STATIC_RULES, *LEARNED_RULES))
        assert ours[kind].rmse_m <= 1.1 * best, kind


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_the_moonshot_minor_loop_rmse_within_1_5_percent_of_stroke(family):
    for kind, result in scores(family, MIXED).items():
        assert result.rmse_pct <= 1.5, kind


@pytest.mark.parametrize(('parse', 'name', 'default', 'other', 'bad'), [
    (generalized_play_bulge, GENERALIZED_PLAY, DEFAULT_BULGE, 2.0, ('x', '-1', '11')),
    (friction_widest_band, FRICTION, DEFAULT_WIDEST_BAND, 0.4, ('x', '0', '1'))])
def test_a_parameterised_muscle_is_named_by_its_number(parse, name, default, other, bad):
    assert parse(name) == default
    assert parse(f'{name}:{other:g}') == other
    assert parse('wide') is None
    for text in bad:
        with pytest.raises(ValueError, match=name):
            parse(f'{name}:{text}')


def test_on_an_asymmetric_muscle_with_return_point_memory_the_default_meets_the_criteria():
    # The generalized Prandtl-Ishlinskii muscle (pma_sim.generalized_play): rising and falling
    # curves follow different envelopes, as on the Duhem muscle, but its loops close (the
    # oracle test above). Every criterion on seeds 1-2 and the switch criteria on all 48
    # runs of seeds 1-8 at 50 Hz with three asymmetry strengths (docs/model-history.md,
    # "Generalized Prandtl-Ishlinskii"): the Duhem muscle's misses come from its open loops,
    # not from its asymmetry.
    errors = table1_fit_errors_m(GENERALIZED_PLAY)
    assert np.sqrt(np.mean(errors ** 2)) < 0.0012   # Table 1 within the HC-SR04's accuracy
    ours, paper = scores(GENERALIZED_PLAY, MIXED), scores(GENERALIZED_PLAY, PAPER)
    for kind in PATH_KINDS:
        assert ours[kind].rmse_m <= 0.9 * paper[kind].rmse_m, kind
        assert ours[kind].max_m <= 0.7 * paper[kind].max_m, kind
        assert ours[kind].rmse_pct <= 1.5, kind


def test_on_a_tuning_set_muscle_with_a_late_sharp_onset_the_default_meets_the_switch_criteria():
    # pma_sim.friction: braid friction growing with the pressure. Fitted to Table 1 it
    # leaves its dead zone at 69 kPa with a kink, between Table 1's points at 50 and 100
    # kPa, where a correction following the sigmoid's shape from knot to knot missed it by
    # millimetres: at the driver's 20 Hz, seed 1, nested, 0.77x the switch's max before the
    # knot at 75 kPa (CORRECTION_KNOTS_PA), 0.67x with it (random: 0.67x, 0.51x). Seeds 1-8
    # at 20 Hz: 4 of 16 runs missed before, none with it (docs/model.md §5, "The knots").
    errors = table1_fit_errors_m(FRICTION)
    assert np.sqrt(np.mean(errors ** 2)) < 0.0012   # Table 1 within the HC-SR04's accuracy
    for kind in PATH_KINDS:
        scenario = Scenario(FRICTION, kind, seed=1, rate_hz=20.0)
        ours, paper = score(scenario, MIXED), score(scenario, PAPER)
        assert ours.rmse_m <= 0.9 * paper.rmse_m, kind
        assert ours.max_m <= 0.7 * paper.max_m, kind
        assert ours.rmse_pct <= 1.5, kind


SLOW_CREEP = 'creep:wide:0.3:1.5'   # the wide muscle, 30 % of each change lagged by 1.5 s


def test_on_a_tuning_set_muscle_that_creeps_slower_the_default_meets_the_criteria():
    # The creep: "length keeps moving for a second or two". The `creep` family lags
    # a quarter of each change by 0.6 s on the narrow muscle; this one lags more of it,
    # longer, on the wide muscle, between the model's two creep lags (0.5 and 2 s).
    # Seed 1, nested / random: RMSE 0.09x / 0.08x the switch, max 0.15x / 0.15x, 0.76x /
    # 0.78x the best fixed rule (docs/model-history.md, "Muscles that creep more slowly").
    ours, paper = scores(SLOW_CREEP, MIXED), scores(SLOW_CREEP, PAPER)
    for kind in PATH_KINDS:
        best = min(scores(SLOW_CREEP, config)[kind].rmse_m
                   for config in (PAPER, *STATIC_RULES, *LEARNED_RULES))
        assert ours[kind].rmse_m <= 0.9 * paper[kind].rmse_m, kind
        assert ours[kind].max_m <= 0.7 * paper[kind].max_m, kind
        assert ours[kind].rmse_m <= 1.1 * best, kind
        assert ours[kind].rmse_pct <= 1.5, kind


def test_a_creep_variant_is_named_by_its_family_share_and_lag():
    assert creep_variant(SLOW_CREEP) == ('wide', CreepParams(share=0.3, time_constant_s=1.5))
    assert creep_variant('creep') is None   # the scored family
    assert creep_variant('wide') is None
    assert rate_dependent(SLOW_CREEP) and rate_dependent('creep')
    assert not rate_dependent('wide')
    for bad in ('creep:', 'creep:creep:0.3:1', 'creep:wide:1.2:1', 'creep:wide:0.3',
                'creep:wide:0.3:0', 'creep:bouc-wen:0.3:1', 'creep:wide:nan:1'):
        with pytest.raises(ValueError, match='creep:INNER:SHARE:TAU'):
            creep_variant(bad)
    with pytest.raises(ValueError, match='rate-independent'):
        return_point_oracle(Scenario(SLOW_CREEP))


def test_on_a_tuning_set_bouc_wen_muscle_the_default_meets_the_switch_criteria():
    # The paper's comparison model fitted to Table 1 (pma_sim.evaluation.BOUC_WEN), no
    # return-point memory; scored beside the four from the start, so in the tuning set
    # (pma_sim.splits). bench_memory_families
    # adds the best-fixed-rule criterion and the second seed.
    assert bouc_wen_fit().loop_width_m > 0.003   # a muscle with hysteresis (4.0 mm)
    ours, paper = scores(BOUC_WEN, MIXED), scores(BOUC_WEN, PAPER)
    for kind in PATH_KINDS:
        assert ours[kind].rmse_m <= 0.9 * paper[kind].rmse_m, kind
        assert ours[kind].max_m <= 0.7 * paper[kind].max_m, kind
        assert ours[kind].rmse_pct <= 1.5, kind


@pytest.mark.parametrize('family', [*FAMILY_NAMES, BOUC_WEN, GENERALIZED_PLAY, SLOW_CREEP])
def test_at_the_drivers_default_20_hz_the_default_meets_the_switch_criteria(family):
    # driver_node asks for 20 Hz unless told otherwise (the firmware allows 50): 2.5x fewer
    # lengths to learn from. With a 4 mm prior on the branch correction (2 mm now) the
    # Duhem muscle missed the max here, nested and random 0.79x and 0.77x
    # (docs/model-history.md, "The branch correction's prior, 4 → 2 mm").
    for kind in PATH_KINDS:
        scenario = Scenario(family, kind, rate_hz=20.0)
        ours, paper = score(scenario, MIXED), score(scenario, PAPER)
        assert ours.rmse_m <= 0.9 * paper.rmse_m, kind
        assert ours.max_m <= 0.7 * paper.max_m, kind


@pytest.mark.parametrize('family', [*FAMILY_NAMES, BOUC_WEN])
def test_on_smooth_paths_the_default_meets_the_switch_criteria(family):
    # Paths the defaults were not chosen on: no holds, slowing into every reversal, where the
    # pressure reading's noise makes small false turns (pma_sim.paths.smooth_path).
    # Seeds 1-8, sigmoid: 80 of 80 runs meet both at 50 Hz, 79 of 80 at 20 Hz
    # (docs/model-history.md, "On smooth paths"). Seed 1's largest max: 0.51x the switch's
    # (narrow, sines).
    for kind in SMOOTH_KINDS:
        scenario = Scenario(family, kind)
        ours, paper = score(scenario, MIXED), score(scenario, PAPER)
        assert ours.rmse_m <= 0.9 * paper.rmse_m, kind
        assert ours.max_m <= 0.7 * paper.max_m, kind
        assert ours.rmse_pct <= 1.5, kind


@pytest.mark.parametrize('family', ['narrow', 'creep'])
def test_mixing_identify_with_play_follows_the_preisach_muscles_on_nested_paths(family):
    # Seed 2, where identify alone is 1.09x (narrow) and 1.13x (creep) the play rule's RMSE:
    # the play rule's rejoining of the major branch is outside identify's shapes.
    scenario = Scenario(family, 'nested', seed=2)
    mixed, paper = score(scenario, MIXED), score(scenario, PAPER)
    best = min(score(scenario, config).rmse_m
               for config in (PAPER, *STATIC_RULES, *LEARNED_RULES))
    assert mixed.rmse_m <= 1.1 * best
    assert mixed.max_m <= 0.7 * paper.max_m


def nested_path(step_pa: float = 1e3) -> np.ndarray:
    turns = np.array(NESTED_TURNS_KPA) * 1e3
    return np.concatenate([[turns[0]]] + [
        np.linspace(a, b, max(1, round(abs(b - a) / step_pa)) + 1)[1:]
        for a, b in itertools.pairwise(turns)])


def test_the_memory_removes_the_jump_at_reversals():
    # The paper's switch jumps by the loop width (~5 mm) when the detector flips; the
    # identify rule's scanning curves start where the length is, so one 1 kPa step moves
    # it by at most the branches' slope (~0.25 mm), whatever the shares.
    path = nested_path()
    branches = default_params().branches()
    jumps = {}
    for memory, shares in (('switch', (0.5, 0.5)), ('identify', (0.0, 1.0)),
                           ('identify', (1.0, 0.0)), ('identify', (0.5, 0.5))):
        model = HysteresisModel(*branches, memory=memory, play_shares=shares)
        jumps[memory, shares] = float(np.max(np.abs(np.diff(model.predict(path)))))
    assert jumps.pop(('switch', (0.5, 0.5))) > 4e-3
    assert max(jumps.values()) < 3e-4


def staircase_through_the_device(family: str, hold_ms: int = 1000, step_pa: float = 50e3):
    """(time, measured pressure, measured length, true length) per 50 Hz sample."""
    config = DeviceConfig(rate_hz=50, seed=5, muscle=family)
    device = SimDevice(config)
    decoder, sensor = protocol.FrameDecoder(), PressureCalibration()
    plan = plan_sweep(500e3, step_pa, hold_ms / 1000, 1, list(REVERSALS_PA), ceiling_pa=500e3)
    rows = []

    def run(ms: int) -> None:
        for t in range(ms):
            if t % 200 == 0:
                device.receive(protocol.encode_command(protocol.Command.HEARTBEAT))
            device.advance(1)
            for frame in decoder.feed(b''.join(device.take_output())):
                if isinstance(frame, protocol.Sample):
                    length = device.rig.range_sensor.echo_to_length_m(frame.echo_us)
                    rows.append((frame.t_ms / 1000.0, sensor.adc_to_pa(frame.adc), length,
                                 device.rig.length_m))

    for setpoint in plan.setpoints_pa:
        device.receive(protocol.encode_command(protocol.Command.SET, round(setpoint)))
        run(400 + hold_ms)
    return tuple(np.array(column) for column in zip(*rows, strict=True))


@pytest.mark.parametrize('family', FAMILY_NAMES)
def test_through_the_device_the_default_beats_the_switch_on_a_sweep_with_reversals(family):
    # The Sweep action's staircase, valves and 10-bit sensor included: the path a user
    # records for `refit --memory-check`. Short (about 50 s), so the learning has only begun.
    time_s, pressure, measured, truth = staircase_through_the_device(family)
    errors = {}
    for config in (PAPER, MIXED):
        online = config.params('sigmoid').build_online()
        errors[config.label] = run_online(online, pressure, measured, time_s) - truth
    rmse = {label: float(np.sqrt(np.mean(e ** 2))) for label, e in errors.items()}
    print(f'\n{family}: staircase through the device, RMSE mm: '
          + ', '.join(f'{label} {value * 1e3:.2f}' for label, value in rmse.items()))
    assert rmse[MIXED.label] < rmse[PAPER.label]
    assert muscle_family(family).rest_length_m == pytest.approx(truth[0], abs=2e-4)
