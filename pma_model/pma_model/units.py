"""Paper units (kPa, cm) to SI (Pa, m) and back.

The model works in SI everywhere; the paper and its Table 1 use kPa and cm. This module
is the one place that knows the factors, so a parameter like the sigmoid's b (per kPa in
the paper, per Pa here) is converted once and in one direction only.
"""

from __future__ import annotations

import numpy as np

PA_PER_KPA = 1000.0
M_PER_CM = 0.01


def kpa_to_pa(pressure_kpa):
    return np.multiply(pressure_kpa, PA_PER_KPA)


def pa_to_kpa(pressure_pa):
    return np.divide(pressure_pa, PA_PER_KPA)


def cm_to_m(length_cm):
    return np.multiply(length_cm, M_PER_CM)


def m_to_cm(length_m):
    return np.divide(length_m, M_PER_CM)


def per_kpa_to_per_pa(rate_per_kpa):
    """A coefficient multiplying pressure (the sigmoid's b): 1/kPa -> 1/Pa."""
    return np.divide(rate_per_kpa, PA_PER_KPA)


def per_pa_to_per_kpa(rate_per_pa):
    return np.multiply(rate_per_pa, PA_PER_KPA)
