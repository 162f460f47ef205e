"""Muscle families: one interface, several hysteresis mechanisms, all fitted to Table 1.

One major loop cannot tell hysteresis families apart: they differ inside it, after
reversals. Each family here reproduces the paper's Table 1 within the HC-SR04's accuracy
(fits in `family_fits.py`, written by `python -m pma_sim.fit_families`), and
each behaves differently after a reversal:

- `narrow`: the Preisach muscle of `muscle.py` (narrow relays). After a reversal the length
  holds for a few tens of kPa, then rejoins the other major branch.
- `wide`: Prandtl-Ishlinskii (play operators on a warped pressure, Hammerstein form) with a
  large reversible share and wide plays. After a reversal the length moves at once and its
  scanning curve spans the whole excursion back to the previous reversal.
- `asymmetric`: a Duhem model: after a reversal the length approaches the other envelope
  exponentially in pressure, with a short pressure scale on the way up (inflation: the
  braid catches quickly) and a long one on the way down (deflation: slow recovery). Its
  minor loops close only approximately (no exact return-point memory), as in many
  real muscles.
- `creep`: the narrow muscle with a viscoelastic element in series: after a pressure step
  the length keeps moving for a second or two, so loops widen with speed. Holds settle
  on the narrow muscle's (Table 1) loop.

Any family takes `drift=DriftSpec(...)`: rest length and stroke change slowly, as with
temperature and wear (`registry.muscle_from_spec('wide+drift')` for the default drift).

These are the mechanisms; `pma_sim.registry` names every family, the ones of
other modules (generalized_play, friction, bouc_wen) too, and builds them by name.

The interface (`Muscle`): `update(pressure_pa, t_s) -> length_m` with gauge pressure [Pa]
and a time [s] that never goes back (rate-independent families ignore it), `length_m`
(the true length, for evaluation), `rest_length_m` and `reset()` (relaxed, at 0 Pa).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from pma_sim import family_fits

SPAN_PA = 700_000.0          # the warped input reaches 1 here: above the 600 kPa supply
DUHEM_SUBSTEP_PA = 1_000.0   # largest pressure step the Duhem update takes at once


class Muscle(Protocol):
    """What the simulated rig needs of a muscle (see the module docstring)."""

    length_m: float

    @property
    def rest_length_m(self) -> float: ...

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float: ...

    def reset(self) -> None: ...


# --- wide: Prandtl-Ishlinskii ---------------------------------------------------------------

@dataclass(frozen=True)
class PlayParams:
    """Hammerstein Prandtl-Ishlinskii: plays of half-width r_j on v = warp(p), weights w_j.

    v = h(p - dead_zone) / h(SPAN - dead_zone) with h(q) = q^n / (q^n + K^n), so v runs
    0..1. Each play's output y_j stays within [v - r_j, v + r_j]; the relaxed state (after
    a long rest at 0 Pa) is y_j = r_j. length = rest - sum_j w_j (y_j - r_j).
    """

    rest_length_m: float
    dead_zone_pa: float
    warp_k_pa: float
    warp_n: float
    radii: tuple[float, ...]
    weights_m: tuple[float, ...]

    def warp(self, pressure_pa):
        def h(q):
            return q ** self.warp_n / (q ** self.warp_n + self.warp_k_pa ** self.warp_n)

        q = np.clip(np.asarray(pressure_pa, dtype=float) - self.dead_zone_pa, 0.0, None)
        return h(q) / h(SPAN_PA - self.dead_zone_pa)

    def envelopes(self, v) -> tuple[np.ndarray, np.ndarray]:
        """(rising, falling) edge of every play's band at warped input v before its half-width,
        shaped v.shape + (plays,): v for both here; a generalized play's differ
        (generalized_play.py)."""
        v = np.asarray(v, dtype=float)[..., None]
        edges = np.broadcast_to(v, (*v.shape[:-1], len(self.radii)))
        return edges, edges


class PlayMuscle:
    """The `wide` family: rate-independent, return-point memory, wiping-out (PI operators)."""

    def __init__(self, params: PlayParams):
        self.params = params
        self._radii = np.array(params.radii, dtype=float)
        self._weights = np.array(params.weights_m, dtype=float)
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return self.params.rest_length_m

    def reset(self) -> None:
        self._outputs = self._radii.copy()
        self.length_m = self.params.rest_length_m

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        low, high = self._band(float(self.params.warp(float(pressure_pa))))
        np.clip(self._outputs, low, high, out=self._outputs)
        self.length_m = self.params.rest_length_m - float(
            self._weights @ (self._outputs - self._radii))
        return self.length_m

    def _band(self, v: float) -> tuple[np.ndarray, np.ndarray]:
        """Every play's band at warped input v: params.envelopes widened by the half-widths,
        written out for the classic play (this runs every millisecond of the simulated rig,
        and the general form costs as much as the rest of the update)."""
        return v - self._radii, v + self._radii


def play_major_loop_m(params: PlayParams, pressures_pa) -> tuple[np.ndarray, np.ndarray]:
    """(increasing, decreasing) branch lengths of the 0 -> max(pressures) -> 0 loop."""
    rising, falling = params.envelopes(params.warp(pressures_pa))
    radii = np.array(params.radii)
    weights = np.array(params.weights_m)
    top = np.maximum(radii, rising.max(axis=0) - radii)
    up = np.maximum(radii[None, :], rising - radii[None, :])
    down = np.minimum(top[None, :], falling + radii[None, :])
    return (params.rest_length_m - (up - radii) @ weights,
            params.rest_length_m - (down - radii) @ weights)


# --- asymmetric: Duhem ----------------------------------------------------------------------

@dataclass(frozen=True)
class EnvelopeParams:
    """L(p) = rest - stroke * (F(p) - F(0)), F a two-component cumulative Gaussian mixture."""

    stroke_m: float
    mix: float
    centre1_pa: float
    sd1_pa: float
    centre2_pa: float
    sd2_pa: float

    def fraction(self, pressure_pa: float) -> float:
        def cdf(centre, sd):
            return 0.5 * (math.erf((pressure_pa - centre) / (sd * math.sqrt(2.0)))
                          - math.erf(-centre / (sd * math.sqrt(2.0))))

        return ((1.0 - self.mix) * cdf(self.centre1_pa, self.sd1_pa)
                + self.mix * cdf(self.centre2_pa, self.sd2_pa))


@dataclass(frozen=True)
class DuhemParams:
    """Envelopes for rising and falling pressure and how fast the length moves between them.

    The state is the length's place in the band between the envelopes,
    u = (L - falling(p)) / (rising(p) - falling(p)). Rising pressure drives u toward 1 (the
    rising envelope) as 1 - u ~ exp(-travelled / rising_scale_pa), falling pressure toward
    0 as u ~ exp(-travelled / falling_scale_pa); the length never moves against the
    pressure (it holds instead). Both envelopes start at the rest length, so every loop
    closes at 0 Pa.
    """

    rest_length_m: float
    rising: EnvelopeParams
    falling: EnvelopeParams
    rising_scale_pa: float
    falling_scale_pa: float


class DuhemMuscle:
    """The `asymmetric` family (see DuhemParams); rate-independent, sub-stepped in pressure."""

    def __init__(self, params: DuhemParams):
        self.params = params
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return self.params.rest_length_m

    def reset(self) -> None:
        self._pressure = 0.0
        self._band_fraction = 0.0   # a muscle vented long ago sits on the falling envelope
        self.length_m = self.params.rest_length_m

    def envelope_m(self, pressure_pa: float, rising: bool) -> float:
        envelope = self.params.rising if rising else self.params.falling
        return self.params.rest_length_m - envelope.stroke_m * envelope.fraction(pressure_pa)

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        target = max(0.0, float(pressure_pa))
        steps = math.ceil(abs(target - self._pressure) / DUHEM_SUBSTEP_PA)
        start = self._pressure
        for k in range(1, steps + 1):
            self._step(start + (target - start) * k / steps)
        return self.length_m

    def _step(self, pressure_pa: float) -> None:
        rising = pressure_pa > self._pressure
        travelled = abs(pressure_pa - self._pressure)
        if rising:
            fraction = 1.0 - (1.0 - self._band_fraction) * math.exp(
                -travelled / self.params.rising_scale_pa)
        else:
            fraction = self._band_fraction * math.exp(-travelled / self.params.falling_scale_pa)
        low = self.envelope_m(pressure_pa, rising=False)
        band = self.envelope_m(pressure_pa, rising=True) - low
        moved = low + fraction * band
        self.length_m = min(self.length_m, moved) if rising else max(self.length_m, moved)
        if band > 1e-9:   # a held length keeps its own place in the band
            fraction = (self.length_m - low) / band
        self._band_fraction = fraction
        self._pressure = pressure_pa


def duhem_major_loop_m(params: DuhemParams, pressures_pa) -> tuple[np.ndarray, np.ndarray]:
    """(increasing, decreasing) lengths of the steady 0 -> max -> 0 loop at `pressures_pa`.

    Two conditioning cycles first: a Duhem loop settles onto its limit cycle.
    """
    pressures_pa = np.asarray(pressures_pa, dtype=float)
    top = float(pressures_pa.max())
    muscle = DuhemMuscle(params)
    for _ in range(2):
        muscle.update(top)
        muscle.update(0.0)
    up, down = [], []
    for p in pressures_pa:
        up.append(muscle.update(p))
    for p in pressures_pa[::-1]:
        down.append(muscle.update(p))
    return np.array(up), np.array(down[::-1])


# --- creep (viscoelastic element in series) --------------------------------------------------

@dataclass(frozen=True)
class CreepParams:
    """A share of every length change arrives through a first-order lag of time constant tau."""

    share: float
    time_constant_s: float


class _Wrapped:
    """A muscle that changes what `inner` does (creep, drift); `inner` keeps the rest length."""

    def __init__(self, inner: Muscle):
        self.inner = inner
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return self.inner.rest_length_m

    def reset(self) -> None:
        self.inner.reset()
        self.length_m = self.inner.length_m
        self._restart()

    def _restart(self) -> None:
        """Reset the wrapper's own state (the inner muscle is already relaxed)."""


class CreepMuscle(_Wrapped):
    """`inner`'s length, part of it lagged: length = static + share * (lagged - static)."""

    def __init__(self, inner: Muscle, params: CreepParams):
        self.params = params
        super().__init__(inner)

    def _restart(self) -> None:
        self._static = self._lagged = self.length_m
        self._time = None

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        t_s = float(t_s)
        if self._time is not None and t_s < self._time:
            raise ValueError(f'time went back: {t_s} s after {self._time} s')
        dt = 0.0 if self._time is None else t_s - self._time
        static = self.inner.update(pressure_pa, t_s)
        tau = self.params.time_constant_s
        if dt > 0.0:
            # Exact for a static length that moves linearly over the step.
            slope = (static - self._static) / dt
            decay = math.exp(-dt / tau)
            self._lagged = static - slope * tau + (self._lagged - self._static
                                                   + slope * tau) * decay
        self._static, self._time = static, t_s
        self.length_m = static + self.params.share * (self._lagged - static)
        return self.length_m


# --- drift (temperature, wear) ---------------------------------------------------------------

@dataclass(frozen=True)
class DriftSpec:
    """From `start_s` on, rest length and stroke move to rest + shift and stroke * gain.

    They approach their new values exponentially with `time_constant_s` (a muscle warming
    up). The defaults are the drift of the modelling guide's adaptation experiment.
    """

    shift_m: float = 0.0015
    gain: float = 1.08
    time_constant_s: float = 30.0
    start_s: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.shift_m) and abs(self.shift_m) <= 0.01):
            raise ValueError(f'shift_m must be within +/-0.01 m, got {self.shift_m!r}')
        if not (math.isfinite(self.gain) and 0.5 <= self.gain <= 2.0):
            raise ValueError(f'gain must be within 0.5..2, got {self.gain!r}')
        if not self.time_constant_s > 0:
            raise ValueError(f'time_constant_s must be > 0, got {self.time_constant_s!r}')

    def progress(self, t_s: float) -> float:
        """0 before start_s, rising toward 1."""
        if t_s <= self.start_s:
            return 0.0
        return -math.expm1(-(t_s - self.start_s) / self.time_constant_s)

    def drifted(self, length_m: float, rest_length_m: float, t_s: float) -> float:
        """What a muscle of length `length_m` without drift measures at t_s with it."""
        done = self.progress(float(t_s))
        gain = 1.0 + done * (self.gain - 1.0)
        return rest_length_m + done * self.shift_m + gain * (length_m - rest_length_m)


class DriftingMuscle(_Wrapped):
    """`inner` with its rest length shifted and its stroke scaled as DriftSpec says."""

    def __init__(self, inner: Muscle, drift: DriftSpec):
        self.drift = drift
        super().__init__(inner)

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        inner = self.inner.update(pressure_pa, t_s)
        self.length_m = self.drift.drifted(inner, self.inner.rest_length_m, t_s)
        return self.length_m


# --- the fitted parameters of the simulator's own families ----------------------------------

def wide_params() -> PlayParams:
    fit = dict(family_fits.WIDE)
    return PlayParams(radii=tuple(fit.pop('radii')), weights_m=tuple(fit.pop('weights_m')),
                      **fit)


def asymmetric_params() -> DuhemParams:
    fit = dict(family_fits.ASYMMETRIC)
    return DuhemParams(rising=EnvelopeParams(**fit.pop('rising')),
                       falling=EnvelopeParams(**fit.pop('falling')), **fit)
