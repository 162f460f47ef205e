"""Valve-driven pressure in the muscle: first-order lags toward supply or ambient.

Through an orifice the flow falls as the pressure difference falls, which a first-order
lag captures well enough for a bang-bang loop: with the defaults, filling from 0 to
500 kPa takes about 1.4 s (tau * ln(600/100)), venting from 500 kPa to 5 kPa about 2.3 s.
Pressures are gauge [Pa], times [s].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pma_common.protocol import Valve


@dataclass(frozen=True)
class PneumaticParams:
    supply_pa: float = 600_000.0         # regulated supply behind the inlet valve
    fill_time_constant_s: float = 0.8    # inlet open
    vent_time_constant_s: float = 0.5    # exhaust open, toward ambient (0 Pa gauge)
    leak_time_constant_s: float = 600.0  # both closed: fittings leak slowly

    def __post_init__(self):
        if not (math.isfinite(self.supply_pa) and self.supply_pa > 0):
            raise ValueError('supply_pa must be finite and > 0')
        for name in ('fill_time_constant_s', 'vent_time_constant_s', 'leak_time_constant_s'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0')


class Pneumatics:
    """Muscle pressure driven by the valve state; `step(dt, valve)` advances it exactly."""

    def __init__(self, params: PneumaticParams = PneumaticParams(), pressure_pa: float = 0.0):
        self.params = params
        self.pressure_pa = float(pressure_pa)
        self._decay_cache: dict[tuple[Valve, float], float] = {}

    def _target_and_tau(self, valve: Valve) -> tuple[float, float]:
        p = self.params
        if valve == Valve.FILL:
            return p.supply_pa, p.fill_time_constant_s
        if valve == Valve.VENT:
            return 0.0, p.vent_time_constant_s
        return 0.0, p.leak_time_constant_s

    def step(self, dt_s: float, valve: Valve) -> float:
        """Advance by dt_s with the valves in `valve` state; return the new pressure [Pa]."""
        target, tau = self._target_and_tau(Valve(valve))
        key = (valve, dt_s)
        decay = self._decay_cache.get(key)
        if decay is None:
            decay = self._decay_cache[key] = math.exp(-dt_s / tau)
        self.pressure_pa = target + (self.pressure_pa - target) * decay
        return self.pressure_pa
