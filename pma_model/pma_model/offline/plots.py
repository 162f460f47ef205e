"""The refit's figures, in paper units (kPa, cm): PNG files, no display needed.

- loop.png (Fig. 6): the measured loop, the paper's branch fit and the model written to
  --params-out;
- residuals.png (Fig. 7): measured minus model per branch, for each branch model;
- comparison.png (Fig. 8): the data against every fitted model, Bouc-Wen included, and each
  model's error at the measured points, measured minus model as in residuals.png;
- timeseries.png: pressure and length against time (a bag or sample log, not a table);
- minor_loops.png: the --memory-check path and each branch model's prediction along it
  with its best memory rule.

Every model has one colour and one plain name in every figure (from the registries,
report.REPORT_MODELS and rules.MEMORY_RULES; COLOURS adds the bag figure's series; legends say
'Hill branches', not 'hill'), increasing branches are solid and decreasing ones dashed, and the
measured points are black and grey, never a model's colour. Every figure carries a footer:
run id, source, recording and plotting dates, software version and the bag's metadata.
"""

from __future__ import annotations

import json
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from pma_model import units
from pma_model.mix import MIX_MEMORY, RuleMix
from pma_model.offline.report import BRANCH_MODEL_FORMS, DIRECTIONS, REPORT_MODELS, FittedModel
from pma_model.offline.samples import BranchData, Samples, settled_holds
from pma_model.rules import MEMORY_RULES

PRESSURE_LABEL = 'gauge pressure P [kPa]'
LENGTH_LABEL = 'muscle length L [cm]'
RESIDUAL_LABEL = 'measured - model [cm]'      # residuals.png and comparison.png alike
# Each model, and each series of the bag figure (bag_plot.py), has one colour in every figure:
# the models' from their registry (report.REPORT_MODELS), the series' here. Every two models
# differ by a CIELAB distance of at least 27 for normal, deuteranope and protanope vision
# (Machado 2009; pma_model/test/test_refit_outputs.py checks it; docs/model-history.md).
MODEL_COLOURS = {name: model.colour for name, model in REPORT_MODELS.items()}
COLOURS = {**MODEL_COLOURS,
           'measured': 'black', 'setpoint': '0.45', 'prediction': '#56B4E9',
           'target': '#D55E00', 'length setpoint': '#D55E00'}
# Plain names for the legends (the JSON keys are in docs/refit.md's table beside them).
MODEL_LABELS = {name: model.label for name, model in REPORT_MODELS.items()}
MEMORY_LABELS = {MIX_MEMORY: RuleMix.label,
                 **{name: rule.label for name, rule in MEMORY_RULES.items()}}
# What --params-out writes (or would: loop.png's title says why it was chosen).
CHOSEN_LABEL = 'the chosen model'
# The bag figure's series: label, colour (COLOURS) and line.
SERIES = {'measured': {'label': 'measured', 'lw': 0.8},
          'setpoint': {'label': 'setpoint (device)', 'lw': 1.0, 'ls': '--'},
          'prediction': {'label': 'model prediction (model_node)', 'lw': 1.0},
          'target': {'label': "controller's target length", 'lw': 1.4},
          'length setpoint': {'label': "controller's length setpoint (rate-limited)",
                              'lw': 1.0, 'ls': '--'}}
BRANCH_STYLES = {'increasing': '-', 'decreasing': '--'}
DATA_STYLES = {'increasing': {'marker': 'o', 'color': 'black', 'mfc': 'black'},
               'decreasing': {'marker': 's', 'color': '0.45', 'mfc': 'none'}}
# Long custom_data values (every setpoint of a sweep, a CSV profile) are in the JSON, not here.
FOOTER_VALUE_CHARS = 48
FOOTER_LINES = 4
FOOTER_FONT_PT = 6.5


def model_colour(name: str) -> str:
    return COLOURS.get(name, '0.3')


def model_label(name: str) -> str:
    return MODEL_LABELS.get(name, name)


def memory_label(rule: str) -> str:
    return MEMORY_LABELS.get(rule, rule)


def series_style(name: str) -> dict:
    """Matplotlib keywords of a bag-figure series: its label, registry colour and line."""
    return dict(SERIES[name], color=COLOURS[name])


def _shortened(value) -> str:
    text = str(value).replace('\n', ' ')
    return text if len(text) <= FOOTER_VALUE_CHARS else text[:FOOTER_VALUE_CHARS - 3] + '...'


def _fill(items: list[str], width: int, gap: str = '   ') -> list[str]:
    """Items on lines of at most `width`, an item split only when it alone is wider."""
    lines: list[str] = []
    for item in items:
        if lines and len(lines[-1]) + len(gap) + len(item) <= width:
            lines[-1] += gap + item
        else:
            lines += textwrap.wrap(item, width, break_on_hyphens=False) or ['']
    return lines


def footer_text(run: Mapping, width: int = 150) -> str:
    """The footer's lines (at most `width` characters): the run, then the bag's custom_data,
    shortened to fit; the JSON has all of it."""
    head = [f"run {run.get('run_id') or '-'}", f"recorded {run.get('recorded') or 'unknown'}",
            f"plotted {run.get('date', '')}", f"software {run.get('software_version', '')}",
            str(run.get('source', ''))]
    items = [f'{key}={_shortened(value)}' for key, value in
             (run.get('custom_data') or {}).items()]
    lines = _fill(head, width)
    metadata = _fill(items, width) if items else ['no bag metadata (custom_data)']
    if len(lines) + len(metadata) > FOOTER_LINES:
        metadata = metadata[:max(1, FOOTER_LINES - len(lines))]
        suffix, last = '   (more in the JSON)', metadata[-1]
        while len(last) + len(suffix) > width and '   ' in last:
            last = last.rsplit('   ', 1)[0]       # whole items only
        metadata[-1] = last[:width - len(suffix)] + suffix
    return '\n'.join(lines + metadata)


def add_footer(figure, run: Mapping | None) -> float:
    """Write the footer at the figure's bottom; the height it takes, as a figure fraction."""
    if not run:
        return 0.0
    # DejaVu Sans Mono's advance is 0.6 em; measured on the PNG, 0.65 with the spacing.
    width = int(figure.get_figwidth() * 72 / (FOOTER_FONT_PT * 0.65)) - 2
    text = footer_text(run, width)
    figure.text(0.005, 0.004, text, fontsize=FOOTER_FONT_PT, color='0.3', ha='left',
                va='bottom', family='monospace')
    height_in = (text.count('\n') + 1) * FOOTER_FONT_PT * 1.3 / 72 + 0.08
    return height_in / figure.get_figheight()


def png_metadata(run: Mapping | None) -> dict[str, str]:
    """The run in the PNG's text chunks too, for a program (or `exiftool`) to read."""
    if not run:
        return {}
    return {'Software': f"pma {run.get('software_version', '')}",
            'Source': str(run.get('source', '')),
            'Creation Time': str(run.get('date', '')),
            'Description': footer_text(run, 10_000),
            'Comment': json.dumps(dict(run), sort_keys=True)}


def save(figure, path: Path, run: Mapping | None = None, dpi: int = 120,
         extra_metadata: Mapping[str, str] | None = None) -> Path:
    """Footer, layout that leaves it room, PNG (the run, the titles and `extra_metadata` in
    its text chunks), close."""
    bottom = add_footer(figure, run)
    figure.tight_layout(rect=(0, bottom, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    titles = [ax.get_title() for ax in figure.axes if ax.get_title()]
    metadata = png_metadata(run) | ({'Title': ' | '.join(titles)} if titles else {}) | dict(
        extra_metadata or {})
    figure.savefig(path, dpi=dpi, metadata=metadata)
    plt.close(figure)
    return path


def _curve_pressures(data: BranchData) -> np.ndarray:
    p_max = max(data.inc_pressure_pa.max(), data.dec_pressure_pa.max())
    return np.linspace(0.0, p_max, 201)


def _data(axes, data: BranchData) -> None:
    for direction, (p, length) in zip(DIRECTIONS, (
            (data.inc_pressure_pa, data.inc_length_m),
            (data.dec_pressure_pa, data.dec_length_m)), strict=True):
        axes.plot(units.pa_to_kpa(p), units.m_to_cm(length), ls='none', ms=5,
                  label=f'measured, {direction}', **DATA_STYLES[direction])


def _branches(axes, model: FittedModel, p: np.ndarray, label: str, **style) -> None:
    """Both branches of a model, each on its own: no segment joins them at the top.

    Along the path 0 -> top -> 0, as a loop model (Bouc-Wen) must be run.
    """
    path = np.concatenate([p, p[::-1]])
    rising = np.concatenate([np.ones(p.size, bool), np.zeros(p.size, bool)])
    lengths = units.m_to_cm(model.predict(path, rising))
    for direction, part in zip(DIRECTIONS, (slice(0, p.size), slice(p.size, None)),
                               strict=True):
        axes.plot(units.pa_to_kpa(path[part]), lengths[part], BRANCH_STYLES[direction],
                  color=style.get('color', model_colour(model.name)),
                  lw=style.get('lw', 1.4), alpha=style.get('alpha', 0.95),
                  label=label if direction == 'increasing' else None)


def _branch_key() -> list[Line2D]:
    return [Line2D([], [], color='0.2', ls=BRANCH_STYLES[d], lw=1.2, label=f'{d} branch')
            for d in DIRECTIONS]


def _legend(axes, extra: list | None = None, **kwargs) -> None:
    handles, _ = axes.get_legend_handles_labels()
    axes.legend(handles=handles + (extra or []), fontsize=8, framealpha=0.9, **kwargs)


def plot_loop(data: BranchData, models: dict[str, FittedModel], path: Path, *,
              chosen: str | None, run: Mapping | None = None, chosen_note: str = '',
              warnings: Sequence[str] = ()) -> Path:
    return save(loop_figure(data, models, chosen=chosen, chosen_note=chosen_note,
                            warnings=warnings), path, run)


def loop_figure(data: BranchData, models: dict[str, FittedModel], *, chosen: str | None,
                chosen_note: str = '', warnings: Sequence[str] = ()):
    """The paper's branch fit (sigmoid, c fixed) and the chosen model, on the measured loop;
    refit's data-check `warnings`, if any, in a box over it."""
    figure, axes = plt.subplots(figsize=(7.2, 5.4))
    _data(axes, data)
    p = _curve_pressures(data)
    paper = models.get('sigmoid_fixed_c')
    if paper is not None and paper.name != chosen:
        _branches(axes, paper, p, model_label(paper.name), lw=1.2)
    title = 'Hysteresis loop and branch fits (paper Fig. 6)'
    if chosen in models:
        _branches(axes, models[chosen], p, f'{model_label(chosen)}, {CHOSEN_LABEL}', lw=2.2)
        title += f'\nthe chosen model: {model_label(chosen)}' + (
            f' ({chosen_note})' if chosen_note else '')
    axes.set(xlabel=PRESSURE_LABEL, ylabel=LENGTH_LABEL, title=title)
    axes.grid(alpha=0.3)
    _legend(axes, _branch_key(), loc='lower left')
    if warnings:
        text = '\n'.join(textwrap.fill(f'! {line}', 95, subsequent_indent='   ')
                         for line in warnings)
        axes.text(0.99, 0.99, f'DATA WARNINGS ({len(warnings)}):\n{text}',
                  transform=axes.transAxes, ha='right', va='top', fontsize=6, color='#B00000',
                  bbox={'facecolor': 'white', 'edgecolor': '#B00000', 'alpha': 0.9})
    return figure


def plot_residuals(data: BranchData, models: dict[str, FittedModel], path: Path,
                   run: Mapping | None = None) -> Path:
    return save(residuals_figure(data, models), path, run)


def residuals_figure(data: BranchData, models: dict[str, FittedModel]):
    """Measured - model per branch for each branch model (the sign of comparison.png's
    errors too)."""
    figure, axes = plt.subplots(1, 2, figsize=(10.5, 4.4), sharey=True)
    for ax, direction, (p, length) in zip(axes, DIRECTIONS, (
            (data.inc_pressure_pa, data.inc_length_m),
            (data.dec_pressure_pa, data.dec_length_m)), strict=True):
        rising = np.full(p.size, direction == 'increasing')
        order = np.argsort(p, kind='stable')
        for name, model in models.items():
            if name in BRANCH_MODEL_FORMS:
                residual = units.m_to_cm(length - model.predict(p, rising))
                ax.plot(units.pa_to_kpa(p[order]), residual[order], 'o-', ms=3.5, lw=1.0,
                        color=model_colour(name), label=model_label(name))
        ax.axhline(0.0, color='k', lw=0.8)
        ax.set(xlabel=PRESSURE_LABEL, title=f'{direction} pressure (paper Fig. 7)')
        ax.grid(alpha=0.3)
        _legend(ax)
    axes[0].set_ylabel(RESIDUAL_LABEL)
    return figure


def plot_comparison(data: BranchData, models: dict[str, FittedModel], path: Path,
                    run: Mapping | None = None) -> Path:
    return save(comparison_figure(data, models), path, run)


def comparison_figure(data: BranchData, models: dict[str, FittedModel]):
    """Every model's two branches (its colour, solid rising, dashed falling) on the loop, and
    below, each model's error at the measured points, where models a line-width apart on
    the loop still differ."""
    figure, (axes, errors) = plt.subplots(2, 1, sharex=True, figsize=(7.8, 7.4),
                                          gridspec_kw={'height_ratios': [3, 1.3]})
    _data(axes, data)
    p = _curve_pressures(data)
    p_loop, l_loop, rising = data.loop()
    for name, model in models.items():
        _branches(axes, model, p, model_label(name))
        error = units.m_to_cm(l_loop - model.predict(p_loop, rising))   # as residuals.png
        for direction, mask in zip(DIRECTIONS, (rising, ~rising), strict=True):
            order = np.argsort(p_loop[mask], kind='stable')
            errors.plot(units.pa_to_kpa(p_loop[mask][order]), error[mask][order],
                        BRANCH_STYLES[direction], marker='.', ms=4, lw=1.0,
                        color=model_colour(name))
    axes.set(ylabel=LENGTH_LABEL, title='Model comparison on the loop (paper Fig. 8)')
    errors.axhline(0.0, color='k', lw=0.8)
    errors.set(xlabel=PRESSURE_LABEL, ylabel=RESIDUAL_LABEL)
    for ax in (axes, errors):
        ax.grid(alpha=0.3)
    _legend(axes, _branch_key(), loc='lower left', ncols=2)
    return figure


def plot_timeseries(samples: Samples, path: Path, run: Mapping | None = None,
                    title: str = '') -> Path:
    return save(timeseries_figure(samples, title), path, run)


def timeseries_figure(samples: Samples, title: str = ''):
    """Pressure (and setpoint) and length against time."""
    figure, (pressure, length) = plt.subplots(2, 1, sharex=True, figsize=(10, 5.6))
    t = samples.time_s - samples.time_s[0]
    if samples.setpoint_pa is not None:        # the registry's colours: no model's
        pressure.plot(t, units.pa_to_kpa(samples.setpoint_pa), color=COLOURS['setpoint'],
                      lw=1.0, ls='--', label='setpoint')
    pressure.plot(t, units.pa_to_kpa(samples.pressure_pa), color=COLOURS['measured'], lw=0.9,
                  label='measured')
    pressure.set_ylabel('gauge pressure [kPa]')
    length.plot(t, units.m_to_cm(samples.length_m), color=COLOURS['measured'], lw=0.6,
                label='measured (HC-SR04)')
    length.set(ylabel='length [cm]', xlabel='time [s]')
    pressure.set_title(title or f'Pressure and length against time: {samples.source}')
    for ax in (pressure, length):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc='best')
    return figure


def plot_minor_loops(samples: Samples, predictions: Mapping[str, np.ndarray],
                     memory: Mapping, path: Path, *, run: Mapping | None = None,
                     chosen: str | None = None) -> Path:
    return save(minor_loops_figure(samples, predictions, memory, chosen=chosen), path, run)


def minor_loops_figure(samples: Samples, predictions: Mapping[str, np.ndarray],
                       memory: Mapping, *, chosen: str | None = None):
    """The memory-check path: measured, and each branch model with its best memory rule
    (`memory`: the report's memory_check)."""
    best_memory, scores = memory['best_memory'], memory['models']
    figure, (loop, trace) = plt.subplots(1, 2, figsize=(12.5, 5.2),
                                         gridspec_kw={'width_ratios': [1, 1.3]})
    p_kpa, t = units.pa_to_kpa(samples.pressure_pa), samples.time_s - samples.time_s[0]
    measured_cm = units.m_to_cm(samples.length_m)
    loop.plot(p_kpa, measured_cm, '.', color='0.7', ms=2, label='measured samples')
    trace.plot(t, measured_cm, '.', color='0.7', ms=2, label='measured samples')
    holds, on_holds = settled_holds(samples)
    if on_holds:
        means = np.array([[p_kpa[a:b].mean(), measured_cm[a:b].mean(), t[a:b].mean()]
                          for a, b in holds])
        loop.plot(means[:, 0], means[:, 1], 'o', color='black', ms=4, label='hold means')
        trace.plot(means[:, 2], means[:, 1], 'o', color='black', ms=3, label='hold means')
    # The chosen model last, on top.
    for name, rule in sorted(best_memory.items(), key=lambda item: item[0] == chosen):
        key = f'{name}/{rule}'
        if key not in predictions:
            continue
        predicted = units.m_to_cm(predictions[key])
        rmse = scores.get(key, {}).get('rmse_cm')
        label = f'{model_label(name)}, {memory_label(rule)}' + (
            f' (RMSE {rmse:.3f} cm)' if rmse is not None else '')
        if name == chosen:
            label += f'; {CHOSEN_LABEL}'
        width = 2.2 if name == chosen else 1.2
        loop.plot(p_kpa, predicted, '-', color=model_colour(name), lw=width, label=label)
        trace.plot(t, predicted, '-', color=model_colour(name), lw=width, label=label)
    loop.set(xlabel=PRESSURE_LABEL, ylabel=LENGTH_LABEL,
             title="Minor loops: measured, and each model's best memory rule")
    trace.set(xlabel='time [s]', ylabel=LENGTH_LABEL,
              title='Length against time along the memory-check run')
    for ax in (loop, trace):
        ax.grid(alpha=0.3)
    twin = trace.twinx()
    twin.plot(t, p_kpa, color='0.35', lw=0.7, ls=':')
    twin.set_ylabel('gauge pressure [kPa], dotted', color='0.35')
    # One legend for both panels: the same lines.
    loop.legend(fontsize=7.5, loc='upper right', framealpha=0.9)   # a loop leaves it empty
    return figure


def write_plots(data: BranchData, models: dict[str, FittedModel], directory, *,
                run: Mapping | None = None, chosen: str | None = None, chosen_note: str = '',
                samples: Samples | None = None, memory: Mapping | None = None,
                memory_samples: Samples | None = None, memory_run: Mapping | None = None,
                predictions: Mapping[str, np.ndarray] | None = None,
                warnings: Sequence[str] = ()) -> list[Path]:
    """Every figure the inputs allow. `chosen`: the model --params-out writes (or would);
    `memory`, `memory_samples`, `memory_run`, `predictions`: the memory check's report,
    path, its bag's run_info, and the predicted lengths; `warnings`: refit's data checks',
    drawn on the loop."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    if chosen is None or chosen not in models:
        chosen = 'sigmoid_fixed_c' if 'sigmoid_fixed_c' in models else next(
            (n for n in models if n in BRANCH_MODEL_FORMS), None)
        chosen_note = ''
    if chosen is not None:
        written.append(plot_loop(data, models, directory / 'loop.png', chosen=chosen, run=run,
                                 chosen_note=chosen_note, warnings=warnings))
        written.append(plot_residuals(data, models, directory / 'residuals.png', run))
    written.append(plot_comparison(data, models, directory / 'comparison.png', run))
    if samples is not None and samples.time_s.size:
        written.append(plot_timeseries(samples, directory / 'timeseries.png', run))
    if memory is not None and memory_samples is not None and predictions:
        written.append(plot_minor_loops(memory_samples, predictions, memory,
                                        directory / 'minor_loops.png', run=memory_run or run,
                                        chosen=chosen))
    return written
