"""The error the memory rules leave near the current pressure, carried until pressure moves on.

A rule with return-point memory predicts that a closed minor loop puts the muscle back on the
curve it left. A muscle without that property (a Duhem- or Bouc-Wen-like one, docs/model.md
§3.1) is still millimetres off there, and stays off until the pressure has travelled far
enough for its state to forget: the error is local in pressure, not a slow drift, and the
rules' branch corrections (learned per knot, for every visit) cannot take it. Rules with the
property leave smaller errors of the same kind where their scanning-curve shapes are wrong.

This is a scalar Kalman filter on the mix's out-of-sample residual, measured - predicted,
whose state (the offset) fades as exp(-travel / FADE_PA) and gains uncertainty in proportion
to the pressure travelled (WALK_M2_PER_PA). At a hold it does not fade, and it averages the
lengths measured there instead of chasing their noise (no travel, no new uncertainty). Travel
is counted through a play of PLAY_PA, so the pressure reading's noise is not taken for it.
It changes only the predicted length (and the inverse along the current path, which sees the
offset fade the same way), never what the rules learn.

Chosen on the mix's predictions on every family (the figures: docs/model-history.md): a
faster walk follows the sensor's noise; fading faster leaves more of the Duhem muscle's gaps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pma_model import kernel

FADE_PA = 100_000.0       # pressure travel over which an unexplained offset fades (1/e)
WALK_M2_PER_PA = 3e-12    # offset variance gained per pascal travelled (0.55 mm per 100 kPa)
PLAY_PA = 10_000.0        # +/-4 sigma of the pressure reading's noise (10 bits: 1.3 kPa)


@dataclass
class LocalOffset:
    """The offset's estimate and variance, and the pressure it was last moved to."""

    noise_m: float                # the length sensor's noise (identification's length_noise_m)
    outlier_m: float              # residuals beyond this are not learned from (adaptation's)
    offset_m: float = 0.0
    variance_m2: float = 0.0
    _play_pa: float = math.nan

    def advance(self, pressure_pa: float) -> float:
        """Move to this pressure (fading and loosening by the travel); the offset here."""
        self.offset_m, self.variance_m2, self._play_pa = kernel.local_advance(
            self.offset_m, self.variance_m2, self._play_pa, float(pressure_pa), 0.5 * PLAY_PA,
            FADE_PA, WALK_M2_PER_PA)
        return self.offset_m

    def learn(self, measured_m: float, predicted_without_m: float) -> None:
        """Update from a measured length and the mix's prediction before this offset."""
        self.offset_m, self.variance_m2 = kernel.local_learn(
            self.offset_m, self.variance_m2, measured_m - predicted_without_m,
            self.noise_m ** 2, self.outlier_m)

    def at(self, pressure_pa: float) -> float:
        """The offset expected once pressure has gone straight from here to `pressure_pa`
        (what the inverse adds along the path)."""
        return kernel.faded_offset(self.offset_m, self._play_pa, pressure_pa, 0.5 * PLAY_PA,
                                   FADE_PA)

    @property
    def play_pa(self) -> float:
        """Where the play through which travel is counted stands (NaN before any pressure)."""
        return self._play_pa
