"""Reversal-rich pressure paths and what the rig's sensors report along them (ROS-free).

For experiments that need many minutes of minor loops without stepping the whole device at
1 ms: the pressure follows ramps between turning points (at a slew rate the valves can
reach) with holds at each, sampled at the driver's rate; the muscle sees the true pressure
and time, and the readings come from the rig's own sensor models (`Rig.read_echo_us`, the
device's 4-conversion pressure reading) converted back as the driver converts them.

- `nested_turns`: groups of loops that close inside each other (a deep turning-point stack),
  each group wiped out by an excursion to 0 Pa or the top;
- `random_turns`: turning points drawn uniformly, so loops nest, cross and wipe each other out;
- `smooth_path`: no ramps and no holds, the other way a rig is driven: a sum of sines
  (`sines`) or a decaying sine restarted at full swing (`damped`), slowing down into every
  reversal, at most as fast as the ramps.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_sim.device import DeviceConfig, Rig, SimDevice
from pma_sim.families import Muscle

TOP_PA = 500_000.0
MAX_SLEW_PA_PER_S = 250e3   # the ramps' fastest: what the valves reach
SMOOTH_KINDS = ('sines', 'damped')


@dataclass(frozen=True)
class PressurePath:
    """Gauge pressure [Pa] at sample times [s], and when the pressure reverses.

    `reversal_times_s`: the times each reversal's turning point is reached (its hold starts).
    """

    time_s: np.ndarray
    pressure_pa: np.ndarray
    turns_pa: tuple[float, ...]
    reversal_times_s: np.ndarray


def ramp_path(turns_pa, rate_hz: float = 50.0, slew_pa_per_s=(80e3, MAX_SLEW_PA_PER_S),
              hold_s=(0.3, 1.5), seed: int = 0) -> PressurePath:
    """Straight ramps between the turning points, each at a random slew rate within
    `slew_pa_per_s`, and a hold of random length within `hold_s` at every turning point."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    turns = [float(turn) for turn in turns_pa]
    pieces = [np.full(max(1, round(rng.uniform(*hold_s) * rate_hz)), turns[0])]
    arrivals = []
    for start, end in itertools.pairwise(turns):
        duration = abs(end - start) / rng.uniform(*slew_pa_per_s)
        count = max(1, round(duration / dt))
        pieces.append(np.linspace(start, end, count + 1)[1:])
        arrivals.append(sum(piece.size for piece in pieces) - 1)
        pieces.append(np.full(max(1, round(rng.uniform(*hold_s) * rate_hz)), end))
    pressure = np.concatenate(pieces)
    reversals = [index for k, index in enumerate(arrivals[:-1], start=1)
                 if (turns[k] - turns[k - 1]) * (turns[k + 1] - turns[k]) < 0]
    return PressurePath(np.arange(pressure.size) * dt, pressure, tuple(turns),
                        np.array(reversals, dtype=int) * dt)


def nested_turns(duration_s: float = 180.0, seed: int = 0, top_pa: float = TOP_PA,
                 mean_slew_pa_per_s: float = 165e3, mean_hold_s: float = 0.9) -> list[float]:
    """Turning points of nested loops: each new turn goes 30-70 % of the way back toward
    the previous opposite turn, 4-8 turns per group, then 0 Pa or the top wipes them out."""
    rng = np.random.default_rng(seed)
    turns = [0.0]
    elapsed = 0.0
    while elapsed < duration_s:
        high, low = rng.uniform(0.55, 1.0) * top_pa, rng.uniform(0.0, 0.3) * top_pa
        group = [high, low]
        for _ in range(rng.integers(4, 9)):
            group.append(group[-1] + rng.uniform(0.3, 0.7) * (group[-2] - group[-1]))
        group.append(0.0 if rng.random() < 0.5 else top_pa)
        for turn in group:
            elapsed += abs(turn - turns[-1]) / mean_slew_pa_per_s + mean_hold_s
            turns.append(float(turn))
    return turns if turns[-1] == 0.0 else [*turns, 0.0]


def random_turns(duration_s: float = 180.0, seed: int = 0, top_pa: float = TOP_PA,
                 mean_slew_pa_per_s: float = 165e3, mean_hold_s: float = 0.9) -> list[float]:
    """Turning points drawn uniformly in 0..top, alternating up and down."""
    rng = np.random.default_rng(seed)
    turns = [0.0]
    elapsed = 0.0
    while elapsed < duration_s:
        rising = len(turns) % 2 == 1
        turn = rng.uniform(turns[-1], top_pa) if rising else rng.uniform(0.0, turns[-1])
        elapsed += abs(turn - turns[-1]) / mean_slew_pa_per_s + mean_hold_s
        turns.append(float(turn))
    return [*turns, 0.0]


def smooth_path(kind: str, duration_s: float = 180.0, seed: int = 0, rate_hz: float = 50.0,
                *, top_pa: float = TOP_PA,
                max_slew_pa_per_s: float = MAX_SLEW_PA_PER_S) -> PressurePath:
    """A smooth reversal-rich path: `sines` (three sines of random periods and phases,
    0.02-0.98 of `top_pa`) or `damped` (a sine about a random centre whose swing decays over
    3-6 periods, restarted at full swing every 12 periods).

    Drawn in a time of its own after a ramp up from 0 Pa, then slowed so that its fastest
    change is `max_slew_pa_per_s` (never sped up). The reversals are the true pressure's
    extrema.
    """
    if kind not in SMOOTH_KINDS:
        raise ValueError(f'{kind!r}: a smooth path is one of {", ".join(SMOOTH_KINDS)}')
    rng = np.random.default_rng(seed)
    own_dt = 1e-3
    own_time = np.arange(0.0, duration_s, own_dt)
    if kind == 'sines':
        pressure = np.zeros_like(own_time)
        for _ in range(3):
            pressure += rng.uniform(0.5, 1.0) * np.sin(
                2.0 * np.pi * own_time / rng.uniform(1.5, 12.0) + rng.uniform(0.0, 2.0 * np.pi))
        pressure = top_pa * (0.5 + 0.48 * pressure / np.max(np.abs(pressure)))
    else:
        period = rng.uniform(2.5, 5.0)
        phase = own_time % (12.0 * period)
        centre = rng.uniform(0.3, 0.6) * top_pa
        swing = min(centre, 0.98 * top_pa - centre)
        pressure = centre + swing * np.exp(-phase / (rng.uniform(3.0, 6.0) * period)) * np.sin(
            2.0 * np.pi * phase / period)
    lead_in = np.arange(0.0, pressure[0], max_slew_pa_per_s * own_dt)   # from rest, 0 Pa
    pressure = np.concatenate((lead_in, pressure))[:own_time.size]
    stretch = max(1.0, float(np.max(np.abs(np.diff(pressure)))) / own_dt / max_slew_pa_per_s)
    time_s = np.arange(round(duration_s * rate_hz)) / rate_hz
    pressure = np.clip(np.interp(time_s / stretch, own_time, pressure), 0.0, top_pa)
    direction = np.sign(np.diff(pressure))
    moving = np.flatnonzero(direction)
    changed = np.flatnonzero(direction[moving[1:]] != direction[moving[:-1]])
    turns = moving[changed] + 1   # where the pressure arrives at each extremum
    return PressurePath(time_s, pressure, tuple(float(p) for p in pressure[turns]),
                        time_s[turns])


@dataclass(frozen=True)
class Run:
    """One simulated run: truth and what the driver would publish, per sample."""

    time_s: np.ndarray
    pressure_pa: np.ndarray            # true gauge pressure
    length_m: np.ndarray               # true length
    measured_pressure_pa: np.ndarray   # as the driver converts the device's reading
    measured_length_m: np.ndarray      # as the driver converts the echo (NaN: no echo)
    reversal_times_s: np.ndarray


def simulate(muscle: Muscle, path: PressurePath, config: DeviceConfig | None = None,
             seed: int = 0) -> Run:
    """Drive `muscle` along `path` (from its current state) and read the rig's sensors."""
    config = config or DeviceConfig(seed=seed)
    rig = Rig(config, muscle=muscle)
    device = SimDevice(config, rig)
    pressure_calibration, length_calibration = PressureCalibration(), LengthCalibration()
    lengths = np.empty(path.pressure_pa.size)
    measured_p = np.empty_like(lengths)
    measured_l = np.empty_like(lengths)
    for i, (t, p) in enumerate(zip(path.time_s, path.pressure_pa, strict=True)):
        rig.pneumatics.pressure_pa = float(p)   # the path is the pressure: no valve model
        rig.time_s = float(t)
        lengths[i] = muscle.update(float(p), float(t))
        measured_p[i] = pressure_calibration.adc_to_pa(device.read_pressure_adc())
        measured_l[i] = length_calibration.echo_to_length_m(rig.read_echo_us())
    return Run(path.time_s, path.pressure_pa, lengths, measured_p, measured_l,
               path.reversal_times_s)
