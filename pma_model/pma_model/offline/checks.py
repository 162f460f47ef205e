"""What refit fits, checked: the sweep's levels, their branches, the rest length (no ROS here).

A refit is only as good as the levels it is given. A sweep that started pressurised (the
muscle at 200 kPa) puts its first 0 kPa level on the decreasing branch: the increasing
branch then starts at 100 kPa and the paper's fixed L0 (the length at the lowest increasing
level) is the length at 100 kPa, 0.85 cm short, and nothing else in the report shows it.
These checks say so, each as one warning (`DataWarning`):

- `rest_level_missing`: the increasing branch has no level within NEAR_ZERO_PA of 0 kPa;
- `top_level_missing`: the decreasing branch has no level within one step (the sweep's level
  spacing, at least the detector's deadband) plus NEAR_ZERO_PA of the top;
- `started_pressurised`: the recording (or the sweep's START record) begins above
  NEAR_ZERO_PA: what came before its first level is unknown;
- `wrong_branch`: a level the muscle reached from the other side than its place in the sweep
  says (before the top, or a level at 0 kPa before the top: rising; after a higher level:
  falling), or that the fit put on the other branch;
- `rest_length`: a branch model's fitted L0 (increasing branch) is further from every length
  measured at rest (0 kPa levels, the recording's first samples at rest) than the sensor's
  noise allows (`noise_tolerance`);
- `too_few_levels`: a branch has no more distinct pressure levels than a model fitted to it
  has free parameters (the curve then passes through every level: its statistics say
  nothing);
- `not_settled`: a level the sweep itself flagged as not settled (SweepRecord LEVEL records,
  `settled` false); only with records: levels derived from the trace skip it.

Levels come from the sweep's LEVEL records when the bag has them (`levels_from_records`),
else from the holds of the pressure trace, as the refit's steady-state reduction finds them
(`derive_levels`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from pma_model import units
from pma_model.detector import BRANCH_INCREASING, detect_branches

# A level within this of 0 kPa is "at rest": the valve regulation band is +/-5 kPa and the
# smallest staircase step in use is 25 kPa, so 20 kPa holds every 0 kPa level and no other.
NEAR_ZERO_PA = 20_000.0
# Distinct pressure levels: hold means within this of each other are one level (the same as
# report.LEVEL_GAP_PA: the +/-5 kPa regulation band, with margin).
LEVEL_GAP_PA = 12_000.0
# The HC-SR04's noise (1 sigma) and its reading step, used when the data cannot tell (a
# branch table has no samples).
NOMINAL_NOISE_M = 1.5e-3
NOMINAL_STEP_M = 3.0e-3
# A fitted L0 further than this many single-reading sigmas from a measured rest length is no
# noise: the rest length is a mean of many readings, its own error is sigma / sqrt(n).
NOISE_SIGMAS = 3.0
# The first samples of a recording count as "at rest" for at most this long.
REST_START_S = 2.0

RISING, FALLING, NONE = 1, -1, 0
_SIDE = {RISING: 'increasing', FALLING: 'decreasing'}
_APPROACH = {RISING: 'from below', FALLING: 'from above', NONE: 'without a change'}

CHECKS = ('rest_level_missing', 'top_level_missing', 'started_pressurised', 'wrong_branch',
          'rest_length', 'too_few_levels', 'not_settled')


@dataclass
class Level:
    """One held pressure level of a sweep, as the checks see it (SI; times from the samples'
    time origin)."""

    index: int
    target_pa: float            # the setpoint (or, without one, the held pressure)
    reached_pa: float           # mean measured pressure over the settled part
    origin_pa: float            # the pressure it was reached from (nan: unknown)
    length_m: float             # mean length over the settled part (nan: no samples)
    approach: int               # RISING (from below), FALLING (from above), NONE
    fit_branch: int | None      # the branch the fit put it on (RISING/FALLING), None: unknown
    settled: bool | None = None  # the sweep's verdict (records), None: not known
    note: str = ''
    start_s: float = math.nan
    end_s: float = math.nan


@dataclass
class SweepLevelRecord:
    """A SweepRecord LEVEL record, ROS-free (times: the driver's clock, seconds)."""

    level_index: int
    level_count: int
    target_pa: float
    reached_pa: float
    branch: int                 # SweepRecord.BRANCH_*: 0 rest, 1 rising, -1 falling
    settled: bool
    hold_start_s: float
    hold_end_s: float
    message: str = ''
    sweep_id: str = ''


@dataclass
class SweepStartRecord:
    started_at_rest: bool
    start_pa: float
    sweep_id: str = ''


@dataclass
class DataWarning:
    check: str
    message: str
    level: int | None = None

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


def _kpa(value_pa: float) -> str:
    return f'{units.pa_to_kpa(value_pa):.0f} kPa'


def _approach(origin_pa: float, target_pa: float, band_pa: float) -> int:
    if not math.isfinite(origin_pa):
        return NONE
    if origin_pa > target_pa + band_pa:
        return FALLING
    if origin_pa < target_pa - band_pa:
        return RISING
    return NONE


def _label(labels: np.ndarray, index: int) -> int:
    return RISING if labels[index] == BRANCH_INCREASING else FALLING


def derive_levels(time_s, pressure_pa, length_m, *, setpoint_pa,
                  runs: Sequence[tuple[int, int]], deadband_pa: float,
                  steady_fraction: float = 0.5) -> list[Level]:
    """Levels from hold runs ([start, end) sample ranges, as samples.hold_runs finds them on
    the setpoint or the pressure): the target is the held setpoint (or pressure), the level's
    pressure and length the means of its settled part (the last `steady_fraction`), its
    origin the pressure where the previous level ended (the recording's first sample for
    the first), its fit branch the detector's label at its end, as the refit labels it."""
    pressure_pa = np.asarray(pressure_pa, float)
    labels = detect_branches(pressure_pa, deadband_pa)
    levels = []
    previous_end = 0
    for index, (start, end) in enumerate(runs):
        settled = slice(start + int((end - start) * (1 - steady_fraction)), end)
        target = (float(np.median(setpoint_pa[start:end])) if setpoint_pa is not None
                  else float(np.mean(pressure_pa[settled])))
        if setpoint_pa is not None and start > 0:   # just before its setpoint was given
            origin = float(pressure_pa[start - 1])
        elif index > 0:                             # where the previous level ended
            origin = float(pressure_pa[previous_end - 1])
        else:
            origin = float(pressure_pa[0])
        levels.append(Level(index, target, float(np.mean(pressure_pa[settled])), origin,
                            float(np.mean(length_m[settled])),
                            _approach(origin, target, deadband_pa), _label(labels, end - 1),
                            start_s=float(time_s[start]), end_s=float(time_s[end - 1])))
        previous_end = end
    return levels


def levels_from_records(records: Sequence[SweepLevelRecord], time_s, pressure_pa, length_m,
                        *, time_origin_s: float, deadband_pa: float,
                        start_pa: float | None = None, setpoint_pa=None,
                        steady_fraction: float = 0.5) -> list[Level]:
    """Levels from the sweep's own LEVEL records: target, reached pressure, branch (how it
    was reached: rest counts as none) and settled are the driver's; the length is the mean
    over the hold window's last `steady_fraction` (only the samples whose recorded setpoint
    is the level's, when `setpoint_pa` is given: the record's end may come after the next
    setpoint), the fit branch the detector's label in its middle (a window without samples
    gives NaN and None), the origin the pressure at the previous hold's end (the first
    level's: `start_pa`, the START record's, else the recording's first sample)."""
    time_s = np.asarray(time_s, float)
    pressure_pa = np.asarray(pressure_pa, float)
    labels = detect_branches(pressure_pa, deadband_pa) if pressure_pa.size else pressure_pa
    levels = []
    origin = (start_pa if start_pa is not None and math.isfinite(start_pa) else
              float(pressure_pa[0]) if pressure_pa.size else math.nan)
    for position, record in enumerate(sorted(records, key=lambda r: r.hold_start_s)):
        start, end = record.hold_start_s - time_origin_s, record.hold_end_s - time_origin_s
        settled_from = end - (end - start) * steady_fraction
        window = (time_s >= settled_from) & (time_s <= end)
        if setpoint_pa is not None:
            window &= np.abs(np.asarray(setpoint_pa) - record.target_pa) <= 1_000.0
        inside = np.flatnonzero(window)
        length = float(np.mean(length_m[inside])) if inside.size else math.nan
        fit_branch = _label(labels, int(inside[inside.size // 2])) if inside.size else None
        approach = {1: RISING, -1: FALLING}.get(int(record.branch), NONE)
        levels.append(Level(position, float(record.target_pa), float(record.reached_pa), origin,
                            length, approach, fit_branch, bool(record.settled), record.message,
                            start, end))
        until = np.flatnonzero(time_s <= end)
        origin = float(pressure_pa[until[-1]]) if until.size else float(record.reached_pa)
    return levels


def intended_branches(levels: Sequence[Level]) -> list[int]:
    """The branch each level belongs to by its place in the sweep: rising up to the top
    (the first level, and every level at 0 kPa before the top: a sweep starts from rest),
    then by the direction from the level before it (falling after a higher level)."""
    if not levels:
        return []
    top = max(range(len(levels)), key=lambda i: levels[i].target_pa)
    intended = []
    for i, level in enumerate(levels):
        if i == 0 or (i < top and level.target_pa <= NEAR_ZERO_PA):
            intended.append(RISING)
            continue
        change = level.target_pa - levels[i - 1].target_pa
        if abs(change) <= LEVEL_GAP_PA:
            intended.append(intended[-1])
        else:
            intended.append(RISING if change > 0 else FALLING)
    return intended


def distinct_levels(pressure_pa) -> np.ndarray:
    """The distinct pressure levels among these (clusters with no gap over LEVEL_GAP_PA),
    as their means."""
    values = np.sort(np.asarray(pressure_pa, float))
    if values.size == 0:
        return values
    groups = np.concatenate(([0], np.diff(values) > LEVEL_GAP_PA)).cumsum()
    return np.array([values[groups == g].mean() for g in range(groups[-1] + 1)])


def noise_estimate(length_m, runs: Sequence[tuple[int, int]]) -> dict:
    """The length sensor's noise, from the data: the pooled standard deviation of the
    readings about their hold's mean (settled halves), and its reading step when the
    readings sit on a grid; the HC-SR04's nominal figures when no hold has two readings."""
    length_m = np.asarray(length_m, float)
    residuals, diffs = [], []
    for start, end in runs:
        part = length_m[start + (end - start) // 2:end]
        if part.size >= 2:
            residuals.append(part - part.mean())
            diffs.append(np.abs(np.diff(part)))
    if not residuals:
        sigma, step, source = NOMINAL_NOISE_M, NOMINAL_STEP_M, 'nominal HC-SR04 (no holds)'
    else:
        pooled = np.concatenate(residuals)
        dof = pooled.size - len(residuals)
        sigma = float(np.sqrt(np.sum(pooled ** 2) / dof)) if dof > 0 else NOMINAL_NOISE_M
        step, source = _reading_step(np.concatenate(diffs)), 'the holds\' readings'
    tolerance = max(NOISE_SIGMAS * sigma, step)
    return {'sigma_cm': float(units.m_to_cm(sigma)), 'step_cm': float(units.m_to_cm(step)),
            'tolerance_cm': float(units.m_to_cm(tolerance)), 'from': source,
            'rule': f'max({NOISE_SIGMAS:g} sigma, reading step)'}


def _reading_step(diffs: np.ndarray) -> float:
    """The grid the readings sit on (the smallest non-zero change, when at least 90 % of the
    changes are whole multiples of it), 0 when they do not."""
    changes = diffs[diffs > 1e-7]
    if changes.size < 5:
        return 0.0
    step = float(changes.min())
    multiples = changes / step
    on_grid = np.abs(multiples - np.round(multiples)) < 0.02
    return step if np.mean(on_grid) >= 0.9 else 0.0


@dataclass
class FitView:
    """What the checks need of the fit: the branch points it used and the models' L0 and k."""

    inc_pressure_pa: np.ndarray
    dec_pressure_pa: np.ndarray
    l0_m: Mapping[str, float]           # {model: fitted L0 of its increasing branch}
    k_branch: Mapping[str, int]         # {model: free parameters per branch}


def check(fit: FitView, levels: Sequence[Level] | None, *, deadband_pa: float,
          noise: dict, rest: Sequence[tuple[str, float]] = (),
          start: SweepStartRecord | None = None, first_pressure_pa: float | None = None,
          from_records: bool = False) -> list[DataWarning]:
    """Every check's warnings (module docstring). `levels`: None for a branch table (no
    trace); `rest`: (what, length) of every length measured at rest (`rest_lengths`);
    `first_pressure_pa`: the recording's first pressure (None: no trace)."""
    found: list[DataWarning] = []
    every = np.concatenate([fit.inc_pressure_pa, fit.dec_pressure_pa])
    spacing = distinct_levels(every)
    step = float(np.median(np.diff(spacing))) if spacing.size > 1 else 0.0
    if fit.inc_pressure_pa.size and fit.inc_pressure_pa.min() > NEAR_ZERO_PA:
        found.append(DataWarning('rest_level_missing', (
            f'the increasing branch has no level near 0 kPa (its lowest is '
            f'{_kpa(fit.inc_pressure_pa.min())}): its L0 is not the rest length')))
    margin = max(step, deadband_pa) + NEAR_ZERO_PA
    if fit.dec_pressure_pa.size and fit.dec_pressure_pa.max() < every.max() - margin:
        found.append(DataWarning('top_level_missing', (
            f'the decreasing branch has no level near the top ({_kpa(every.max())}): its '
            f'highest is {_kpa(fit.dec_pressure_pa.max())}, more than a step '
            f'({_kpa(margin - NEAR_ZERO_PA)}) below')))
    if start is not None and not start.started_at_rest:
        at = f', at {_kpa(start.start_pa)}' if math.isfinite(start.start_pa) else ''
        found.append(DataWarning('started_pressurised', (
            f'the sweep started pressurised{at}: its first levels were reached from above')))
    elif start is None and first_pressure_pa is not None and first_pressure_pa > NEAR_ZERO_PA:
        found.append(DataWarning('started_pressurised', (
            f'the recording starts at {_kpa(first_pressure_pa)}, not at rest: the muscle was '
            'pressurised before the sweep\'s first level')))
    if levels:
        found += _wrong_branches(levels)
    found += _rest_length(fit, rest, noise)
    found += _too_few_levels(fit)
    if from_records and levels:
        for level in levels:
            if level.settled is False:
                found.append(DataWarning('not_settled', (
                    f'level {level.index + 1} ({_kpa(level.target_pa)}, reached '
                    f'{_kpa(level.reached_pa)}) was not settled, the sweep says'
                    + (f': {level.note.removeprefix("not settled: ")}' if level.note else '')),
                    level.index))
    return found


def _wrong_branches(levels: Sequence[Level]) -> list[DataWarning]:
    found = []
    for level, intended in zip(levels, intended_branches(levels), strict=True):
        reasons = []
        if level.approach not in (NONE, intended):
            origin = (f' (from {_kpa(level.origin_pa)})' if math.isfinite(level.origin_pa)
                      else '')
            reasons.append(f'reached {_APPROACH[level.approach]}{origin}')
        if level.fit_branch is not None and level.fit_branch != intended:
            reasons.append(f'the fit put it on the {_SIDE[level.fit_branch]} branch')
        if reasons:
            where = ('as a level at rest before the top' if intended == RISING and
                     level.target_pa <= NEAR_ZERO_PA else 'by its place in the sweep')
            found.append(DataWarning('wrong_branch', (
                f'level {level.index + 1} ({_kpa(level.target_pa)}): ' + ' and '.join(reasons)
                + f'; {where} it belongs on the {_SIDE[intended]} branch'), level.index))
    return found


def rest_lengths(levels: Sequence[Level],
                 rest_start: tuple[float, float] | None = None) -> list[tuple[str, float]]:
    """(what, length) of every length measured at rest: the levels at 0 kPa and the
    recording's first samples at rest (`rest_start`: their mean length and count)."""
    found = [(f'level {level.index + 1}', level.length_m) for level in levels
             if level.reached_pa <= NEAR_ZERO_PA and math.isfinite(level.length_m)]
    if rest_start is not None:
        found.append((f'the first {rest_start[1]:.0f} samples', rest_start[0]))
    return found


def _rest_length(fit: FitView, measured: Sequence[tuple[str, float]],
                 noise: dict) -> list[DataWarning]:
    if not measured or not fit.l0_m:
        return []
    tolerance = units.cm_to_m(noise['tolerance_cm'])
    low = min(value for _, value in measured)
    high = max(value for _, value in measured)
    off = {name: l0 for name, l0 in fit.l0_m.items()
           if l0 < low - tolerance or l0 > high + tolerance}
    if not off:
        return []
    rest = (f'{units.m_to_cm(low):.2f} cm' if high - low < 5e-5 else
            f'{units.m_to_cm(low):.2f}-{units.m_to_cm(high):.2f} cm')
    models = ', '.join(f'{name} {units.m_to_cm(l0):.2f} cm' for name, l0 in off.items())
    return [DataWarning('rest_length', (
        f'fitted L0 ({models}) differs from the length measured at rest ({rest}: '
        f'{", ".join(what for what, _ in measured)}) by more than the sensor noise allows '
        f'({noise["tolerance_cm"]:.2f} cm)'))]


def _too_few_levels(fit: FitView) -> list[DataWarning]:
    found = []
    for direction, pressures in (('increasing', fit.inc_pressure_pa),
                                 ('decreasing', fit.dec_pressure_pa)):
        count = distinct_levels(pressures).size
        short = sorted(f'{name} ({k})' for name, k in fit.k_branch.items() if k >= count)
        if short:
            found.append(DataWarning('too_few_levels', (
                f'the {direction} branch has {count} pressure levels, no more than the free '
                f'parameters of {", ".join(short)}: the fit passes through every level and '
                'its statistics say nothing')))
    return found
