"""Online drift correction: recursive least squares on a rest-length shift and a stroke gain.

A muscle drifts (temperature, rubber softening): its rest length moves and its stroke
scales. The adapter keeps the model's shape and fits, around the model's rest length L_ref,
    L_hat = L_ref + shift + gain * (model - L_ref)  ==  offset + gain * model
with offset = L_ref * (1 - gain) + shift (the PmaPrediction fields). Writing it about L_ref
keeps the two regressors well conditioned (the raw form has 1 and ~0.27 m, nearly collinear).

Bounded so a bad sensor cannot run it away: NaN measurements and residuals larger than
`outlier_m` are ignored, shift and gain are clamped, and the covariance is capped at its
initial value so a long hold with no excitation cannot wind it up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_NOISE_SCALE_M = 1e-4  # order of the ultrasonic length noise; sets the RLS prior's weight


@dataclass(frozen=True)
class AdaptationSettings:
    enabled: bool = False
    forgetting: float = 0.99      # RLS forgetting factor lambda (memory ~ 1/(1-lambda) samples)
    max_shift_m: float = 0.005    # |shift| limit [m]
    min_gain: float = 0.8         # stroke gain limits
    max_gain: float = 1.25
    outlier_m: float = 0.01       # residuals beyond this [m] are not learned from

    def __post_init__(self):
        if not isinstance(self.enabled, bool):
            raise ValueError(f'enabled must be true or false, got {self.enabled!r}')
        if not (math.isfinite(self.forgetting) and 0.5 < self.forgetting <= 1.0):
            raise ValueError(f'forgetting must be in (0.5, 1], got {self.forgetting!r}')
        if not (math.isfinite(self.max_shift_m) and self.max_shift_m > 0):
            raise ValueError(f'max_shift_m must be finite and > 0, got {self.max_shift_m!r}')
        if not (math.isfinite(self.min_gain) and math.isfinite(self.max_gain)
                and 0 < self.min_gain <= 1.0 <= self.max_gain):
            raise ValueError('gain limits must satisfy 0 < min_gain <= 1 <= max_gain, got '
                             f'{self.min_gain!r}..{self.max_gain!r}')
        if not (math.isfinite(self.outlier_m) and self.outlier_m > 0):
            raise ValueError(f'outlier_m must be finite and > 0, got {self.outlier_m!r}')


class DriftAdapter:
    """RLS with forgetting on (shift, gain) around a frozen model; see the module docstring."""

    def __init__(self, reference_length_m: float, settings: AdaptationSettings | None = None):
        if not (math.isfinite(reference_length_m) and reference_length_m > 0):
            raise ValueError(f'reference_length_m must be finite and > 0, '
                             f'got {reference_length_m!r}')
        self.reference_length_m = float(reference_length_m)
        self.settings = settings or AdaptationSettings()
        # RLS carries covariance / noise variance. Prior: the whole allowed shift and gain
        # range, against a length noise of _NOISE_SCALE_M; it is also the wind-up cap.
        gain_span = self.settings.max_gain - self.settings.min_gain
        self._initial_covariance = np.diag([self.settings.max_shift_m ** 2,
                                            gain_span ** 2]) / _NOISE_SCALE_M ** 2
        self.reset()

    def reset(self) -> None:
        self._theta = np.array([0.0, 1.0])  # shift_m, gain
        self._covariance = self._initial_covariance.copy()
        self.samples_used = 0
        self.samples_rejected = 0

    @property
    def shift_m(self) -> float:
        return float(self._theta[0])

    @property
    def gain(self) -> float:
        return float(self._theta[1])

    @property
    def offset_m(self) -> float:
        """The offset of L_hat = offset + gain * model (the PmaPrediction field)."""
        return self.reference_length_m * (1.0 - self.gain) + self.shift_m

    def correct(self, model_length_m):
        """Adapted length(s) for the base model's prediction(s) [m]."""
        return self.reference_length_m + self.shift_m + self.gain * (
            np.asarray(model_length_m, dtype=float) - self.reference_length_m)

    def uncorrect(self, adapted_length_m):
        """The base-model length(s) whose correction is adapted_length_m (for the inverse)."""
        return self.reference_length_m + (np.asarray(adapted_length_m, dtype=float)
                                          - self.reference_length_m - self.shift_m) / self.gain

    def correct_then_learn(self, model_length_m: float, measured_length_m: float) -> float:
        """This sample's adapted prediction, made before learning from its measurement.

        The online order: the published prediction (and its residual) stays out-of-sample.
        """
        predicted = float(self.correct(model_length_m))
        self.update(model_length_m, measured_length_m)
        return predicted

    def update(self, model_length_m: float, measured_length_m: float) -> bool:
        """Learn from one sample; False (and no change) for NaN/inf or an outlier."""
        model_length_m, measured_length_m = float(model_length_m), float(measured_length_m)
        if not (math.isfinite(model_length_m) and math.isfinite(measured_length_m)):
            self.samples_rejected += 1
            return False
        regressor = np.array([1.0, model_length_m - self.reference_length_m])
        residual = measured_length_m - self.reference_length_m - float(regressor @ self._theta)
        if abs(residual) > self.settings.outlier_m:
            self.samples_rejected += 1
            return False
        forgetting = self.settings.forgetting
        spread = self._covariance @ regressor
        gain_vector = spread / (forgetting + float(regressor @ spread))
        self._theta = self._theta + gain_vector * residual
        covariance = (self._covariance - np.outer(gain_vector, spread)) / forgetting
        covariance = 0.5 * (covariance + covariance.T)
        # Cap each variance at its prior so an unexcited direction cannot wind up.
        scale = np.sqrt(np.minimum(1.0, np.diag(self._initial_covariance)
                                   / np.maximum(np.diag(covariance), 1e-300)))
        self._covariance = covariance * np.outer(scale, scale)
        self._theta[0] = min(max(self._theta[0], -self.settings.max_shift_m),
                             self.settings.max_shift_m)
        self._theta[1] = min(max(self._theta[1], self.settings.min_gain), self.settings.max_gain)
        self.samples_used += 1
        return True
