"""Tuning set: the paper's nonlinear comparison model, Bouc-Wen, fitted to Table 1.

pma_model.boucwen with a Hill backbone (`refit`'s `bouc_wen_nonlinear`), least squares on
Table 1's loop. Its loop is up to 4 mm wide and it has no return-point memory, like the
`asymmetric` family, by another mechanism: its minor loops ratchet. (With the sigmoid
backbone the least-squares optimum has no loop at all, so that fit would be a muscle without
hysteresis.) The one family of the simulator that needs the model package (pma_model), which
is why pma_sim depends on it; it has no drift option. ROS-free.
"""

from __future__ import annotations

import functools

import numpy as np

from pma_model.boucwen import BoucWenModel, fit_bouc_wen
from pma_model.params import paper_table1


@functools.lru_cache(maxsize=1)
def bouc_wen_fit() -> BoucWenModel:
    """Bouc-Wen with a Hill backbone, least squares on Table 1's loop (RMSE 0.14 cm)."""
    table = paper_table1()
    pressures = np.concatenate([table.pressure_pa, table.pressure_pa])
    lengths = np.concatenate([table.increasing_length_m, table.decreasing_length_m])
    rising = np.arange(pressures.size) < table.pressure_pa.size
    return fit_bouc_wen(pressures, lengths, rising, backbone='hill').model


class BoucWenMuscle:
    """A `families.Muscle` whose length is a Bouc-Wen model's (rate independent)."""

    def __init__(self, model: BoucWenModel):
        self.model = model
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return float(self.model.length_m(0.0, 0.0))

    def reset(self) -> None:
        self._pressure_pa, self._state = 0.0, 0.0
        self.length_m = self.rest_length_m

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        pressure_pa = max(0.0, float(pressure_pa))
        self._state = self.model.advance_state(self._state, self._pressure_pa, pressure_pa)
        self._pressure_pa = pressure_pa
        self.length_m = float(self.model.length_m(pressure_pa, self._state))
        return self.length_m
