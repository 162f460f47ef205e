"""The simulated muscle: fit to the paper's Table 1 and the Preisach memory properties."""

import copy
import csv
import math
import time
from pathlib import Path

import numpy as np
import pytest

from pma_sim import muscle
from pma_sim.muscle import PreisachMuscle

pytestmark = pytest.mark.in_process

ROOT = Path(__file__).resolve().parents[2]
TABLE_CSVS = [ROOT / 'pma_model' / 'pma_model' / 'data' / 'paper_table1.csv',
              ROOT.parent / 'shared' / 'data' / 'paper_table1.csv']
KPA = 1000.0


def sweep(model: PreisachMuscle, start_pa: float, end_pa: float, step_pa: float = 1000.0):
    """Drive the pressure monotonically (1 kPa steps); return the length at every step."""
    count = max(1, round(abs(end_pa - start_pa) / step_pa))
    return [model.update(p) for p in np.linspace(start_pa, end_pa, count + 1)]


def test_embedded_table_matches_the_paper_csv():
    table = next((path for path in TABLE_CSVS if path.exists()), None)
    if table is None:
        pytest.skip('no copy of paper_table1.csv found')
    with table.open() as f:
        rows = list(csv.DictReader(f))
    assert [float(r['pressure_kpa']) * KPA for r in rows] == list(muscle.TABLE1_PRESSURE_PA)
    np.testing.assert_allclose([float(r['length_increasing_cm']) / 100 for r in rows],
                               muscle.TABLE1_LENGTH_INCREASING_M)
    np.testing.assert_allclose([float(r['length_decreasing_cm']) / 100 for r in rows],
                               muscle.TABLE1_LENGTH_DECREASING_M)


def test_major_loop_matches_table1_within_3_mm(capsys):
    model = PreisachMuscle()
    sweep(model, 0, 500 * KPA)
    sweep(model, 500 * KPA, 0)                       # preconditioning cycle
    up = sweep(model, 0, 500 * KPA)[::50]
    down = sweep(model, 500 * KPA, 0)[::-50]
    errors = np.concatenate([np.array(up) - muscle.TABLE1_LENGTH_INCREASING_M,
                             np.array(down) - muscle.TABLE1_LENGTH_DECREASING_M])
    rmse_cm = float(np.sqrt(np.mean(errors ** 2))) * 100
    with capsys.disabled():
        print(f'\nsimulated major loop vs Table 1: RMSE {rmse_cm:.3f} cm, '
              f'max {np.abs(errors).max() * 100:.3f} cm over {errors.size} points')
    assert np.abs(errors).max() < 0.003
    # The closed form used by the fit agrees with the stepped simulation.
    closed_up, closed_down = muscle.major_loop_m(muscle.TABLE1_FIT, muscle.TABLE1_PRESSURE_PA)
    np.testing.assert_allclose(closed_up, up, atol=1e-6)
    np.testing.assert_allclose(closed_down, down, atol=1e-6)


def test_dead_zone_below_50_kpa_and_a_real_loop_above():
    model = PreisachMuscle()
    rest = model.length_m
    up = sweep(model, 0, 45 * KPA)
    assert max(rest - length for length in up) < 0.0005     # < 0.5 mm: braid slack
    up_100 = sweep(model, 45 * KPA, 100 * KPA)[-1]
    sweep(model, 100 * KPA, 500 * KPA)
    down_100 = sweep(model, 500 * KPA, 100 * KPA)[-1]
    assert up_100 - down_100 > 0.003                         # the loop is open at 100 kPa


def test_a_deep_copy_carries_on_like_the_original_and_leaves_it_alone():
    # The return-point oracle of tests/support snapshots the muscle at every reversal.
    original = PreisachMuscle()
    for p in (0, 400e3, 100e3, 300e3, 200e3):
        original.update(p)
    snapshot = copy.deepcopy(original)
    path = (250e3, 150e3, 450e3, 50e3, 350e3)
    ahead = [original.update(p) for p in path]
    assert [snapshot.update(p) for p in path] == ahead
    assert snapshot.turning_points_pa() == original.turning_points_pa()
    snapshot.update(0.0)
    assert original.turning_points_pa() != snapshot.turning_points_pa()
    assert original.length_m == ahead[-1]


def test_minor_loop_closes_return_point_memory():
    model = PreisachMuscle()
    at_300 = sweep(model, 0, 300 * KPA)[-1]
    at_150 = sweep(model, 300 * KPA, 150 * KPA)[-1]
    back_at_300 = sweep(model, 150 * KPA, 300 * KPA)[-1]
    assert at_150 > at_300 + 0.005                           # it really moved
    assert back_at_300 == pytest.approx(at_300, abs=1e-9)


def test_wiping_out_returns_to_the_major_branch():
    reference = PreisachMuscle()
    on_major = sweep(reference, 0, 400 * KPA)[-1]
    model = PreisachMuscle()
    sweep(model, 0, 300 * KPA)
    sweep(model, 300 * KPA, 150 * KPA)
    sweep(model, 150 * KPA, 250 * KPA)
    sweep(model, 250 * KPA, 200 * KPA)
    assert len(model.turning_points_pa()) == 3                # 300, 150, 250 kPa
    at_400 = sweep(model, 200 * KPA, 400 * KPA)[-1]
    assert model.turning_points_pa() == []                   # the minor loops are forgotten
    assert at_400 == pytest.approx(on_major, abs=1e-9)


def test_no_drift_over_30_minor_cycles():
    model = PreisachMuscle()
    sweep(model, 0, 500 * KPA)
    sweep(model, 500 * KPA, 200 * KPA)
    first = model.length_m
    for _ in range(30):
        sweep(model, 200 * KPA, 350 * KPA, 7000)
        sweep(model, 350 * KPA, 200 * KPA, 7000)
    assert model.length_m == pytest.approx(first, abs=1e-9)
    assert len(model.turning_points_pa()) <= 3               # memory does not grow


def test_loop_is_rate_independent_and_length_stays_physical():
    coarse, fine = PreisachMuscle(), PreisachMuscle()
    previous = 0.0
    for target in np.random.default_rng(3).uniform(0, 600 * KPA, 40):
        a = sweep(coarse, previous, target, 25_000)
        b = sweep(fine, previous, target, 500)
        previous = target
        assert a[-1] == pytest.approx(b[-1], abs=1e-9)
        assert min(b) > 0.239 and max(b) <= 0.3007


def test_runs_well_above_1_khz():
    model = PreisachMuscle()
    pressures = 250 * KPA + 200 * KPA * np.sin(np.linspace(0, 20 * math.pi, 5000))
    start = time.perf_counter()
    for p in pressures:
        model.update(float(p))
    per_step = (time.perf_counter() - start) / len(pressures)
    assert per_step < 100e-6, f'{per_step * 1e6:.1f} us per step'
