"""The simulated muscle families: each fits Table 1, each behaves differently inside the loop.

docs/simulated-rig.md, "Muscle families". The fits are package data (pma_sim/family_fits.py,
written by `python -m pma_sim.fit_families --write`); these tests check the shipped
numbers, they do not refit.
"""

import itertools
import re

import numpy as np
import pytest

from pma_sim import families, family_fits, fit_families, paths
from pma_sim.device import DeviceConfig, Rig
from pma_sim.families import CreepMuscle, DriftingMuscle, DriftSpec
from pma_sim.registry import FAMILY_NAMES, muscle_family, muscle_from_spec

KPA = 1000.0
RATE_INDEPENDENT = ('narrow', 'wide', 'asymmetric')


def sweep(muscle, start_kpa, end_kpa, step_kpa=1.0, t_s=0.0):
    """Drive the pressure monotonically; the length at every step (time does not move)."""
    count = max(1, round(abs(end_kpa - start_kpa) / step_kpa))
    return [muscle.update(p * KPA, t_s) for p in np.linspace(start_kpa, end_kpa, count + 1)]


@pytest.mark.parametrize('name', FAMILY_NAMES)
def test_every_family_reproduces_table1_within_the_sensor_accuracy(name, capsys):
    errors = fit_families.loop_errors_m(name)
    rmse = float(np.sqrt(np.mean(errors ** 2)))
    with capsys.disabled():
        print(f'\n{name}: steady major loop vs Table 1: RMSE {rmse * 100:.3f} cm, '
              f'max {np.abs(errors).max() * 100:.3f} cm')
    assert rmse < 0.0015                      # the HC-SR04 is good to ~3 mm
    assert np.abs(errors).max() < 0.003


def test_the_documented_fits_are_those_of_the_shipped_constants():
    text = (fit_families.OUTPUT).read_text()
    for name in ('narrow', 'wide', 'asymmetric'):
        documented = re.search(rf'- {name}: RMSE ([0-9.]+) cm, max ([0-9.]+) cm', text)
        errors = fit_families.loop_errors_m(name)
        assert float(documented.group(1)) == pytest.approx(
            np.sqrt(np.mean(errors ** 2)) * 100, abs=5e-4)
        assert float(documented.group(2)) == pytest.approx(np.abs(errors).max() * 100,
                                                           abs=5e-4)
    assert family_fits.CREEP == fit_families.CREEP


def after_a_reversal(name, reversal_kpa, rising, travel_kpa):
    """(lengths along travel_kpa after a reversal at reversal_kpa, the other major branch
    there), 1 kPa apart: falling after a rise from rest, or rising after a fall from the top."""
    muscle, other = muscle_family(name), muscle_family(name)
    if rising:
        sweep(muscle, 0, 500)
        sweep(muscle, 500, reversal_kpa)
        sweep(other, 0, reversal_kpa)
    else:
        sweep(muscle, 0, reversal_kpa)
        sweep(other, 0, 500)
        sweep(other, 500, reversal_kpa)
    end = reversal_kpa + (travel_kpa if rising else -travel_kpa)
    return np.array(sweep(muscle, reversal_kpa, end)), np.array(sweep(other, reversal_kpa, end))


def test_the_families_differ_after_a_reversal():
    """The major loop cannot tell them apart; after a reversal they differ."""
    start_rate, gap_left = {}, {}
    for name in RATE_INDEPENDENT:
        for rising in (True, False):
            scan, other = after_a_reversal(name, 250, rising, 100)
            # how fast the length leaves the reversal, relative to the other branch
            start_rate[name, rising] = (scan[20] - scan[0]) / (other[20] - other[0])
            # how much of the gap to the other branch is left 80 kPa on
            gap_left[name, rising] = (scan[80] - other[80]) / (scan[0] - other[0])
    print({key: round(value, 2) for key, value in start_rate.items()},
          {key: round(value, 2) for key, value in gap_left.items()})
    for rising in (True, False):
        assert gap_left['narrow', rising] < 0.1     # narrow relays: back on the branch
        assert gap_left['wide', rising] > 0.3       # wide plays: the scan spans the excursion
    # asymmetric: holds on the way up, moves at once on the way down
    assert start_rate['asymmetric', True] < 0.3
    assert start_rate['asymmetric', False] > 0.6


@pytest.mark.parametrize('name', ('narrow', 'wide'))
def test_return_point_memory_and_wiping_out(name):
    muscle = muscle_family(name)
    at_300 = sweep(muscle, 0, 300)[-1]
    sweep(muscle, 300, 150)
    assert sweep(muscle, 150, 300)[-1] == pytest.approx(at_300, abs=1e-9)
    on_major = sweep(muscle_family(name), 0, 400)[-1]
    assert sweep(muscle, 300, 400)[-1] == pytest.approx(on_major, abs=1e-9)


def test_asymmetric_minor_loops_close_nearly_and_settle():
    # A Duhem muscle has no exact return-point memory: the first loop leaves a small gap,
    # repeated loops settle on a limit cycle instead of drifting away.
    muscle = muscle_family('asymmetric')
    at_300 = sweep(muscle, 0, 300)[-1]
    ends = []
    for _ in range(10):
        sweep(muscle, 300, 150)
        ends.append(sweep(muscle, 150, 300)[-1])
    assert abs(ends[0] - at_300) < 0.001
    assert abs(ends[-1] - ends[-2]) < 1e-5


@pytest.mark.parametrize('name', RATE_INDEPENDENT)
def test_rate_independent_families_ignore_step_size_and_time(name):
    coarse, fine = muscle_family(name), muscle_family(name)
    previous = 0.0
    for k, target in enumerate(np.random.default_rng(3).uniform(0, 500, 25)):
        a = sweep(coarse, previous, target, 25.0, t_s=k)
        b = sweep(fine, previous, target, 0.5, t_s=10.0 * k)
        previous = target
        assert a[-1] == pytest.approx(b[-1], abs=2e-5 if name == 'asymmetric' else 1e-9)
        assert 0.239 < min(b) and max(b) < 0.303


def test_creep_keeps_moving_for_a_second_or_two_after_a_step():
    muscle = muscle_family('creep')
    static = muscle_family('narrow')
    t = 0.0
    muscle.update(0.0, t)
    lengths = {}
    for t_ms in range(0, 6001, 10):   # a step to 300 kPa at t = 0, then a hold
        t = t_ms / 1000.0
        lengths[t_ms] = muscle.update(300 * KPA, t)
    target = static.update(300 * KPA)
    step = lengths[0] - muscle.rest_length_m
    assert lengths[0] - target > 0.15 * (muscle.rest_length_m - target)   # not all at once
    assert lengths[1000] - target > 0.1 * (lengths[0] - target)             # still moving at 1 s
    assert abs(lengths[6000] - target) < 1e-4                               # settled
    assert step < 0
    with pytest.raises(ValueError, match='time went back'):
        muscle.update(300 * KPA, 1.0)


def test_drift_moves_rest_length_and_stroke_over_its_time_constant():
    spec = DriftSpec(shift_m=0.0015, gain=1.08, time_constant_s=30.0, start_s=10.0)
    drifting, plain = muscle_from_spec('narrow+drift'), muscle_family('narrow')
    assert isinstance(drifting, DriftingMuscle) and drifting.drift == DriftSpec()
    drifting = muscle_family('narrow', spec)
    rest = plain.rest_length_m
    for t in (0.0, 5.0):
        assert drifting.update(200 * KPA, t) == pytest.approx(plain.update(200 * KPA, t))
    late = drifting.update(200 * KPA, 10.0 + 300.0)
    assert late == pytest.approx(rest + 0.0015 + 1.08 * (plain.update(200 * KPA) - rest),
                                 abs=1e-7)
    with pytest.raises(ValueError, match='gain'):
        DriftSpec(gain=5.0)


def test_registry_names_every_family_and_refuses_others():
    for name in FAMILY_NAMES:
        muscle = muscle_from_spec(name)
        assert muscle.length_m == pytest.approx(muscle.rest_length_m)
    assert isinstance(muscle_family('creep'), CreepMuscle)
    with pytest.raises(ValueError, match='narrow, wide, asymmetric, creep'):
        muscle_from_spec('cubic')
    with pytest.raises(ValueError, match='unknown muscle family'):
        DeviceConfig(muscle='wide+drfit')
    rig = Rig(DeviceConfig(muscle='wide+drift'))
    assert isinstance(rig.muscle, DriftingMuscle)
    assert isinstance(rig.muscle.inner, families.PlayMuscle)


def test_paths_visit_their_turning_points_and_the_sensors_are_the_rigs():
    turns = paths.random_turns(60, seed=2)
    path = paths.ramp_path(turns, seed=2)
    assert path.time_s[-1] > 50
    for turn in turns:
        assert np.min(np.abs(path.pressure_pa - turn)) < 1e-6
    assert len(path.reversal_times_s) == len(turns) - 2
    run = paths.simulate(muscle_family('wide'), path, seed=2)
    noise_m = np.nanstd(run.measured_length_m - run.length_m)
    noise_pa = np.std(run.measured_pressure_pa - run.pressure_pa)
    assert 0.0012 < noise_m < 0.0025          # HC-SR04: 1.5 mm noise, 3 mm steps
    assert 800 < noise_pa < 2000              # mean of 4 conversions of 2.5 kPa each
    nested = paths.nested_turns(120, seed=1)
    # nested groups: each turn lies between the two before it
    inside = sum(min(a, b) < c < max(a, b) for a, b, c in zip(nested, nested[1:], nested[2:],
                                                              strict=False))
    assert inside > len(nested) / 2


@pytest.mark.parametrize('kind', paths.SMOOTH_KINDS)
def test_smooth_paths_start_at_rest_reverse_at_their_extrema_and_keep_to_the_valves_pace(kind):
    path = paths.smooth_path(kind, 120, seed=3, rate_hz=20)
    pressure = path.pressure_pa
    assert pressure.size == 2400 and pressure[0] == 0.0
    assert 0.0 <= pressure.min() and pressure.max() <= paths.TOP_PA
    assert np.max(np.abs(np.diff(pressure))) * 20 <= paths.MAX_SLEW_PA_PER_S + 1e-6
    assert np.count_nonzero(np.diff(pressure) == 0.0) < 5   # no holds
    reversals = np.round(path.reversal_times_s * 20).astype(int)
    assert reversals.size > 30
    steps = np.diff(pressure)
    for index in reversals:   # the pressure arrives at an extremum and turns back there
        arriving = steps[index - 1]
        leaving = steps[index:][steps[index:] != 0.0][0]
        assert arriving != 0.0 and np.sign(leaving) == -np.sign(arriving)
    for start, end in itertools.pairwise(reversals):   # no turn in between
        between = steps[start:end]
        assert np.all(between <= 0.0) or np.all(between >= 0.0)
    with pytest.raises(ValueError, match='sines, damped'):
        paths.smooth_path('square')


def test_fake_arduino_runs_the_chosen_family(procs):
    proc = procs.ros2_run('pma_sim', 'fake_arduino', '--muscle', 'asymmetric+drift',
                          '--log-level', 'INFO')
    proc.wait_for_line(lambda text: 'muscle asymmetric+drift' in text, timeout=20)
    bad = procs.ros2_run('pma_sim', 'fake_arduino', '--muscle', 'preisach2')
    bad.wait_for_line("unknown muscle family 'preisach2'", timeout=20)
    assert bad.popen.wait(timeout=20) == 2
