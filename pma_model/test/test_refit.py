"""`ros2 run pma_model refit` as a real process: the paper's table, a sweep bag, bad input."""

import itertools
import json
import os
import subprocess
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_samples import (
    TRUE_DECREASING,
    TRUE_INCREASING,
    staircase,
    write_sample_log,
    write_state_bag,
)

from pma_common.commands import run_command
from pma_model import units
from pma_model.params import ModelParams

PAPER_TABLE = resources.files('pma_model').joinpath('data', 'paper_table1.csv')
REFIT = Path(__file__).resolve().parents[2] / 'ros2_ws' / 'install' / 'pma_model' / 'lib' / \
    'pma_model' / 'refit'
MODELS = {'sigmoid_fixed_c', 'sigmoid_free_c', 'hill', 'bouc_wen', 'bouc_wen_nonlinear'}
METRIC_KEYS = {'mae_cm', 'mse_cm2', 'rmse_cm', 'max_cm', 'r2', 'r', 'aic', 'aicc', 'bic', 'n',
               'k'}


def run_refit(procs, *args, timeout=150):
    proc = procs.ros2_run('pma_model', 'refit', *[str(a) for a in args])
    code = proc.popen.wait(timeout)
    proc.stop()  # already exited: this only joins the output reader
    return code, proc.output


@pytest.fixture(scope='module')
def table_run(tmp_path_factory, module_procs):
    out = tmp_path_factory.mktemp('refit_table')
    code, output = run_refit(module_procs, PAPER_TABLE, '--json', out / 'report.json',
                             '--params-out', out / 'params.yaml', '--plots', out / 'plots')
    assert code == 0, output
    return out, json.loads((out / 'report.json').read_text()), output


def test_json_shape_and_the_papers_numbers(table_run):
    _, report, _ = table_run
    for direction in ('increasing', 'decreasing'):
        models = report['branches'][direction]['models']
        assert set(models) == MODELS
        for entry in models.values():
            assert METRIC_KEYS <= set(entry['metrics'])
            assert entry['params'] and 'stderr' in entry
    paper = report['branches']['increasing']['models']['sigmoid_fixed_c']
    assert {'a', 'b_per_kpa', 'c', 'l0_cm'} <= set(paper['params'])
    assert round(paper['params']['a'], 5) == 0.19073
    assert round(paper['params']['b_per_kpa'], 6) == 0.011333
    assert paper['params']['l0_cm'] == pytest.approx(30.06)
    assert paper['params']['c'] == 6.214 and set(paper['stderr']) == {'a', 'b_per_kpa'}
    metrics = paper['metrics']
    assert (round(metrics['mae_cm'], 4), round(metrics['r2'], 4), round(metrics['r'], 4)) == \
        (0.1664, 0.9912, 0.9960)
    assert (round(metrics['aic'], 3), round(metrics['bic'], 3)) == (-31.563, -30.767)
    assert round(metrics['mse_cm2'], 4) == 0.0394
    decreasing = report['branches']['decreasing']['models']['sigmoid_fixed_c']['params']
    assert round(decreasing['a'], 4) == 0.1879 and round(decreasing['b_per_kpa'], 5) == 0.01305


def test_other_models_land_on_the_reference_figures(table_run):
    _, report, _ = table_run
    branches = report['branches']
    assert branches['increasing']['models']['hill']['metrics']['mse_cm2'] == \
        pytest.approx(0.0169, abs=0.0005)
    assert branches['decreasing']['models']['hill']['metrics']['mse_cm2'] == \
        pytest.approx(0.0163, abs=0.0005)
    loop = report['loop']['models']
    assert loop['bouc_wen']['metrics']['mae_cm'] == pytest.approx(0.427, abs=0.01)
    assert loop['bouc_wen']['metrics']['r2'] == pytest.approx(0.939, abs=0.003)
    assert loop['bouc_wen_nonlinear']['metrics']['mse_cm2'] < 0.1 * \
        loop['bouc_wen']['metrics']['mse_cm2']
    assert loop['hill']['metrics']['aicc'] < loop['sigmoid_fixed_c']['metrics']['aicc']
    assert abs(loop['bouc_wen_nonlinear']['drift']['drift_cm']) > 0.1
    holdout = report['holdout']
    assert (holdout['n_train'], holdout['n_test']) == (12, 10)
    assert holdout['models']['sigmoid_fixed_c']['rmse_cm'] == pytest.approx(0.256, abs=0.005)
    assert holdout['models']['hill']['rmse_cm'] == pytest.approx(0.207, abs=0.005)
    c_interval = branches['increasing']['models']['sigmoid_free_c']['ci95']['c']
    assert c_interval[1] - c_interval[0] > 4.0
    assert any('c = ' in w and 'poorly identified' in w for w in report['warnings'])


def test_table_output_params_file_and_plots(table_run):
    out, report, output = table_run
    assert 'paper Table 2 sigmoid' in output and '0.15780' in output
    params = ModelParams.load_yaml(out / 'params.yaml')
    assert params.branch_form == 'hill'  # best loop AICc among the forms model_node runs
    # Only the branches: a hot reload must not reset the node's memory, adaptation, limits.
    written = yaml.safe_load((out / 'params.yaml').read_text())['/**']['ros__parameters']
    assert set(written) == {'branch_form', 'increasing', 'decreasing'}
    assert set(written['increasing']) == {'sigmoid', 'hill'}
    paper = report['branches']['increasing']['models']['sigmoid_fixed_c']['params']
    assert params.increasing.sigmoid.a == pytest.approx(paper['a'])
    fitted = report['branches']['increasing']['models']['hill']['params']
    assert params.increasing.hill.k_pa == pytest.approx(units.kpa_to_pa(fitted['k_kpa']))
    # A branch table has no time: no time series, and no memory check asked for.
    assert sorted(p.name for p in (out / 'plots').iterdir()) == [
        'comparison.png', 'loop.png', 'residuals.png']
    for name in ('loop.png', 'residuals.png', 'comparison.png'):
        png = (out / 'plots' / name).read_bytes()
        assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 10_000


def test_sweep_bag_recovers_the_loop(procs, tmp_path):
    t, pressure, setpoint, length = staircase(noise_m=2e-4, nan_every=11)
    bag = write_state_bag(tmp_path / 'sweep', t, pressure, setpoint, length)
    code, output = run_refit(procs, bag, '--no-holdout', '--json', tmp_path / 'r.json',
                             '--params-out', tmp_path / 'p.yaml', '--model', 'sigmoid_fixed_c')
    assert code == 0, output
    report = json.loads((tmp_path / 'r.json').read_text())
    assert report['data']['steady_state'] and report['data']['dropped_nan_lengths'] > 0
    params = ModelParams.load_yaml(tmp_path / 'p.yaml')
    assert params.branch_form == 'sigmoid'
    for fitted, truth in ((params.increasing.sigmoid, TRUE_INCREASING),
                          (params.decreasing.sigmoid, TRUE_DECREASING)):
        assert fitted.a == pytest.approx(truth.a, abs=0.003)
        assert fitted.b_per_pa == pytest.approx(truth.b_per_pa, rel=0.04)
        # The paper's convention fixes L0 at the measured 0 kPa length, which for a sigmoid
        # truth is its length at 0 Pa (0.8 mm below its L0 parameter).
        assert fitted.l0_m == pytest.approx(TRUE_INCREASING.length(0.0), abs=2e-4)
    assert report['branches']['increasing']['models']['sigmoid_fixed_c']['metrics']['rmse_cm'] \
        < 0.05


def assert_clean_error(code, output, text):
    assert code == 2, output
    assert 'Traceback' not in output
    errors = [line for line in output.splitlines()
              if line.startswith('refit:') and not line.startswith('refit: warning:')]
    assert len(errors) == 1 and text in errors[0], output


def test_a_pipe_closed_early_ends_refit_quietly():
    """`refit TABLE | head -3` ended in a BrokenPipeError traceback."""
    read, write = os.pipe()
    os.close(read)
    try:
        result = subprocess.run([str(REFIT), str(PAPER_TABLE), '--no-holdout'], stdout=write,
                                stderr=subprocess.PIPE, text=True, timeout=150, check=False)
    finally:
        os.close(write)
    assert result.returncode == 141 and 'Traceback' not in result.stderr, result.stderr


def test_missing_file(procs, tmp_path):
    assert_clean_error(*run_refit(procs, tmp_path / 'absent.mcap'), 'no such file')


def test_outputs_and_the_memory_path_are_checked_before_the_fits(procs, tmp_path):
    # Both were found out only after every model was fitted (seconds to minutes), the
    # first naming refit's temporary file (`.x.yaml.tmp`).
    blocked = tmp_path / 'a_file'
    blocked.write_text('')
    for args, text in ((('--params-out', blocked / 'x.yaml'), f'cannot write to {blocked}'),
                       (('--plots', blocked / 'plots'), f'cannot write to {blocked}'),
                       (('--memory-check', tmp_path / 'absent'), 'no such file')):
        code, output = run_refit(procs, PAPER_TABLE, *args)
        assert_clean_error(code, output, text)
        assert 'fitting' not in output, output


def test_bag_without_usable_data(procs, tmp_path):
    t, pressure, setpoint, _ = staircase()
    bag = write_state_bag(tmp_path / 'nan', t, pressure, setpoint, np.full(t.size, np.nan))
    assert_clean_error(*run_refit(procs, bag), 'no usable samples')


def test_single_branch_only(procs, tmp_path):
    t = np.linspace(0, 10, 501)
    pressure = 5e4 * t
    log = write_sample_log(tmp_path / 'up.csv', t, pressure, TRUE_INCREASING.length(pressure))
    assert_clean_error(*run_refit(procs, log), '0 decreasing points; a refit needs at least 5')


def test_fit_that_cannot_run(procs, tmp_path):
    table = tmp_path / 'short.csv'
    table.write_text('pressure_kpa,length_increasing_cm,length_decreasing_cm\n'
                     '0,30,30\n100,29,28.5\n200,27,26.5\n')
    assert_clean_error(*run_refit(procs, table), 'needs at least 5')


@pytest.mark.parametrize('truth', ['play', 'madelung'])
def test_memory_check_finds_the_rule_behind_a_path_with_minor_loops(procs, tmp_path, truth):
    # A path with reversals inside the loop, made by the default (Table 1) branches with one
    # memory rule, plus sensor-sized noise: the check must name that rule, and the params
    # file must carry it.
    from dataclasses import replace

    from pma_model.params import default_params

    turns_kpa = [0, 350, 150, 300, 200, 500, 100, 250, 0]
    pressure = np.concatenate([np.linspace(a, b, 300, endpoint=False)
                               for a, b in itertools.pairwise(turns_kpa)])
    pressure = np.append(pressure, 0.0) * 1e3
    model = replace(default_params(), memory=truth).build_model()
    length = model.predict(pressure) + np.random.default_rng(4).normal(0, 2e-4, pressure.size)
    path = write_sample_log(tmp_path / 'minor.csv', np.arange(pressure.size) * 0.02, pressure,
                            length)
    code, output = run_refit(procs, PAPER_TABLE, '--no-holdout', '--memory-check', path,
                             '--json', tmp_path / 'r.json', '--params-out', tmp_path / 'p.yaml',
                             '--model', 'sigmoid_fixed_c')
    assert code == 0, output
    check = json.loads((tmp_path / 'r.json').read_text())['memory_check']
    assert check['best_memory']['sigmoid_fixed_c'] == truth
    assert check['reversals'] >= 7
    scores = {name.split('/')[1]: entry['rmse_cm'] for name, entry in check['models'].items()
              if name.startswith('sigmoid_fixed_c/')}
    assert scores[truth] < 0.05  # the noise, 0.02 cm, plus the refit's branch error
    assert f'sigmoid_fixed_c -> {truth}' in output
    written = yaml.safe_load((tmp_path / 'p.yaml').read_text())['/**']['ros__parameters']
    assert written['memory'] == truth and written['branch_form'] == 'sigmoid'


def test_holdout_levels_survive_the_scatter_of_measured_holds():
    from pma_model.offline.report import holdout_split
    from pma_model.offline.samples import BranchData

    rng = np.random.default_rng(1)
    levels = np.arange(0.0, 500_001.0, 50_000.0)
    up = levels + rng.uniform(-5e3, 5e3, levels.size)        # hold means: +/-5 kPa band
    down = levels[::-1][1:] + rng.uniform(-5e3, 5e3, levels.size - 1)
    data = BranchData(up, 0.3 - up * 1e-7, down, 0.3 - down * 1.1e-7)
    train, test = holdout_split(data)
    # 0, 100, ... kPa train and 50, 150, ... test, on both branches alike
    assert (train.inc_pressure_pa.size, test.inc_pressure_pa.size) == (6, 5)
    assert (train.dec_pressure_pa.size, test.dec_pressure_pa.size) == (5, 5)
    assert np.all(np.abs(np.round(train.dec_pressure_pa / 100e3) * 100e3
                         - train.dec_pressure_pa) < 6e3)


def test_a_quick_ramp_is_refused_for_its_holds_and_fitted_without_a_hold_out():
    """A staircase of one 100 kPa step with no hold (`pma sweep --max 100kPa --step 100kPa
    --hold 0`): its samples rise and fall, but no level is held on the way up, which the
    refusal said as 'only one branch in the data (no increasing points)'; and raw samples
    that all fall in one or two pressure levels left nothing to test a hold-out on, which
    ended the refit in 'the fit did not converge: zero-size array ...'."""
    from pma_model.offline.refit import check_data
    from pma_model.offline.report import holdout_report
    from pma_model.offline.samples import BranchData, SamplesError

    up, down = np.linspace(0.0, 95e3, 8), np.linspace(67e3, 9e3, 19)
    held = BranchData(up[-1:], 0.29 - up[-1:] * 1e-7, down[:3], 0.29 - down[:3] * 1.1e-7,
                      steady_state=True)
    with pytest.raises(SamplesError, match='1 increasing held levels; a refit needs at least '
                       '5 per branch: a staircase up and back down'):
        check_data(held)
    raw = BranchData(up, 0.3 - up * 1e-7, down, 0.3 - down * 1.1e-7)
    check_data(raw)
    result = holdout_report(raw, {}, stroke_cm=1.0)
    assert 'too few pressure levels' in result['skipped'] and result['models'] == {}


def test_a_bare_mcap_file_is_read_as_a_bag(procs, tmp_path):
    # Documented as supported, yet the CSV sniffing read it as text first ('utf-8' codec
    # can't decode byte 0x89).
    t, pressure, setpoint, length = staircase()
    bag = write_state_bag(tmp_path / 'sweep', t, pressure, setpoint, length)
    bare = bag / 'sweep_0.mcap'
    named_csv = tmp_path / 'sweep.csv'              # content decides, not the name
    named_csv.write_bytes(bare.read_bytes())
    for path in (bare, named_csv):
        code, output = run_refit(procs, path, '--no-holdout', '--json', tmp_path / 'r.json')
        assert code == 0, output
        report = json.loads((tmp_path / 'r.json').read_text())
        assert report['data']['n_increasing'] >= 10 and report['data']['truncated'] is None


def test_bytes_that_are_neither_bag_nor_text_get_the_bag_readers_answer(procs, tmp_path):
    noise = np.random.default_rng(7).bytes(4096)
    (tmp_path / 'x.mcap').write_bytes(b'\x89' + noise)
    assert_clean_error(*run_refit(procs, tmp_path / 'x.mcap'), 'not an MCAP file')
    (tmp_path / 'x.csv').write_bytes(b'time_s,gauge_pressure_pa,length_m\n0,1,0.3\n\xff' + noise)
    assert_clean_error(*run_refit(procs, tmp_path / 'x.csv'),
                       'neither an MCAP bag nor a UTF-8 CSV file: byte 0xff at offset 42 '
                       '(line 3)')


def test_a_truncated_bag_is_refitted_on_what_it_holds_with_one_line_saying_so(procs,
                                                                              tmp_path):
    t, pressure, setpoint, length = staircase()
    bag = write_state_bag(tmp_path / 'crashed', t, pressure, setpoint, length)
    mcap = bag / 'crashed_0.mcap'
    mcap.write_bytes(mcap.read_bytes()[:int(mcap.stat().st_size * 0.75)])  # no summary
    code, output = run_refit(procs, bag, '--no-holdout', '--json', tmp_path / 'r.json')
    assert code == 0, output
    warnings = [line for line in output.splitlines() if 'is truncated (' in line]
    assert len(warnings) == 2, output   # the one stderr line, and the table saying so
    assert warnings[0].startswith('refit: warning:')
    # the spelling that works on this path: `pma run` without a ros2 command line
    assert run_command('pma_bag', 'recover', bag) in warnings[0]
    assert 'TruncatedBagWarning' not in output and 'warnings.warn' not in output
    report = json.loads((tmp_path / 'r.json').read_text())
    assert 'cut off' in report['data']['truncated']
    assert report['data']['samples_used'] < t.size


# Two short tables (6 levels) on which one model does not converge: Bouc-Wen with the Hill
# backbone on a 30 kPa sweep, the Hill branch on the 200 kPa one.
BOUC_WEN_FAILS = """pressure_kpa,length_increasing_cm,length_decreasing_cm
0,29.9893,29.9527
6,29.9588,29.9002
12,29.9764,29.9035
18,29.9251,29.9564
24,29.8644,29.9391
30,29.8762,
"""
HILL_FAILS = """pressure_kpa,length_increasing_cm,length_decreasing_cm
0,30.0851,29.9952
40,29.6645,29.9150
80,29.3904,29.1550
120,28.6576,28.3209
160,27.8143,27.2397
200,26.9669,
"""


def test_one_model_failing_is_reported_for_that_model_only(procs, tmp_path):
    table = tmp_path / 'short.csv'
    table.write_text(BOUC_WEN_FAILS)
    code, output = run_refit(procs, table, '--no-holdout', '--json', tmp_path / 'r.json',
                             '--params-out', tmp_path / 'p.yaml', '--verbose')
    assert code == 0, output
    report = json.loads((tmp_path / 'r.json').read_text())
    failed = report['loop']['models']['bouc_wen_nonlinear']
    assert 'did not converge' in failed['error'] and 'metrics' not in failed
    for name in MODELS - {'bouc_wen_nonlinear'}:
        assert 'metrics' in report['loop']['models'][name], name
    assert any(w.startswith('bouc_wen_nonlinear: not fitted') for w in report['warnings'])
    rows = [line for line in output.splitlines() if line.startswith('bouc_wen_nonlinear')]
    assert len(rows) == 3 and all('failed: the fit of' in row for row in rows), output
    assert ModelParams.load_yaml(tmp_path / 'p.yaml').branch_form in ('sigmoid', 'hill')


def test_the_model_asked_for_failing_fails_the_refit(procs, tmp_path):
    table = tmp_path / 'short.csv'
    table.write_text(HILL_FAILS)
    code, output = run_refit(procs, table, '--no-holdout', '--json', tmp_path / 'r.json',
                             '--params-out', tmp_path / 'p.yaml', '--model', 'hill')
    assert_clean_error(code, output, 'hill, the model asked for with --model, did not '
                                     'converge')
    assert not (tmp_path / 'p.yaml').exists()
    report = json.loads((tmp_path / 'r.json').read_text())   # the rest is still reported
    assert 'error' in report['loop']['models']['hill']
    assert 'metrics' in report['loop']['models']['sigmoid_fixed_c']
    # Without --model the params file takes the best branch model that did converge.
    code, output = run_refit(procs, table, '--no-holdout', '--params-out', tmp_path / 'p.yaml')
    assert code == 0, output
    assert ModelParams.load_yaml(tmp_path / 'p.yaml').branch_form == 'sigmoid'
