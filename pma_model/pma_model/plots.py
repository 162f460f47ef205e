"""The paper's figures from a refit, in paper units (kPa, cm): PNG files, no display needed.

- loop.png (Fig. 6): the measured loop and the two fitted branches of the paper's form;
- residuals.png (Fig. 7): measured minus model per branch, for each branch model;
- comparison.png (Fig. 8): the data against every fitted model, Bouc-Wen included.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np

from pma_model import units
from pma_model.report import BRANCH_MODEL_FORMS, DIRECTIONS, FittedModel
from pma_model.samples import BranchData

PRESSURE_LABEL = 'gauge pressure P [kPa]'
LENGTH_LABEL = 'muscle length L [cm]'


def _curve_pressures(data: BranchData) -> np.ndarray:
    p_max = max(data.inc_pressure_pa.max(), data.dec_pressure_pa.max())
    return np.linspace(0.0, p_max, 201)


def _data(axes, data: BranchData) -> None:
    axes.plot(units.pa_to_kpa(data.inc_pressure_pa), units.m_to_cm(data.inc_length_m), 'o',
              color='tab:red', label='measured, increasing')
    axes.plot(units.pa_to_kpa(data.dec_pressure_pa), units.m_to_cm(data.dec_length_m), 's',
              color='tab:blue', mfc='none', label='measured, decreasing')


def _finish(figure, axes, path: Path) -> Path:
    for ax in np.atleast_1d(axes):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def plot_loop(data: BranchData, model: FittedModel, path: Path) -> Path:
    figure, axes = plt.subplots(figsize=(6.4, 4.8))
    _data(axes, data)
    p = _curve_pressures(data)
    for rising, colour, label in ((True, 'tab:red', 'increasing'),
                                  (False, 'tab:blue', 'decreasing')):
        lengths = model.predict(p, np.full(p.size, rising))
        axes.plot(units.pa_to_kpa(p), units.m_to_cm(lengths), '-', color=colour,
                  label=f'{model.name} fit, {label}')
    axes.set(xlabel=PRESSURE_LABEL, ylabel=LENGTH_LABEL,
             title='Hysteresis loop and branch fits (paper Fig. 6)')
    return _finish(figure, axes, path)


def plot_residuals(data: BranchData, models: dict[str, FittedModel], path: Path) -> Path:
    figure, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, direction, (p, length) in zip(axes, DIRECTIONS, (
            (data.inc_pressure_pa, data.inc_length_m),
            (data.dec_pressure_pa, data.dec_length_m)), strict=True):
        rising = np.full(p.size, direction == 'increasing')
        for name, model in models.items():
            if name in BRANCH_MODEL_FORMS:
                residual = units.m_to_cm(length - model.predict(p, rising))
                ax.plot(units.pa_to_kpa(p), residual, 'o-', ms=4, label=name)
        ax.axhline(0.0, color='k', lw=0.8)
        ax.set(xlabel=PRESSURE_LABEL, title=f'{direction} pressure (paper Fig. 7)')
    axes[0].set_ylabel('measured - model [cm]')
    return _finish(figure, axes, path)


def plot_comparison(data: BranchData, models: dict[str, FittedModel], path: Path) -> Path:
    figure, axes = plt.subplots(figsize=(7, 5))
    _data(axes, data)
    p = _curve_pressures(data)
    loop_p = np.concatenate([p, p[::-1]])
    rising = np.concatenate([np.ones(p.size, bool), np.zeros(p.size, bool)])
    for name, model in models.items():
        axes.plot(units.pa_to_kpa(loop_p), units.m_to_cm(model.predict(loop_p, rising)), '-',
                  lw=1.2, label=name)
    axes.set(xlabel=PRESSURE_LABEL, ylabel=LENGTH_LABEL,
             title='Model comparison on the loop (paper Fig. 8)')
    return _finish(figure, axes, path)


def write_plots(data: BranchData, models: dict[str, FittedModel], directory) -> list[Path]:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    branch_model = models.get('sigmoid_fixed_c') or next(
        (m for n, m in models.items() if n in BRANCH_MODEL_FORMS), None)
    written = []
    if branch_model is not None:
        written.append(plot_loop(data, branch_model, directory / 'loop.png'))
        written.append(plot_residuals(data, models, directory / 'residuals.png'))
    written.append(plot_comparison(data, models, directory / 'comparison.png'))
    return written
