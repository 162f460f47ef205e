"""The figure a controller run is judged by: length (setpoint, measured, true) and pressure
against time. Paper units (cm, kPa) here only: this is for people, not for the interfaces."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np


def plot_control_run(path: Path, *, t_s, target_m, measured_m, command_pa, pressure_pa,
                     true_m=None, title: str = 'length control',
                     run: Mapping | None = None) -> Path:
    """Write a two-panel PNG; `true_m` (a simulation's truth) is drawn when given; `run`
    (pma_model.offline.provenance.run_info) is the footer, as on the refit's figures."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from pma_model.offline.plots import save

    t = np.asarray(t_s, dtype=float)
    figure, (lengths, pressures) = plt.subplots(2, 1, sharex=True, figsize=(10, 6.5))
    lengths.plot(t, 100 * np.asarray(measured_m), '.', color='0.6', markersize=2,
                 label='measured (HC-SR04)')
    if true_m is not None:
        lengths.plot(t, 100 * np.asarray(true_m), color='tab:green', linewidth=1.2,
                     label='true (simulated muscle)')
    lengths.plot(t, 100 * np.asarray(target_m), color='black', linestyle='--', linewidth=1.0,
                 label='setpoint')
    lengths.set_ylabel('length [cm]')
    lengths.legend(loc='upper right', fontsize=8)
    lengths.grid(alpha=0.3)
    lengths.set_title(title)
    pressures.plot(t, np.asarray(command_pa) / 1e3, color='tab:red', linewidth=1.0,
                   label='command (pma/pressure_setpoint)')
    pressures.plot(t, np.asarray(pressure_pa) / 1e3, color='tab:blue', linewidth=0.8,
                   label='measured')
    pressures.set_ylabel('gauge pressure [kPa]')
    pressures.set_xlabel('time [s]')
    pressures.legend(loc='upper right', fontsize=8)
    pressures.grid(alpha=0.3)
    return save(figure, path, run, dpi=110)
