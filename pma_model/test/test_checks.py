"""refit checks what it fits (pma_model.offline.checks, issue 46): a sweep started pressurised, a
missing top, too few levels, L0 against the rest length, the sweep's own `settled` verdicts;
the console summary, --strict and the params file's warning header."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from test_samples import TRUE_DECREASING, TRUE_INCREASING, write_state_bag

from pma_model.detector import BRANCH_INCREASING, detect_branches
from pma_model.offline import checks
from pma_model.offline.samples import Samples, hold_runs, read_bag, split_branches
from pma_model.params import ModelParams

pytestmark = pytest.mark.in_process

RATE_HZ = 20.0
DEADBAND_PA = 30_000.0


def sweep(levels_kpa, *, start_kpa=0.0, hold_s=2.0, noise_m=1.5e-3, seed=1, lead_s=0.0):
    """(t, pressure, setpoint, length) of a staircase through `levels_kpa` from a muscle at
    `start_kpa` (first-order regulation, tau 0.15 s) on the known loop, with sensor noise;
    `lead_s` of samples at the start pressure (setpoint too) before the first level."""
    rng = np.random.default_rng(seed)
    per = int(hold_s * RATE_HZ)
    lead = int(lead_s * RATE_HZ)
    setpoint = np.concatenate([np.full(lead, start_kpa * 1e3),
                               np.repeat(np.asarray(levels_kpa, float) * 1e3, per)])
    t = np.arange(setpoint.size) / RATE_HZ
    pressure = np.empty_like(setpoint)
    value = start_kpa * 1e3
    for i, target in enumerate(setpoint):
        value += (target - value) * (1 - math.exp(-1 / (RATE_HZ * 0.15)))
        pressure[i] = value
    rising = detect_branches(pressure, 20_000.0) == BRANCH_INCREASING
    length = np.where(rising, TRUE_INCREASING.length(pressure), TRUE_DECREASING.length(pressure))
    return t, pressure, setpoint, length + rng.normal(0, noise_m, length.size)


MAJOR = [*range(0, 501, 100), *range(400, -1, -100)]


def samples_of(t, pressure, setpoint, length) -> Samples:
    return Samples(t, pressure, length, setpoint, source='synthetic')


def run_checks(samples: Samples, l0_m=None, k_branch=None, records=None, start=None):
    """What refit's checks say of these samples, with the paper's fixed L0 (the length at
    the lowest increasing level) unless `l0_m` is given."""
    data = split_branches(samples, DEADBAND_PA, True)
    runs = hold_runs(samples.setpoint_pa)
    noise = checks.noise_estimate(samples.length_m, runs)
    if records:
        levels = checks.levels_from_records(records, samples.time_s, samples.pressure_pa,
                                            samples.length_m, time_origin_s=0.0,
                                            deadband_pa=DEADBAND_PA)
    else:
        levels = checks.derive_levels(samples.time_s, samples.pressure_pa, samples.length_m,
                                      setpoint_pa=samples.setpoint_pa, runs=runs,
                                      deadband_pa=DEADBAND_PA)
    fit = checks.FitView(data.inc_pressure_pa, data.dec_pressure_pa,
                         {'sigmoid_fixed_c': data.rest_length_m if l0_m is None else l0_m},
                         k_branch or {'sigmoid_fixed_c': 2})
    return checks.check(fit, levels, deadband_pa=DEADBAND_PA, noise=noise,
                        rest=checks.rest_lengths(levels), start=start,
                        first_pressure_pa=float(samples.pressure_pa[0]),
                        from_records=bool(records)), levels, data


def names(found):
    return sorted(warning.check for warning in found)


def test_a_sweep_from_rest_passes_every_check():
    found, levels, data = run_checks(samples_of(*sweep(MAJOR)))
    assert found == []
    assert (data.inc_pressure_pa.size, data.dec_pressure_pa.size) == (6, 5)
    assert [level.fit_branch for level in levels] == [1] * 6 + [-1] * 5
    assert checks.intended_branches(levels) == [1] * 6 + [-1] * 5


def test_a_sweep_started_pressurised_is_caught_four_ways():
    """The issue's sweep: the muscle at 200 kPa, so the 0 kPa level lands on the decreasing
    branch (5 rising + 6 falling levels) and the paper's L0 is the length at 100 kPa."""
    found, levels, data = run_checks(samples_of(*sweep(MAJOR, start_kpa=200, lead_s=0.5)))
    assert (data.inc_pressure_pa.size, data.dec_pressure_pa.size) == (6, 6)  # + the lead
    assert names(found) == ['rest_length', 'rest_level_missing', 'started_pressurised',
                            'wrong_branch']
    wrong = next(w for w in found if w.check == 'wrong_branch')
    zero = levels[wrong.level]
    assert zero.target_pa == 0 and zero.approach == checks.FALLING
    assert zero.fit_branch == checks.FALLING
    assert 'reached from above (from 200 kPa)' in wrong.message
    assert 'belongs on the increasing branch' in wrong.message
    rest = next(w for w in found if w.check == 'rest_length')
    assert 'sigmoid_fixed_c 29.0' in rest.message and '30.0' in rest.message  # 100 kPa vs rest


def test_without_a_lead_the_recording_itself_starts_pressurised():
    found, _, data = run_checks(samples_of(*sweep(MAJOR, start_kpa=200)))
    assert (data.inc_pressure_pa.size, data.dec_pressure_pa.size) == (5, 6)
    assert 'started_pressurised' in names(found) and 'wrong_branch' in names(found)


def test_a_falling_branch_without_its_top():
    levels = [*range(0, 501, 50), 200, 150, 100, 50, 0]
    found, _, _ = run_checks(samples_of(*sweep(levels)))
    assert names(found) == ['top_level_missing']
    assert 'highest is 200 kPa' in found[0].message


def test_fewer_levels_than_parameters():
    """6 increasing and 5 decreasing levels: 5 parameters are too many for the second,
    6 for both."""
    found, _, _ = run_checks(samples_of(*sweep(MAJOR)),
                             k_branch={'sigmoid_fixed_c': 2, 'hill': 4, 'five': 5})
    assert names(found) == ['too_few_levels']
    assert 'the decreasing branch has 5 pressure levels' in found[0].message
    assert 'of five (5):' in found[0].message
    found, _, _ = run_checks(samples_of(*sweep(MAJOR)), k_branch={'six': 6, 'five': 5})
    assert [w.message.split(' has ')[0] for w in found] == ['the increasing branch',
                                                            'the decreasing branch']


@pytest.mark.parametrize(('offset_m', 'warned'), [(0.002, False), (-0.003, False),
                                                  (0.006, True), (-0.0085, True)])
def test_l0_against_the_rest_length_within_the_sensor_noise(offset_m, warned):
    """3 sigma of 1.5 mm noise is 4.5 mm: 2-3 mm off is noise, 6 mm and the issue's 8.5 mm
    are not."""
    t, pressure, setpoint, length = sweep(MAJOR)
    rest = float(np.mean(length[int(RATE_HZ):int(2 * RATE_HZ)]))
    found, _, _ = run_checks(samples_of(t, pressure, setpoint, length), l0_m=rest + offset_m)
    assert ('rest_length' in names(found)) is warned


def test_noise_estimate_from_quantised_readings():
    """HC-SR04-like readings: 1.5 mm noise on a 3 mm grid; the tolerance is 3 sigma."""
    rng = np.random.default_rng(3)
    length = np.round((0.3 + rng.normal(0, 0.0015, 400)) / 0.003) * 0.003
    noise = checks.noise_estimate(length, [(0, 200), (200, 400)])
    assert noise['step_cm'] == pytest.approx(0.3)
    assert 0.12 < noise['sigma_cm'] < 0.2
    assert noise['tolerance_cm'] == pytest.approx(max(3 * noise['sigma_cm'], 0.3))
    nominal = checks.noise_estimate(np.empty(0), [])
    assert nominal['tolerance_cm'] == pytest.approx(0.45) and 'nominal' in nominal['from']


def test_intended_branches_follow_reversals():
    def level(i, kpa):
        return checks.Level(i, kpa * 1e3, kpa * 1e3, math.nan, 0.3, checks.NONE, None)

    path = [0, 100, 300, 150, 500, 200, 350, 0]
    assert checks.intended_branches([level(i, p) for i, p in enumerate(path)]) == \
        [1, 1, 1, -1, 1, -1, 1, -1]


def records_for(t, setpoint, pressure, *, unsettled=(), first_branch=0):
    """LEVEL records as the driver publishes them, one per hold of the setpoint."""
    runs = hold_runs(setpoint)
    found = []
    for index, (start, end) in enumerate(runs):
        previous = setpoint[runs[index - 1][0]] if index else None
        branch = first_branch if previous is None else (1 if setpoint[start] > previous else -1)
        found.append(checks.SweepLevelRecord(
            index, len(runs), float(setpoint[start]), float(np.mean(pressure[start:end])),
            branch, index not in unsettled, float(t[start]), float(t[end - 1]),
            'not within tolerance' if index in unsettled else ''))
    return found


def test_records_give_the_levels_and_their_settled_verdicts():
    t, pressure, setpoint, length = sweep(MAJOR)
    records = records_for(t, setpoint, pressure, unsettled={3})
    found, levels, _ = run_checks(samples_of(t, pressure, setpoint, length), records=records)
    assert names(found) == ['not_settled']
    assert found[0].level == 3 and '300 kPa' in found[0].message
    assert 'not within tolerance' in found[0].message
    assert [level.settled for level in levels].count(False) == 1


def test_records_of_a_pressurised_start():
    t, pressure, setpoint, length = sweep(MAJOR, start_kpa=200)
    records = records_for(t, setpoint, pressure, first_branch=-1)
    found, _, _ = run_checks(samples_of(t, pressure, setpoint, length), records=records,
                             start=checks.SweepStartRecord(False, 200_000.0))
    assert names(found) == ['rest_length', 'rest_level_missing', 'started_pressurised',
                            'wrong_branch']
    assert 'sweep started pressurised, at 200 kPa' in \
        next(w for w in found if w.check == 'started_pressurised').message


def write_records(bag, records, start, start_s=1_700_000_000.0):
    """Append the sweep's records to a bag written by write_state_bag: a second bag is
    simpler, so the state bag is rewritten with both topics."""
    from rclpy.serialization import serialize_message

    from pma_interfaces.msg import SweepRecord

    messages = []
    head = SweepRecord(kind=SweepRecord.KIND_START, sweep_id='ab' * 16, profile='staircase',
                       started_at_rest=start.started_at_rest,
                       start_gauge_pressure_pa=start.start_pa)
    messages.append(head)
    for record in records:
        message = SweepRecord(kind=SweepRecord.KIND_LEVEL, sweep_id='ab' * 16,
                              profile='staircase', level_index=record.level_index,
                              level_count=record.level_count,
                              target_gauge_pressure_pa=record.target_pa,
                              reached_gauge_pressure_pa=record.reached_pa,
                              branch=record.branch, settled=record.settled,
                              message=record.message)
        for field, seconds in (('hold_start', record.hold_start_s),
                               ('hold_end', record.hold_end_s)):
            stamp = getattr(message, field)
            stamp.sec, stamp.nanosec = divmod(round((start_s + seconds) * 1e9), 10**9)
        messages.append(message)
    return [serialize_message(message) for message in messages]


def test_a_bag_with_sweep_records_is_read_and_checked(tmp_path):
    """read_bag takes pma/sweep_record beside pma/state; refit's checks then use them."""
    from pma_bag import BagReader, BagWriter
    from pma_model.offline.report import data_checks

    t, pressure, setpoint, length = sweep(MAJOR)
    records = records_for(t, setpoint, pressure, unsettled={7})
    plain = write_state_bag(tmp_path / 'plain', t, pressure, setpoint, length)
    payloads = write_records(plain, records, checks.SweepStartRecord(True, 0.0))
    bag = tmp_path / 'with_records'
    with BagReader(plain) as reader, BagWriter(bag) as writer:
        writer.add_topic('/pma/state', 'pma_interfaces/msg/PmaState')
        writer.add_topic('/pma/sweep_record', 'pma_interfaces/msg/SweepRecord')
        for message in reader.messages():
            writer.write('/pma/state', message.data, message.log_time_ns)
        last = message.log_time_ns
        for data in payloads:
            writer.write('/pma/sweep_record', data, last)
    samples = read_bag(bag, progress=False)
    assert len(samples.sweep_levels) == len(records) and samples.sweep_start.started_at_rest
    assert samples.sweep_levels[7].settled is False
    assert samples.time_origin_s == pytest.approx(1_700_000_000.0)
    assert read_bag(plain, progress=False).sweep_levels is None
    data = split_branches(samples, DEADBAND_PA, True)
    from pma_model.offline.report import fit_model
    fitted = {'sigmoid_fixed_c': fit_model('sigmoid_fixed_c', data)}
    report = data_checks(data, samples, fitted, DEADBAND_PA)
    assert report['levels_from'].startswith("the sweep's records")
    assert [w['check'] for w in report['warnings']] == ['not_settled']
    assert report['levels'][7]['settled'] is False
    assert report['skipped'] == []
    derived = data_checks(data, read_bag(plain, progress=False), fitted, DEADBAND_PA)
    assert derived['warnings'] == [] and any('not_settled' in s for s in derived['skipped'])


# --- refit itself (in this process: main(argv)) ---------------------------------------------

@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    out = tmp_path_factory.mktemp('checks_bags')
    return {'rest': write_state_bag(out / 'rest', *sweep(MAJOR)),
            'pressurised': write_state_bag(out / 'pressurised', *sweep(MAJOR, start_kpa=200))}


def refit(capsys, *args):
    from pma_model.offline.refit import main

    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_strict_refuses_a_pressurised_sweep(bags, tmp_path, capsys):
    from pma_model.offline.refit import EXIT_STRICT

    code, out, err = refit(capsys, bags['pressurised'], '--no-holdout', '--strict',
                           '--json', tmp_path / 'r.json', '--params-out', tmp_path / 'p.yaml')
    assert code == EXIT_STRICT == 3, out + err
    assert not (tmp_path / 'p.yaml').exists()
    assert f'--strict: 4 data warnings (above); {tmp_path / "p.yaml"} not written' in err
    assert 'data checks: 4 WARNINGS' in out and '! wrong_branch: level 1 (0 kPa)' in out
    import json
    report = json.loads((tmp_path / 'r.json').read_text())
    assert [w['check'] for w in report['data_checks']['warnings']] == [
        'rest_level_missing', 'started_pressurised', 'wrong_branch', 'rest_length']


def test_without_strict_the_params_file_says_so_and_still_loads(bags, tmp_path, capsys):
    code, out, _ = refit(capsys, bags['pressurised'], '--no-holdout',
                         '--params-out', tmp_path / 'p.yaml')
    assert code == 0
    assert 'marked: fitted to data with 4 warnings' in out
    text = (tmp_path / 'p.yaml').read_text()
    assert text.startswith('# WARNING: refit warned about the data this model was fitted to')
    assert '#   - wrong_branch: level 1 (0 kPa)' in text
    ModelParams.load_yaml(tmp_path / 'p.yaml')       # model_node's own loader takes it
    assert '/**' in yaml.safe_load(text)


def test_a_sweep_from_rest_is_quiet_and_short(bags, tmp_path, capsys):
    code, out, err = refit(capsys, bags['rest'], '--no-holdout', '--strict',
                           '--params-out', tmp_path / 'p.yaml', '--plots', tmp_path / 'plots')
    assert code == 0, out + err
    assert 'data checks: no warnings' in out
    assert not (tmp_path / 'p.yaml').read_text().startswith('# WARNING')
    assert len(out.splitlines()) <= 30, out
    assert 'is poorly identified' not in out and 'whole loop' not in out
    assert len(err.splitlines()) == 1 and err.startswith('fitting sigmoid_fixed_c ...')
    code, verbose, _ = refit(capsys, bags['rest'], '--no-holdout', '--verbose')
    assert 'whole loop' in verbose and 'is poorly identified' in verbose
    assert 'data checks: no warnings' in verbose


def test_strict_counts_a_truncated_bag(tmp_path, capsys):
    """A bag cut short (its recorder killed) is refitted on what it holds, with a warning;
    --strict makes that warning an error too."""
    from pma_model.offline.refit import EXIT_STRICT

    bag = write_state_bag(tmp_path / 'crashed', *sweep(MAJOR))
    mcap = bag / 'crashed_0.mcap'
    mcap.write_bytes(mcap.read_bytes()[:int(mcap.stat().st_size * 0.9)])   # no summary
    code, out, err = refit(capsys, bag, '--no-holdout', '--strict',
                           '--params-out', tmp_path / 'p.yaml')
    assert code == EXIT_STRICT, out + err
    assert 'is truncated (' in err and '--strict: 1 data warning (above)' in err
    assert not (tmp_path / 'p.yaml').exists()
