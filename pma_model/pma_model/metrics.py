"""Goodness-of-fit numbers for a model against data, in whatever unit the data are in.

The conventions are fixed here so every report agrees (and matches the paper's Table 2 for
its sigmoid: it uses AIC = n*ln(MSE) + 2k with k = 2 fitted parameters; its printed MSE is
4x the value its own MAE, R2, AIC and BIC imply). R2 uses the total sum of squares about the
data mean. NaN pairs are dropped and n counts only the pairs used.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class FitMetrics:
    n: int                     # pairs used
    k: int                     # fitted parameters (for AIC/AICc/BIC)
    mae: float
    mse: float
    rmse: float
    max_abs_error: float
    r2: float                  # 1 - SSE/SST, SST about the mean of the data
    pearson_r: float
    stroke: float              # max - min of the data unless given
    rmse_pct_stroke: float
    max_pct_stroke: float
    aic: float                 # n*ln(MSE) + 2k
    aicc: float                # AIC + 2k(k+1)/(n-k-1); NaN when n <= k + 1
    bic: float                 # n*ln(MSE) + k*ln(n)

    def as_dict(self) -> dict:
        return asdict(self)


def fit_metrics(measured, predicted, k: int = 0, stroke: float | None = None) -> FitMetrics:
    """Every metric of `predicted` against `measured` (same unit, e.g. cm for the paper)."""
    measured = np.asarray(measured, dtype=float).ravel()
    predicted = np.asarray(predicted, dtype=float).ravel()
    if measured.shape != predicted.shape:
        raise ValueError(f'measured and predicted differ in size: {measured.size} vs '
                         f'{predicted.size}')
    if k < 0:
        raise ValueError(f'k must be >= 0, got {k}')
    keep = np.isfinite(measured) & np.isfinite(predicted)
    measured, predicted = measured[keep], predicted[keep]
    n = int(measured.size)
    if n < 2:
        raise ValueError(f'need at least 2 finite pairs, got {n}')
    errors = predicted - measured
    mse = float(np.mean(errors ** 2))
    sst = float(np.sum((measured - measured.mean()) ** 2))
    if stroke is None:
        stroke = float(measured.max() - measured.min())
    with np.errstate(divide='ignore', invalid='ignore'):
        pearson = float(np.corrcoef(measured, predicted)[0, 1])
        log_mse = math.log(mse) if mse > 0 else -math.inf
    aic = n * log_mse + 2 * k
    return FitMetrics(
        n=n, k=k,
        mae=float(np.mean(np.abs(errors))),
        mse=mse,
        rmse=math.sqrt(mse),
        max_abs_error=float(np.max(np.abs(errors))),
        r2=1.0 - float(np.sum(errors ** 2)) / sst if sst > 0 else math.nan,
        pearson_r=pearson,
        stroke=float(stroke),
        rmse_pct_stroke=100.0 * math.sqrt(mse) / stroke if stroke > 0 else math.nan,
        max_pct_stroke=100.0 * float(np.max(np.abs(errors))) / stroke if stroke > 0
        else math.nan,
        aic=aic,
        aicc=aic + 2 * k * (k + 1) / (n - k - 1) if n - k - 1 > 0 else math.nan,
        bic=n * log_mse + k * math.log(n),
    )
