"""Drift: the muscle's rest length shifts and its stroke scales (temperature, wear).

The correction keeps the model's shape and maps its length, around the model's rest length
L_ref, as
    L_hat = L_ref + shift + gain * (model - L_ref)  ==  offset + gain * model
with offset = L_ref * (1 - gain) + shift (the PmaPrediction fields). Writing it about L_ref
keeps the two unknowns well conditioned (the raw form has 1 and ~0.27 m, nearly collinear).

Drift is slow; the error of the minor-loop rule is fast and tied to reversals. So shift and
gain are estimated (in `identification.OnlineModel`, jointly with what the model learns
about the muscle) as random walks that move over `time_constant_s`, and every sample is
weighted by how sure the memory is there: where the candidate minor-loop shapes disagree
(just after a reversal) a residual says little about drift and is nearly ignored. They are
bounded so a bad sensor cannot run them away: residuals beyond `outlier_m` are not learned
from, and shift and gain are clamped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pma_model import kernel


@dataclass(frozen=True)
class AdaptationSettings:
    enabled: bool = False
    time_constant_s: float = 10.0  # the drift estimate follows changes over about this long
    max_shift_m: float = 0.005     # |shift| limit [m]
    min_gain: float = 0.8          # stroke gain limits
    max_gain: float = 1.25
    outlier_m: float = 0.01        # residuals beyond this [m] are not learned from

    def __post_init__(self):
        if not isinstance(self.enabled, bool):
            raise ValueError(f'enabled must be true or false, got {self.enabled!r}')
        if not (math.isfinite(self.time_constant_s) and 1.0 <= self.time_constant_s <= 3600.0):
            raise ValueError('time_constant_s must be within 1..3600 s, '
                             f'got {self.time_constant_s!r}')
        if not (math.isfinite(self.max_shift_m) and self.max_shift_m > 0):
            raise ValueError(f'max_shift_m must be finite and > 0, got {self.max_shift_m!r}')
        if not (math.isfinite(self.min_gain) and math.isfinite(self.max_gain)
                and 0 < self.min_gain <= 1.0 <= self.max_gain):
            raise ValueError('gain limits must satisfy 0 < min_gain <= 1 <= max_gain, got '
                             f'{self.min_gain!r}..{self.max_gain!r}')
        if not (math.isfinite(self.outlier_m) and self.outlier_m > 0):
            raise ValueError(f'outlier_m must be finite and > 0, got {self.outlier_m!r}')


@dataclass(frozen=True)
class Drift:
    """A rest-length shift and a stroke gain about `reference_length_m` (module docstring)."""

    reference_length_m: float
    shift_m: float = 0.0
    gain: float = 1.0

    @property
    def offset_m(self) -> float:
        """The offset of L_hat = offset + gain * model (the PmaPrediction field)."""
        return kernel.drift_offset(self.reference_length_m, self.shift_m, self.gain)

    def correct(self, model_length_m):
        """Drifted length(s) for the model's length(s) [m]; a float stays a float (the
        inverse's searches call this per evaluation)."""
        if not isinstance(model_length_m, float):
            model_length_m = np.asarray(model_length_m, dtype=float)
            if model_length_m.ndim == 0:
                model_length_m = float(model_length_m)
        return kernel.drifted_length(self.reference_length_m, self.shift_m, self.gain,
                                     model_length_m)

    def uncorrect(self, drifted_length_m):
        """The model length(s) whose correction is drifted_length_m (for the inverse)."""
        return self.reference_length_m + (np.asarray(drifted_length_m, dtype=float)
                                          - self.reference_length_m - self.shift_m) / self.gain
