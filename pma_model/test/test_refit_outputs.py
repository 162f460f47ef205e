"""What refit leaves behind for a researcher: the JSON's run, every figure, its footer.

refit runs as a real process on real bags (with the experiment's custom_data, as the Sweep
action writes it) and the PNGs are read back, text chunks included; the figures' contents
are checked on the matplotlib figures the same functions build, against models fitted here.
"""

import datetime
import importlib.metadata
import itertools
import json
import re
from dataclasses import replace

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from PIL import Image
from test_refit import PAPER_TABLE, run_refit
from test_samples import staircase, write_state_bag

from pma_model import units
from pma_model.detector import DEFAULT_DEADBAND_PA
from pma_model.offline.plots import (
    BRANCH_STYLES,
    DATA_STYLES,
    MEMORY_LABELS,
    MODEL_COLOURS,
    MODEL_LABELS,
    RESIDUAL_LABEL,
    comparison_figure,
    footer_text,
    loop_figure,
    minor_loops_figure,
    residuals_figure,
    save,
    timeseries_figure,
)
from pma_model.offline.provenance import software_version
from pma_model.offline.refit import plotted_choice
from pma_model.offline.report import BRANCH_MODEL_FORMS, MODEL_NAMES, build_report, memory_check
from pma_model.offline.samples import Samples, read_branch_table, split_branches
from pma_model.params import ModelParams, default_params

CUSTOM = {'note': 'new muscle, 21 degC', 'sweep.profile': 'staircase',
          'device.firmware': 'fake_arduino',
          'sweep.setpoints_pa': json.dumps(list(range(0, 500_001, 5_000)))}
RECORDED = '2023-11-14 22:13:20 UTC'        # write_state_bag's start, 1_700_000_000 s
RUN_ID = '20251124-101500'


def minor_loop_path(rate_hz=20.0, hold_s=1.0):
    """(t, pressure, setpoint, length): holds along 0 -> 350 -> 150 -> 500 -> 200 -> 0 kPa,
    lengths from the default branches with the play rule."""
    turns = [0.0, 350e3, 150e3, 500e3, 200e3, 0.0]
    levels = [0.0] + [p for a, b in itertools.pairwise(turns)
                      for p in np.linspace(a, b, 1 + round(abs(b - a) / 50e3))[1:]]
    setpoint = np.repeat(levels, int(hold_s * rate_hz))
    model = replace(default_params(), memory='play').build_model()
    length = model.predict(setpoint) + np.random.default_rng(3).normal(0, 2e-4, setpoint.size)
    return np.arange(setpoint.size) / rate_hz, setpoint, setpoint, length


@pytest.fixture(scope='module')
def refit_run(tmp_path_factory, module_procs):
    out = tmp_path_factory.mktemp('outputs')
    major = write_state_bag(out / 'major_loop', *staircase(noise_m=2e-4), custom_data=CUSTOM)
    minor = write_state_bag(out / 'minor_loops', *minor_loop_path(),
                            custom_data={'note': 'minor loops', 'sweep.profile': 'forc'})
    code, output = run_refit(module_procs, major, '--no-holdout', '--memory-check', minor,
                             '--json', out / 'r.json', '--params-out', out / 'p.yaml',
                             '--plots', out / 'plots', '--run-id', RUN_ID)
    assert code == 0, output
    return out, json.loads((out / 'r.json').read_text()), output


@pytest.fixture(scope='module')
def fitted_minor_loops():
    """Models fitted on a staircase, their memory check along the minor loops, and the
    predicted paths (as refit computes them)."""
    t, pressure, setpoint, length = staircase(noise_m=2e-4)
    data = split_branches(Samples(t, pressure, length, setpoint, source='major'),
                          DEFAULT_DEADBAND_PA)
    _, fitted = build_report(data, MODEL_NAMES, holdout=False)
    t, pressure, setpoint, length = minor_loop_path()
    path = Samples(t, pressure, length, setpoint, source='minor')
    predictions = {}
    check = memory_check(path, fitted, predictions=predictions)
    return data, fitted, path, check, predictions


def closing(figure):
    plt.close(figure)
    return figure


def test_the_json_says_which_run_when_and_by_which_software(refit_run):
    out, report, _ = refit_run
    run = report['run']
    assert run['run_id'] == RUN_ID
    assert run['source'] == str(out / 'major_loop')
    assert run['recorded'] == RECORDED
    made = datetime.datetime.strptime(run['date'], '%Y-%m-%d %H:%M:%S UTC').replace(
        tzinfo=datetime.timezone.utc)
    assert abs(datetime.datetime.now(datetime.timezone.utc) - made).total_seconds() < 600
    assert run['software_version'].startswith(importlib.metadata.version('pma_model'))
    assert run['software_version'] == software_version()
    assert report['custom_data'] == CUSTOM
    check = report['memory_check']
    assert check['custom_data'] == {'note': 'minor loops', 'sweep.profile': 'forc'}
    assert check['recorded'] == RECORDED


def test_every_figure_carries_the_run_and_the_bag_metadata(refit_run):
    out, report, output = refit_run
    names = ('loop.png', 'residuals.png', 'comparison.png', 'timeseries.png',
             'minor_loops.png')
    assert sorted(p.name for p in (out / 'plots').iterdir()) == sorted(names)
    wrote = f'wrote 5 figures to {out / "plots"}: '
    assert any(line.startswith(wrote) for line in output.splitlines()), output
    for name in names:
        assert name in output.split(wrote)[1].splitlines()[0]
        with Image.open(out / 'plots' / name) as image:
            assert image.size[0] > 800 and image.size[1] > 500
            chunks = image.text
        run = json.loads(chunks['Comment'])
        assert run['run_id'] == RUN_ID, name
        assert chunks['Software'] == f'pma {report["run"]["software_version"]}'
        assert f'run {RUN_ID}' in chunks['Description']
        assert f'recorded {RECORDED}' in chunks['Description']
        assert f'plotted {report["run"]["date"]}' in chunks['Description']
        if name == 'minor_loops.png':      # the memory-check bag's own metadata
            assert run['source'] == str(out / 'minor_loops')
            assert run['custom_data'] == report['memory_check']['custom_data']
            assert 'note=minor loops' in chunks['Description']
        else:
            assert run['source'] == str(out / 'major_loop')
            assert run['custom_data'] == CUSTOM
            assert 'note=new muscle, 21 degC' in chunks['Description']


def test_the_loop_figure_names_the_model_written_to_params_out(refit_run):
    out, report, output = refit_run
    written = ModelParams.load_yaml(out / 'p.yaml')
    name = re.search(rf'wrote {re.escape(str(out / "p.yaml"))} \((\w+), ', output).group(1)
    assert BRANCH_MODEL_FORMS[name] == written.branch_form
    rule = report['memory_check']['best_memory'][name]
    assert written.memory == rule
    with Image.open(out / 'plots' / 'loop.png') as image:
        title = image.text['Title']
    assert title.endswith(
        f'the chosen model: {MODEL_LABELS[name]} (written to params-out, memory {rule})')


def test_without_a_run_id_the_bag_names_the_run(procs, tmp_path):
    bag = write_state_bag(tmp_path / 'muscle_3_major', *staircase())
    code, output = run_refit(procs, bag, '--no-holdout', '--json', tmp_path / 'r.json')
    assert code == 0, output
    run = json.loads((tmp_path / 'r.json').read_text())['run']
    assert run['run_id'] == 'muscle_3_major' and run['recorded'] == RECORDED


def test_the_plotted_choice_is_what_params_out_takes():
    report, _ = build_report(read_branch_table(PAPER_TABLE), MODEL_NAMES, holdout=False)
    assert plotted_choice(report, 'hill', True) == ('hill', 'written to params-out')
    assert plotted_choice(report, 'sigmoid_free_c', False) == (
        'sigmoid_free_c', 'asked for with --model')
    best = ('hill', 'best loop AICc: what params-out takes')   # the paper table's best
    assert plotted_choice(report, None, False) == best
    report['loop']['models']['sigmoid_free_c'] = {'error': 'did not converge'}
    report['branches']['increasing']['models']['sigmoid_free_c'] = {'error': 'no'}
    assert plotted_choice(report, 'sigmoid_free_c', False) == best
    report['memory_check'] = {'best_memory': {'hill': 'play'}}
    assert plotted_choice(report, 'hill', True) == ('hill', 'written to params-out, memory play')


def test_the_loop_figure_draws_the_chosen_model_over_the_papers(fitted_minor_loops):
    data, fitted, *_ = fitted_minor_loops
    figure = closing(loop_figure(data, fitted, chosen='hill', chosen_note='written to params-out'))
    axes = figure.axes[0]
    assert axes.get_title().endswith('the chosen model: Hill branches (written to params-out)')
    for name, width in (('hill', 2.2), ('sigmoid_fixed_c', 1.2)):
        lines = [line for line in axes.get_lines() if line.get_color() == MODEL_COLOURS[name]]
        assert len(lines) == 2 and {line.get_linewidth() for line in lines} == {width}
        for line, rising in zip(lines, (True, False), strict=True):
            p = units.kpa_to_pa(np.asarray(line.get_xdata()))
            expected = units.m_to_cm(fitted[name].predict(p, np.full(p.size, rising)))
            assert np.asarray(line.get_ydata()) == pytest.approx(expected, abs=1e-9), name
    assert {line.get_color() for line in axes.get_lines()} == {
        MODEL_COLOURS['hill'], MODEL_COLOURS['sigmoid_fixed_c'], 'black', '0.45'}


def test_the_time_series_shows_pressure_setpoint_and_length(fitted_minor_loops):
    path = fitted_minor_loops[2]
    figure = closing(timeseries_figure(path))
    pressure_axes, length_axes = figure.axes
    lines = {line.get_label(): line for line in pressure_axes.get_lines()}
    assert set(lines) == {'setpoint', 'measured'}
    t = path.time_s - path.time_s[0]
    for label, values in (('setpoint', path.setpoint_pa), ('measured', path.pressure_pa)):
        assert np.array_equal(lines[label].get_xdata(), t)
        assert np.array_equal(lines[label].get_ydata(), units.pa_to_kpa(values))
    (length_line,) = length_axes.get_lines()
    assert np.array_equal(length_line.get_ydata(), units.m_to_cm(path.length_m))
    assert 'kPa' in pressure_axes.get_ylabel() and 'cm' in length_axes.get_ylabel()
    assert length_axes.get_xlabel() == 'time [s]'


def test_the_minor_loops_show_each_models_prediction_and_the_chosen_on_top(
        fitted_minor_loops):
    _, _, path, check, predictions = fitted_minor_loops
    best = check['best_memory']
    assert set(best) == set(BRANCH_MODEL_FORMS)
    assert len(predictions) == len(check['models'])
    figure = closing(minor_loops_figure(path, predictions, check, chosen='hill'))
    loop, trace = figure.axes[:2]
    drawn = [line for line in loop.get_lines() if line.get_linestyle() == '-']
    assert drawn[-1].get_label().startswith(
        f'Hill branches, {MEMORY_LABELS[best["hill"]]} (RMSE')
    assert len(drawn) == len(best)
    for name, rule in best.items():
        (line,) = [line for line in drawn if line.get_color() == MODEL_COLOURS[name]]
        key = f'{name}/{rule}'
        rmse = check['models'][key]['rmse_cm']
        assert line.get_label().startswith(
            f'{MODEL_LABELS[name]}, {MEMORY_LABELS[rule]} (RMSE {rmse:.3f} cm)')
        assert line.get_label().endswith('; the chosen model') == (name == 'hill')
        assert line.get_linewidth() == (2.2 if name == 'hill' else 1.2)
        assert np.array_equal(line.get_xdata(), units.pa_to_kpa(path.pressure_pa))
        assert np.array_equal(line.get_ydata(), units.m_to_cm(predictions[key]))
        (along,) = [line for line in trace.get_lines() if line.get_color() == MODEL_COLOURS[name]]
        assert np.array_equal(along.get_xdata(), path.time_s - path.time_s[0])
        assert np.array_equal(along.get_ydata(), units.m_to_cm(predictions[key]))
    # The holds are averaged where the path settles: one mean per level held.
    (means,) = [line for line in loop.get_lines() if line.get_label() == 'hold means']
    assert len(means.get_xdata()) == np.count_nonzero(np.diff(path.setpoint_pa)) + 1 == 29
    measured = [line for line in loop.get_lines() if line.get_linestyle() == 'None']
    assert len(measured) == 2
    assert not {line.get_color() for line in measured} & set(MODEL_COLOURS.values())


def test_five_models_each_keep_one_colour_and_no_segment_closes_a_loop():
    data = read_branch_table(PAPER_TABLE)
    _, fitted = build_report(data, MODEL_NAMES, holdout=False)
    figure = closing(comparison_figure(data, fitted))
    loop_axes, error_axes = figure.axes
    lines = [line for line in loop_axes.get_lines() if line.get_linestyle() != 'None']
    markers = [line for line in loop_axes.get_lines() if line.get_linestyle() == 'None']
    assert len(lines) == 2 * len(MODEL_NAMES)
    for name in MODEL_NAMES:
        mine = [line for line in lines if line.get_color() == MODEL_COLOURS[name]]
        # Both branches in the model's colour, solid up and dashed down; each runs one way
        # in pressure, so no segment joins the top of one branch to the other.
        assert sorted(line.get_linestyle() for line in mine) == sorted(BRANCH_STYLES.values())
        for line in mine:
            steps = np.diff(line.get_xdata())
            assert np.all(steps > 0) or np.all(steps < 0), name
        errors = [line for line in error_axes.get_lines()
                  if line.get_color() == MODEL_COLOURS[name]]
        assert sorted(line.get_linestyle() for line in errors) == sorted(BRANCH_STYLES.values())
    assert len(set(MODEL_COLOURS.values())) == len(MODEL_NAMES)
    # The measured points are black and grey, filled up and hollow down: no model's colour.
    assert sorted((m.get_color(), m.get_marker(), m.get_markerfacecolor())
                  for m in markers) == sorted(
        (style['color'], style['marker'], style['mfc']) for style in DATA_STYLES.values())
    assert not {m.get_color() for m in markers} & set(MODEL_COLOURS.values())


def test_the_footer_fits_its_width_and_leaves_long_values_to_the_json():
    run = {'run_id': 'r1', 'source': '/runs/r1/major_loop', 'recorded': None,
           'date': '2025-11-24 10:15:00 UTC', 'software_version': '0.1.0+gabc',
           'custom_data': {**CUSTOM, **{f'calibration.k{i}': '1.5' for i in range(40)}}}
    text = footer_text(run, width=120)
    lines = text.splitlines()
    assert len(lines) <= 4 and all(len(line) <= 120 for line in lines)
    assert lines[0].startswith('run r1   recorded unknown   plotted 2025-11-24 10:15:00 UTC')
    assert 'note=new muscle, 21 degC' in text
    assert 'sweep.setpoints_pa=[0, 5000, 10000, 15000, 20000, 25000, 30000, ...' in text
    assert lines[-1].endswith('calibration.k5=1.5   (more in the JSON)')
    assert footer_text({**run, 'custom_data': {}}).endswith('no bag metadata (custom_data)')


def test_the_footer_is_drawn_below_the_plot(tmp_path, fitted_minor_loops):
    data, fitted, *_ = fitted_minor_loops
    run = {'run_id': 'r1', 'source': 'major_loop', 'recorded': RECORDED,
           'date': '2025-11-24 10:15:00 UTC', 'software_version': '0.1.0', 'custom_data': CUSTOM}
    figure = comparison_figure(data, fitted)
    save(figure, tmp_path / 'c.png', run)
    (footer,) = figure.texts
    assert footer.get_text().startswith(f'run r1   recorded {RECORDED}   plotted 2025-11-24')
    assert 'note=new muscle, 21 degC' in footer.get_text()
    renderer = FigureCanvasAgg(figure).get_renderer()    # save() closed its window
    top_of_footer = footer.get_window_extent(renderer).y1
    for axes in figure.axes:
        assert axes.get_tightbbox(renderer).y0 > top_of_footer


def _legend_texts(axes) -> list[str]:
    legend = axes.get_legend()
    return [text.get_text() for text in legend.get_texts()] if legend else []


def test_the_legends_use_plain_names_not_json_keys(fitted_minor_loops):
    data, fitted, path, check, predictions = fitted_minor_loops
    figures = [loop_figure(data, fitted, chosen='hill'), comparison_figure(data, fitted),
               residuals_figure(data, fitted),
               minor_loops_figure(path, predictions, check, chosen='hill')]
    texts = [text for figure in figures for axes in figure.axes for text in _legend_texts(axes)]
    for figure in figures:
        plt.close(figure)
    assert texts
    keys = set(MODEL_NAMES) | set(MEMORY_LABELS) | {'params-out', '--params-out'}
    for text in texts:       # 'hill', 'mix', 'identify', 'params-out' only as plain words
        words = set(text.replace(',', ' ').replace(';', ' ').replace('/', ' ').split())
        assert not words & keys, text
    comparison = _legend_texts(figures[1].axes[0])
    assert {MODEL_LABELS[name] for name in fitted} <= set(comparison)
    assert 'Hill branches, the chosen model' in texts


def test_comparison_and_residuals_use_one_sign_measured_minus_model(fitted_minor_loops):
    data, fitted, *_ = fitted_minor_loops
    comparison = closing(comparison_figure(data, fitted))
    residuals = closing(residuals_figure(data, fitted))
    errors = comparison.axes[1]
    assert errors.get_ylabel() == residuals.axes[0].get_ylabel() == RESIDUAL_LABEL \
        == 'measured - model [cm]'
    # The same points, the same values: the increasing branch of the paper's sigmoid.
    model = fitted['sigmoid_fixed_c']
    expected = units.m_to_cm(data.inc_length_m - model.predict(
        data.inc_pressure_pa, np.ones(data.inc_pressure_pa.size, bool)))
    order = np.argsort(data.inc_pressure_pa, kind='stable')
    (in_comparison, _) = [line for line in errors.get_lines()
                          if line.get_color() == MODEL_COLOURS['sigmoid_fixed_c']]
    (in_residuals,) = [line for line in residuals.axes[0].get_lines()
                       if line.get_color() == MODEL_COLOURS['sigmoid_fixed_c']]
    assert np.asarray(in_comparison.get_ydata()) == pytest.approx(expected[order], abs=1e-12)
    assert np.asarray(in_residuals.get_ydata()) == pytest.approx(expected[order], abs=1e-12)


def test_the_minor_loop_titles_are_not_file_paths(fitted_minor_loops):
    _, _, path, check, predictions = fitted_minor_loops
    source = '/home/lab/runs/2026-12-01/minor_loops'
    figure = closing(minor_loops_figure(replace(path, source=source), predictions, check))
    titles = [axes.get_title() for axes in figure.axes if axes.get_title()]
    assert titles and not any(source in title or '/' in title for title in titles), titles


def _cielab_distance(first: str, second: str) -> float:
    """The smallest CIE76 distance of two colours for normal, deuteranope and protanope
    vision (Machado, Oliveira & Fernandes 2009, severity 1, on linear sRGB)."""
    from matplotlib.colors import to_rgb
    simulations = (np.eye(3),
                   np.array([[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                             [-0.011820, 0.042940, 0.968881]]),
                   np.array([[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216],
                             [-0.003882, -0.048116, 1.051998]]))
    to_xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722],
                       [0.0193, 0.1192, 0.9505]])

    def lab(colour, simulation):
        rgb = np.array(to_rgb(colour))
        linear = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
        xyz = to_xyz @ np.clip(simulation @ linear, 0, 1) / np.array([0.95047, 1.0, 1.08883])
        f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
        return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])

    return min(float(np.linalg.norm(lab(first, s) - lab(second, s))) for s in simulations)


def test_every_two_models_are_told_apart_by_colour_blind_readers_too():
    # Orange #E69F00 and vermillion #D55E00 (sigmoid, c fitted and linear Bouc-Wen) were
    # 18 apart: one colour in comparison.png to many readers.
    assert _cielab_distance('#E69F00', '#D55E00') < 20
    distances = {(a, b): _cielab_distance(MODEL_COLOURS[a], MODEL_COLOURS[b])
                 for a, b in itertools.combinations(MODEL_NAMES, 2)}
    assert min(distances.values()) > 25, distances
    # Measured data in every figure keeps out of the models' colours (the time series too).
    figure = closing(timeseries_figure(Samples(np.arange(5.0), np.zeros(5), np.full(5, 0.3),
                                               np.zeros(5), source='x')))
    assert not {line.get_color() for axes in figure.axes for line in axes.get_lines()} \
        & set(MODEL_COLOURS.values())
