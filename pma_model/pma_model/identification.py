"""Online identification: learn which muscle this is from the lengths the model already sees.

One major loop (Table 1) fixes the branches only roughly and says nothing about minor loops,
so the model keeps learning, sample by sample, three things about the muscle and two about
its state (docs/model.md, "Online identification"):

- the minor-loop rule: the play share of the 'identify' memory for rising and for falling
  pressure (0 = Madelung, 1 = hold-then-branch; memory.py), and how it changes with where
  the reversal lies across the loop (the slope). The prediction is linear in both, with
  regressor (play-like - Madelung) length on the current scanning curve, so each
  direction's pair is a recursive least-squares estimate, kept so that every curve's share
  is within 0..1: a continuous memory parameter between the two rules, whose regret
  against the best fixed pair grows only logarithmically. It learns only where the shapes
  differ: after reversals.
- the branch shape: a correction delta(P) given at knots every 50 kPa and at 75 kPa
  (CORRECTION_KNOTS_PA), added inside both branches (CorrectedBranch) so every memory rule
  uses it and keeps its continuity and return-point memory. Between knots it follows the
  branch's own length, so it can flatten the sigmoid's dead zone and still invert in closed
  form. It is learned as a mean for both branches plus a difference (increasing minus
  decreasing, half added to each): the paper's two sigmoids miss a muscle in different
  places (on the simulated families the two branches' misfits differ by up to 3.4 mm at a
  knot), which a mean cannot follow. The knots learn through the exact derivative of the
  length (HysteresisModel.length_gradient): on a scanning curve the length is pinned to
  turning points that came from earlier curves, often of the other branch, so a residual
  there says something about both. The difference has a tighter prior (DIFFERENCE_PRIOR_M; a
  loose one trades off against the play shares: docs/model.md §5).
- creep: length = static + sum_j k_j (lag_j(static) - static), the model's static length
  through first-order lags of CREEP_TIME_CONSTANTS_S: a share of each change arriving late,
  which vanishes in a hold (so the inverse, a steady-state answer, ignores it; a controller
  that must be at a length now aims its inverse through settled_aim_m instead).
- a rested muscle's first loading (its virgin curve), which may lie off the loop it settles
  into: a term of the pressure travelled since start, gone once the muscle has travelled
  VIRGIN_END_PA, so that loading is not learned as the rising branch.
- drift (adaptation.enabled): rest-length shift and stroke gain (adaptation.Drift).

delta, the creep gains, the virgin term and the drift are one Kalman filter (random walks:
delta and creep nearly static, drift moving over adaptation.time_constant_s; drift starts at
0 with no prior spread, so how the muscle differs from Table 1 is learned as shape and later
change as drift). Its measurement noise is the sensor's, also after a reversal: the exact
derivative says which knots, turning points and share a residual there belongs to, and
trusting those samples less only slowed learning (docs/model-history.md).
Only where drift alone learns (identification off) is a residual the memory could explain
trusted less, by how far the two memory shapes disagree: nothing else could take it up.
The learned numbers are applied to the memory model when they have moved enough to matter
(COMMIT_M, COMMIT_SHARE), by replaying the remembered turning points: the state stays a
function of the pressure history and the learned numbers.

`OnlineModel.step` is one compiled call (kernel.online_step) on the state packed into arrays
(`_pack`) for the rules in KERNEL_RULES; `reference_step` is the same in Python, what the
compiled step is tested against and the step of the other rules.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import ClassVar, Protocol

import numpy as np

from pma_model import kernel
from pma_model.adaptation import AdaptationSettings, Drift
from pma_model.branches import DEFAULT_MAX_GAUGE_PRESSURE_PA, Branch
from pma_model.correction import (
    CORRECTION_KNOTS_PA,
    DECREASING_KNOTS,
    INCREASING_KNOTS,
    MAX_CORRECTION_M,
    MAX_DIFFERENCE_M,
    CorrectedBranch,
    correction_caps,
    knot_row,
    knot_sensitivity,
    monotone_correction,
)
from pma_model.curves import FLAT_SPAN_M, MID_DEPTH, play_share_at
from pma_model.detector import (
    BRANCH_AUTO,
    BRANCH_DECREASING,
    BRANCH_INCREASING,
    DEFAULT_DEADBAND_PA,
)
from pma_model.memory import (
    MAX_TURNING_POINTS,
    NARROW_LOOP_M,
    HysteresisModel,
    InverseResult,
    PathState,
)

CREEP_TIME_CONSTANTS_S = (0.5, 2.0)
MAX_CREEP_GAIN = 1.0
ROUNDING_M = 1e-12           # a bound missed by less than this is met (float rounding)
# Far beyond any loss difference of the mix (errors are capped at adaptation.outlier_m, at
# most 0.05 m, and forgotten over 100 s: 0.25 m^2 s).
MAX_EXCESS_LOSS_M2S = 1.0
# Drift alone learning (identification off): memory shapes this far apart halve a sample's
# weight (quarter R), down to SPREAD_FLOOR (a sample is never worth nothing).
SPREAD_SCALE_M = 0.0005
SPREAD_FLOOR = 1e-3
COMMIT_M = 2e-5              # apply learned branch changes once they move 0.02 mm somewhere
COMMIT_SHARE = 0.01          # or a share or its slope by this much
MAX_STEP_S = 1.0             # a longer gap between samples counts as this (a pause)
GAIN_WALK_LENGTH_M = 0.03    # the gain may move as fast as the shift does at this |L - L_ref|

# Kalman filter priors (standard deviations) and random-walk rates (per second).
# The priors were chosen by measurement; the figures are in docs/model-history.md ("The
# constants' figures").
# The branch difference's prior: looser, it trades off against the play shares.
DIFFERENCE_PRIOR_M = 0.001
# The mean correction's prior: about the size of what it has to learn (how far Table 1's
# branches miss the simulated muscles). A wider one lets a few noisy samples near a knot the
# path has barely reached move it by millimetres, and the first excursion past that pressure
# errs by as much.
CORRECTION_PRIOR_M = 0.002
# Drift has none: it starts at 0 (OnlineModel._new_filter).
# The first loading of a rested muscle (its virgin curve) can lie off the loop it settles into
# (the Bouc-Wen muscle's does). It is learned as its own term, a function of the
# pressure travelled since start given at VIRGIN_TRAVEL_KNOTS_PA and 0 from VIRGIN_END_PA on,
# so the first rise is not learned as the rising branch; once the muscle has travelled that
# far the term is gone and leaves the filter (marginalised: its rows and columns dropped).
VIRGIN_TRAVEL_KNOTS_PA = tuple(float(p) for p in np.linspace(0.0, 400_000.0, 5))
VIRGIN_END_PA = 500_000.0
# On the first loading a virgin offset and a branch misfit look alike; the priors split a
# residual between them until the muscle comes back: a wide prior costs the muscles without a
# virgin curve, a narrow one gives up most of the gain on the one with.
VIRGIN_PRIOR_M = 0.001
_PRIOR = {'correction': CORRECTION_PRIOR_M, 'difference': DIFFERENCE_PRIOR_M, 'creep': 0.5,
          'share': 1.0, 'share_slope': 0.5}
_PRIOR_RESUMED = {'correction': 0.001, 'difference': 0.0005, 'creep': 0.1, 'share': 0.2,
                  'share_slope': 0.1}
_WALK_PER_S = {'correction': 1e-5, 'creep': 1e-3, 'share': 0.003, 'share_slope': 0.003}
# The rules whose online step is compiled (kernel.online_step); the others run the Python
# reference (OnlineModel.reference_step), as does a model whose doubt is a second memory.
KERNEL_RULES = {'madelung': kernel.RULE_MADELUNG, 'identify': kernel.RULE_IDENTIFY,
                'play': kernel.RULE_PLAY}
# What the compiled step keeps in its packed state instead (OnlineModel._unpack restores them
# when they are read).
_PACKED_NAMES = frozenset(('_filter', '_shares', '_share_covariance', '_committed_raw',
                           '_committed_shares', '_lag_values', '_time', '_static', 'commits',
                           '_travel_pa', '_play_pa'))


@dataclass(frozen=True)
class IdentificationSettings:
    """Whether to learn, and what has been learned (saved, so a restart resumes it)."""

    enabled: bool = True
    play_share_rising: float = 0.5
    play_share_falling: float = 0.5
    # How each share changes with where the reversal lies across the loop (memory.py,
    # origin_depth): the shares above are those of a reversal mid-loop.
    play_share_slope_rising: float = 0.0
    play_share_slope_falling: float = 0.0
    branch_correction_m: tuple[float, ...] = (0.0,) * len(CORRECTION_KNOTS_PA)
    # Increasing minus decreasing correction: each branch gets the mean plus or minus half.
    branch_difference_m: tuple[float, ...] = (0.0,) * len(CORRECTION_KNOTS_PA)
    creep_gains: tuple[float, ...] = (0.0,) * len(CREEP_TIME_CONSTANTS_S)
    length_noise_m: float = 0.0017   # HC-SR04: 1.5 mm noise and 3 mm steps
    # The 'mix' memory's play rule learns a correction and creep of its own (mix.py);
    # its weight against 'identify' follows how much more squared error it made recently
    # (the weights' whole state, saved exactly: a weight near 0 or 1 would round).
    play_rule_correction_m: tuple[float, ...] = (0.0,) * len(CORRECTION_KNOTS_PA)
    play_rule_difference_m: tuple[float, ...] = (0.0,) * len(CORRECTION_KNOTS_PA)
    play_rule_creep_gains: tuple[float, ...] = (0.0,) * len(CREEP_TIME_CONSTANTS_S)
    play_rule_excess_loss_m2s: float = 0.0

    def __post_init__(self):
        if not isinstance(self.enabled, bool):
            raise ValueError(f'enabled must be true or false, got {self.enabled!r}')
        for name in ('play_share_rising', 'play_share_falling'):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f'{name} must be within 0..1, got {value!r}')
        for name, share in (('play_share_slope_rising', self.play_share_rising),
                            ('play_share_slope_falling', self.play_share_falling)):
            value = getattr(self, name)
            # The share at either end of the loop, share -/+ slope / 2, stays within 0..1.
            if not (math.isfinite(value) and abs(value) <= 2.0 * min(share, 1.0 - share)
                    + ROUNDING_M):
                raise ValueError(f'{name} must keep the share within 0..1 across the loop '
                                 f'(|slope| <= 2 * min(share, 1 - share)), got {value!r}')
        for name, size, limit in (
                ('branch_correction_m', len(CORRECTION_KNOTS_PA), MAX_CORRECTION_M),
                ('branch_difference_m', len(CORRECTION_KNOTS_PA), MAX_DIFFERENCE_M),
                ('creep_gains', len(CREEP_TIME_CONSTANTS_S), MAX_CREEP_GAIN),
                ('play_rule_correction_m', len(CORRECTION_KNOTS_PA), MAX_CORRECTION_M),
                ('play_rule_difference_m', len(CORRECTION_KNOTS_PA), MAX_DIFFERENCE_M),
                ('play_rule_creep_gains', len(CREEP_TIME_CONSTANTS_S), MAX_CREEP_GAIN)):
            object.__setattr__(self, name, _checked_vector(name, getattr(self, name), size,
                                                           limit))
        excess = self.play_rule_excess_loss_m2s
        if not (math.isfinite(excess) and abs(excess) <= MAX_EXCESS_LOSS_M2S):
            raise ValueError(f'play_rule_excess_loss_m2s must be within '
                             f'+/-{MAX_EXCESS_LOSS_M2S} m^2 s, got {excess!r}')
        if not (math.isfinite(self.length_noise_m) and 1e-5 <= self.length_noise_m <= 0.05):
            raise ValueError('length_noise_m must be within 1e-5..0.05 m, '
                             f'got {self.length_noise_m!r}')

    @property
    def play_shares(self) -> tuple[float, float]:
        return self.play_share_rising, self.play_share_falling

    @property
    def share_slopes(self) -> tuple[float, float]:
        return self.play_share_slope_rising, self.play_share_slope_falling

    def share_at(self, rising: bool, depth: float) -> float:
        """The play share a curve gets from a reversal at `depth` across the loop."""
        index = 0 if rising else 1
        return play_share_at(self.play_shares[index], self.share_slopes[index], depth)

    # What identification learns (the rest are settings): saved, published, carried over.
    LEARNED: ClassVar[tuple[str, ...]] = ('play_share_rising', 'play_share_falling',
                                          'play_share_slope_rising',
                                          'play_share_slope_falling',
                                          'branch_correction_m', 'branch_difference_m',
                                          'creep_gains', 'play_rule_correction_m',
                                          'play_rule_difference_m', 'play_rule_creep_gains',
                                          'play_rule_excess_loss_m2s')
    # One OnlineModel's own learned fields, and where the mix's play rule keeps its copy.
    _PLAY_RULE_FIELDS: ClassVar[dict[str, str]] = {
        'branch_correction_m': 'play_rule_correction_m',
        'branch_difference_m': 'play_rule_difference_m',
        'creep_gains': 'play_rule_creep_gains'}

    def learned_values(self) -> dict[str, float | list[float]]:
        """{name: value} of what was learned, vectors as lists (for JSON and YAML)."""
        return {name: list(value) if isinstance(value, tuple) else value
                for name in self.LEARNED for value in (getattr(self, name),)}

    @property
    def learned_anything(self) -> bool:
        """True when an OnlineModel starts from learned numbers (tighter priors)."""
        return any(self.branch_correction_m) or any(self.branch_difference_m) or \
            any(self.creep_gains) or self.play_shares != (0.5, 0.5) or any(self.share_slopes)

    def for_rule(self, rule: str) -> IdentificationSettings:
        """What the mix's OnlineModel for `rule` starts from: the play rule its own
        correction, difference and creep (and the default shares: it has none of its own);
        every other rule these settings as they are."""
        if rule != 'play':
            return self
        default = IdentificationSettings()
        return replace(self, play_share_rising=default.play_share_rising,
                       play_share_falling=default.play_share_falling,
                       play_share_slope_rising=default.play_share_slope_rising,
                       play_share_slope_falling=default.play_share_slope_falling,
                       **{own: getattr(self, copy)
                          for own, copy in self._PLAY_RULE_FIELDS.items()})

    def with_play_rule_learned(self, learned: IdentificationSettings
                               ) -> IdentificationSettings:
        """These settings with what the mix's play rule has learned (`learned`, its own
        OnlineModel's): the inverse of for_rule('play')."""
        return replace(self, **{copy: getattr(learned, own)
                                for own, copy in self._PLAY_RULE_FIELDS.items()})


def _checked_vector(name: str, values, size: int, limit: float) -> tuple[float, ...]:
    try:
        vector = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a list of {size} numbers, got {values!r}') from None
    if len(vector) != size:
        raise ValueError(f'{name} must have {size} values, got {len(vector)}')
    if not all(math.isfinite(v) and abs(v) <= limit for v in vector):
        raise ValueError(f'{name} values must be finite and within +/-{limit}, got {vector}')
    return vector


# --- the online model -----------------------------------------------------------------------

@dataclass(frozen=True)
class Prediction:
    length_m: float          # what the model predicts for this sample (before learning from it)
    branch: int              # the deadband detector's branch code
    static_length_m: float   # the memory model alone (no creep, no drift)
    offset_m: float          # drift correction: length = offset + gain * (static + creep)
    gain: float
    local_offset_m: float = 0.0   # the mix's local offset (local_offset.py), in length_m


class OnlineRule(Protocol):
    """An online model of the memory: OnlineModel (one rule) or mix.RuleMix (rules mixed by
    their recent error, a rule built from rules). What model_node, the length controller and
    the refit use of either."""

    increasing: Branch
    decreasing: Branch
    max_gauge_pressure_pa: float

    def step(self, pressure_pa: float, measured_length_m: float = math.nan,
             t_s: float | None = None) -> Prediction:
        """Predict this sample, then learn from its measured length."""

    def pressure_for_length(self, length_m: float, branch: int = BRANCH_AUTO) -> InverseResult:
        """The pressure at which the muscle settles at length_m (the inverse)."""

    def settled_aim_m(self, length_m: float, max_creep_share: float) -> float:
        """The settled length to ask the inverse for, to be length_m long now."""

    def learned(self) -> IdentificationSettings:
        """What has been learned, as the settings a restart resumes from."""

    def resume_from(self, other: OnlineRule) -> None:
        """Continue `other`'s pressure history with these settings."""

    def weights_by_rule(self) -> dict[str, float]:
        """{rule: weight} of a mix; empty for one rule."""

    def without_local_offset(self) -> OnlineRule:
        """This model without a local offset (for a caller feeding the residual back)."""

    @property
    def experts(self) -> tuple[OnlineModel, ...]:
        """The online models of its rules (one rule: itself)."""

    @property
    def drift(self) -> Drift: ...

    @property
    def branch(self) -> int: ...

    @property
    def samples_learned(self) -> int: ...

    @property
    def samples_rejected(self) -> int: ...

    @property
    def virgin_term_m(self) -> float: ...

    @property
    def first_loading_ended(self) -> bool: ...

    @property
    def local_offset_m(self) -> float:
        """The mix's local offset here (0 for one rule)."""


@dataclass(frozen=True)
class StateBlocks:
    """Where each named block of the filter's state lies: the mean branch correction and the
    branch difference at CORRECTION_KNOTS_PA, the creep gains, the virgin term at
    VIRGIN_TRAVEL_KNOTS_PA (None once it has ended and left the state), drift's shift and
    its gain - 1."""

    correction: slice
    difference: slice
    creep: slice
    virgin: slice | None
    shift: int
    gain: int

    @classmethod
    def laid_out(cls, knots: int, creeps: int, virgins: int) -> StateBlocks:
        """The blocks one after the other in that order (no virgin block if `virgins` is 0)."""
        ends = np.cumsum([knots, knots, creeps, virgins]).tolist()
        return cls(slice(0, ends[0]), slice(ends[0], ends[1]), slice(ends[1], ends[2]),
                   slice(ends[2], ends[3]) if virgins else None, ends[3], ends[3] + 1)

    def without_virgin(self) -> StateBlocks:
        return StateBlocks.laid_out(_length(self.correction), _length(self.creep), 0)

    @property
    def size(self) -> int:
        return self.gain + 1

    @property
    def shape(self) -> slice:
        """The mean correction and the difference: what the branches are built from."""
        return slice(self.correction.start, self.difference.stop)

    @property
    def bounded(self) -> slice:
        """Everything after the mean correction, bounded value by value (_state_bounds); the
        mean correction is kept monotone instead (_project_shape)."""
        return slice(self.correction.stop, self.size)


def _length(block: slice) -> int:
    return block.stop - block.start


@dataclass
class _Filter:
    """Kalman filter over the blocks of `blocks` (StateBlocks)."""

    mean: np.ndarray
    covariance: np.ndarray
    walk_per_s: np.ndarray    # random-walk variance added per second
    blocks: StateBlocks
    samples: int = 0
    rejected: int = 0


@dataclass
class OnlineModel:
    """The memory model plus what it learns online; `step` is the whole online order.

    Built by ModelParams.build_online(). `step(pressure, measured, t)` predicts the sample
    from the pressure history, then learns from its measured length (so the published
    residual stays out-of-sample). With identification and adaptation both off it is the
    plain memory model.
    """

    increasing: Branch
    decreasing: Branch
    memory: str = 'identify'
    deadband_pa: float = DEFAULT_DEADBAND_PA
    max_gauge_pressure_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)
    adaptation: AdaptationSettings = field(default_factory=AdaptationSettings)

    def __post_init__(self):
        # The compiled step's packed state (_pack), and whether it is ahead of the attributes
        # it keeps (_PACKED_NAMES, the memory model's state).
        self._kernel: _Packed | None = None
        self._python_stale = False
        # Per knot interval, how far each branch's correction may rise (plain floats: they
        # bound the correction on every sample), and both bounds for the shared mean.
        self._caps = tuple(tuple(correction_caps(branch).tolist())
                           for branch in (self.increasing, self.decreasing))
        self._mean_caps = tuple(map(min, *self._caps))
        settings = self.identification
        self._learning = settings.enabled
        self._drifting = self.adaptation.enabled
        # Drift's gain acts about mid-stroke: there a gain change moves nothing, so shift
        # and gain are nearly uncorrelated unknowns (about the rest length they trade off).
        knots = np.array(CORRECTION_KNOTS_PA)
        self.reference_length_m = float(np.mean(
            0.5 * (self.increasing.length(knots) + self.decreasing.length(knots))))
        shares, slopes = settings.play_shares, settings.share_slopes
        # Per direction [share mid-loop, slope across the loop] (memory.play_share_at), and
        # their covariance as [var share, covariance, var slope] (plain floats: every sample
        # after a reversal updates one).
        self._shares = np.array(list(zip(shares, slopes, strict=True)), dtype=float)
        priors = _PRIOR_RESUMED if settings.learned_anything else _PRIOR
        self._share_covariance = [[priors['share'] ** 2, 0.0, priors['share_slope'] ** 2]
                                  for _ in range(2)]
        self._filter = self._new_filter(settings, priors)
        # What the model was last built with (_commit_if_moved), as plain floats: the filter's
        # [mean correction, difference] and the shares [rising share, slope, falling ...].
        self._committed_raw = self._filter.mean[self._filter.blocks.shape].tolist()
        self._committed_shares = self._shares.ravel().tolist()
        branches = self._corrected(self._branch_offsets())
        self._memory_model = HysteresisModel(*branches, memory=self.memory,
                                     deadband_pa=self.deadband_pa,
                                     max_gauge_pressure_pa=self.max_gauge_pressure_pa,
                                     play_shares=shares, share_slopes=slopes)
        # Drift alone learning: nothing but drift could take up the memory's error after a
        # reversal, so the 'identify' shapes measure the memory's doubt there. With
        # identification on, the exact derivative places such a residual itself.
        self._doubt = None if self._learning or not self._drifting else (
            self.model if self.model.has_play_share else
            HysteresisModel(*branches, memory='identify', deadband_pa=self.deadband_pa,
                            max_gauge_pressure_pa=self.max_gauge_pressure_pa,
                            play_shares=shares, share_slopes=slopes))
        # Only a rule with a play share ('identify') learns one.
        self._learns_share = self._learning and self.model.has_play_share
        self._lag_values: list[float] | None = None   # the creep lags (_advance_lags)
        self._time = None
        self._static = math.nan
        # The pressure travelled since start (the virgin term's argument), through a play of
        # the deadband's width so a noisy hold travels nowhere.
        self._travel_pa = 0.0
        self._play_pa = math.nan
        self.commits = 0
        # The compiled step (the Python one, reference_step, is what it is checked against).
        self.compiled = self.memory in KERNEL_RULES and self._doubt is None

    # --- the compiled step's packed state --------------------------------------------

    @property
    def model(self) -> HysteresisModel:
        """The memory model, up to date; the compiled step packs its state afresh after this
        (the caller may change the model)."""
        if self._python_stale:
            self._unpack()
        self._kernel = None
        return self._memory_model

    def _read_memory(self) -> HysteresisModel:
        """The memory model, up to date, for reading only (the packed state stays)."""
        if self._python_stale:
            self._unpack()
        return self._memory_model

    def path_state(self) -> PathState:
        """The memory's HysteresisModel.path_state (read from the compiled step's state
        without unpacking the rest)."""
        if not self._python_stale:
            return self._memory_model.path_state()
        packed = self._kernel
        if packed.path is None:   # kept until the next step
            values = packed.numbers[:kernel.N_SLOPE_DOWN + 1].tolist()
            rule = self._memory_model._rule
            packed.path = PathState(
                values[kernel.N_P], values[kernel.N_L], values[kernel.N_RISING] != 0.0,
                tuple(map(tuple, packed.stack[:int(values[kernel.N_COUNT])].tolist())),
                *self._packed_branches(packed), rule.path_kind, rule.has_play_share,
                (values[kernel.N_SHARE_UP], values[kernel.N_SHARE_DOWN]),
                (values[kernel.N_SLOPE_UP], values[kernel.N_SLOPE_DOWN]),
                self.max_gauge_pressure_pa)
        return packed.path

    def _packed_branches(self, packed: _Packed) -> tuple[Branch, Branch]:
        """The branches the compiled step's rows hold: the memory model's while no commit has
        made new ones, else built once per commit (their kernel rows those rows)."""
        if packed.numbers[kernel.N_COMMITS] == packed.shown_commits:
            return packed.branches
        knots = len(CORRECTION_KNOTS_PA)
        at = kernel.ROW_HEAD + 2 * knots
        branches = self._corrected(tuple(tuple(row[at:at + knots].tolist())
                                         for row in packed.rows))
        for branch, row in zip(branches, packed.rows, strict=True):
            if isinstance(branch, CorrectedBranch):   # the same numbers, not recomputed
                branch.__dict__['kernel_row'] = row.copy()
        packed.branches, packed.shown_commits = branches, packed.numbers[kernel.N_COMMITS]
        return branches

    @property
    def pressure_pa(self) -> float:
        """The memory's pressure (the last finite one stepped)."""
        if self._python_stale:
            return float(self._kernel.numbers[kernel.N_P])
        return self._memory_model.pressure_pa

    @property
    def clock_s(self) -> float | None:
        """The last sample's time (None before any with one)."""
        if self._python_stale:
            numbers = self._kernel.numbers
            return float(numbers[kernel.N_TIME]) if numbers[kernel.N_HAS_TIME] else None
        return self._time

    def __getattr__(self, name: str):
        # Only for a name not found: one the compiled step keeps packed (_PACKED_NAMES).
        if name in _PACKED_NAMES and self.__dict__.get('_python_stale', False):
            self._unpack()
            return self.__dict__[name]
        raise AttributeError(f'{type(self).__name__!r} object has no attribute {name!r}')

    def _pack(self) -> _Packed:
        """The state as kernel.online_step reads it, from the attributes (which are current)."""
        memory, state = self._memory_model, self._filter
        knots, creeps = len(CORRECTION_KNOTS_PA), len(CREEP_TIME_CONSTANTS_S)
        numbers = np.zeros(kernel.N_LAGS + creeps + 2 * knots + 4)
        stack = np.empty((MAX_TURNING_POINTS + 1, 2))
        memory.kernel_numbers(numbers, stack)
        numbers[kernel.N_HAS_TIME] = self._time is not None
        numbers[kernel.N_TIME] = 0.0 if self._time is None else self._time
        numbers[kernel.N_STATIC] = self._static
        numbers[kernel.N_TRAVEL], numbers[kernel.N_TRAVEL_PLAY] = self._travel_pa, self._play_pa
        if self._lag_values is not None:
            numbers[kernel.N_LAGS_SET] = 1.0
            numbers[kernel.N_LAGS:kernel.N_LAGS + creeps] = self._lag_values
        numbers[kernel.N_SAMPLES], numbers[kernel.N_REJECTED] = state.samples, state.rejected
        numbers[kernel.N_COMMITS] = self.commits
        numbers[kernel.N_SHARES:kernel.N_SHARES + 4] = self._shares.ravel()
        numbers[kernel.N_SHARE_COVARIANCE:kernel.N_SHARE_COVARIANCE + 6] = [
            value for row in self._share_covariance for value in row]
        numbers[kernel.N_LAGS + creeps:] = [*self._committed_raw, *self._committed_shares]
        rows = np.stack([knot_row(memory.increasing), knot_row(memory.decreasing)])
        gradients = np.empty((MAX_TURNING_POINTS + 1, 2 * knots + 2))
        self._kernel = _Packed(numbers, self._kernel_config(state), state, rows, stack,
                               gradients, (memory.increasing, memory.decreasing), self.commits,
                               state.mean.size)
        return self._kernel

    def _kernel_config(self, state: _Filter) -> np.ndarray:
        """kernel.online_step's constants (C_ layout) for a filter of this size."""
        size, has_virgin = state.mean.size, state.blocks.virgin is not None
        low, high = self._state_bounds(size, has_virgin)
        head = [KERNEL_RULES[self.memory], self.max_gauge_pressure_pa,
                self._memory_model.deadband_pa, BRANCH_INCREASING, BRANCH_DECREASING,
                self._learning, self._drifting, self._learns_share, self.reference_length_m,
                self.identification.length_noise_m ** 2, self.adaptation.outlier_m,
                self.adaptation.time_constant_s, MAX_STEP_S, MID_DEPTH, NARROW_LOOP_M,
                FLAT_SPAN_M, COMMIT_M, COMMIT_SHARE, SPREAD_FLOOR, GAIN_WALK_LENGTH_M ** 2,
                _WALK_PER_S['share'] ** 2, _WALK_PER_S['share_slope'] ** 2,
                _PRIOR['share'] ** 2, _PRIOR['share_slope'] ** 2, MAX_TURNING_POINTS,
                MAX_CORRECTION_M, len(CREEP_TIME_CONSTANTS_S),
                len(VIRGIN_TRAVEL_KNOTS_PA) if has_virgin else 0, VIRGIN_END_PA]
        blocks = [CREEP_TIME_CONSTANTS_S, (*self._caps[0], *self._caps[1], *self._mean_caps),
                  state.walk_per_s.tolist(), low.tolist(), high.tolist(), _VIRGIN_KNOTS]
        at = kernel.CONFIG_HEAD
        # C_TAUS_AT, C_CAPS_AT, C_WALK_AT, C_LOW_AT, C_HIGH_AT, C_VIRGIN_KNOTS_AT
        for block in blocks:
            head.append(at)
            at += len(block)
        return np.array([*head, *(value for block in blocks for value in block)], dtype=float)

    def _drop_python_state(self) -> None:
        """The compiled step moves the packed state: the attributes it keeps go until read."""
        for name in _PACKED_NAMES:
            self.__dict__.pop(name, None)
        self._python_stale = True

    def _unpack(self) -> None:
        """The attributes and the memory model from the packed state (which stays valid)."""
        packed = self._kernel
        numbers = packed.numbers
        knots, creeps = len(CORRECTION_KNOTS_PA), len(CREEP_TIME_CONSTANTS_S)
        self._memory_model.load_kernel_numbers(numbers, packed.stack,
                                               *self._packed_branches(packed))
        values = numbers.tolist()
        state = packed.filter
        state.samples = int(values[kernel.N_SAMPLES])
        state.rejected = int(values[kernel.N_REJECTED])
        lags = values[kernel.N_LAGS:kernel.N_LAGS + creeps]
        committed = values[kernel.N_LAGS + creeps:]
        covariance = values[kernel.N_SHARE_COVARIANCE:kernel.N_SHARE_COVARIANCE + 6]
        self.__dict__.update(
            _filter=state, commits=int(values[kernel.N_COMMITS]),
            _shares=np.array(values[kernel.N_SHARES:kernel.N_SHARES + 4]).reshape(2, 2),
            _share_covariance=[covariance[:3], covariance[3:]],
            _committed_raw=committed[:2 * knots], _committed_shares=committed[2 * knots:],
            _lag_values=lags if values[kernel.N_LAGS_SET] else None,
            _time=values[kernel.N_TIME] if values[kernel.N_HAS_TIME] else None,
            _static=values[kernel.N_STATIC], _travel_pa=values[kernel.N_TRAVEL],
            _play_pa=values[kernel.N_TRAVEL_PLAY])
        self._python_stale = False

    # --- construction ---------------------------------------------------------------

    def _new_filter(self, settings: IdentificationSettings, priors: dict) -> _Filter:
        """The filter's state: [mean correction, difference, creep gains, virgin term at
        VIRGIN_TRAVEL_KNOTS_PA (until it ends), shift, gain - 1].

        Drift is what has changed since the model started: it starts at exactly 0 with no
        prior spread, and only its random walk lets it move. How this muscle differs from
        Table 1 at start is shape (the correction's wide prior). The shape used to be kept
        out of the two directions drift moves the knots in, with a prior on drift as wide
        as the shape's: then the filter had to explain the muscle's rest length and stroke
        misfit as drift, and any local correction had to be balanced elsewhere, so the
        knots zigzagged to their limits (docs/model-history.md).
        """
        knots = len(CORRECTION_KNOTS_PA)
        creeps, virgins = len(CREEP_TIME_CONSTANTS_S), len(VIRGIN_TRAVEL_KNOTS_PA)
        mean = np.concatenate([settings.branch_correction_m, settings.branch_difference_m,
                               settings.creep_gains, np.zeros(virgins), [0.0, 0.0]])
        learn = 1.0 if self._learning else 0.0
        prior = np.concatenate([np.full(knots, learn * priors['correction'] ** 2),
                                np.full(knots, learn * priors['difference'] ** 2),
                                np.full(creeps, learn * priors['creep'] ** 2),
                                np.full(virgins, learn * VIRGIN_PRIOR_M ** 2), [0.0, 0.0]])
        walk = np.concatenate([np.full(2 * knots, learn * _WALK_PER_S['correction'] ** 2),
                               np.full(creeps, learn * _WALK_PER_S['creep'] ** 2),
                               np.zeros(virgins), [0.0, 0.0]])
        return _Filter(mean, np.diag(prior), walk, StateBlocks.laid_out(knots, creeps, virgins))

    def _end_virgin_term(self, state: _Filter) -> None:
        """Drop the virgin term from the filter `state`: marginalising a Gaussian is deleting
        its rows and columns, so what it taught the rest through their covariance is kept."""
        rows = np.arange(state.mean.size)[state.blocks.virgin]
        state.mean = np.delete(state.mean, rows)
        # C order, as the filter was built: np.delete along the columns returns a Fortran-
        # ordered array, and the compiled step would compile (and cache) a second signature.
        state.covariance = np.ascontiguousarray(
            np.delete(np.delete(state.covariance, rows, axis=0), rows, axis=1))
        state.walk_per_s = np.delete(state.walk_per_s, rows)
        state.blocks = state.blocks.without_virgin()

    def _drift_directions(self) -> np.ndarray:
        """How a shift and a stroke gain move the knots: columns 1 and B(knots) - L_ref,
        B the mean of the two branches."""
        knots = np.array(CORRECTION_KNOTS_PA)
        middle = 0.5 * (self.increasing.length(knots) + self.decreasing.length(knots))
        return np.column_stack([np.ones(knots.size), middle - self.reference_length_m])

    def _monotone(self, correction) -> tuple[float, ...]:
        """The correction, bounded and kept monotone on both branches."""
        return monotone_correction(correction, self._mean_caps)

    def _branch_offsets(self, mean=None, difference=None) -> tuple[np.ndarray, np.ndarray]:
        """(increasing, decreasing) corrections the model can use: mean +/- half the
        difference, each bounded and monotone on its own branch."""
        if mean is None:
            mean, difference = self._raw_corrections()
        return tuple(np.array(monotone_correction(mean + sign * 0.5 * difference, caps))
                     for sign, caps in ((1.0, self._caps[0]), (-1.0, self._caps[1])))

    def _corrected(self, offsets) -> tuple[Branch, Branch]:
        increasing, decreasing = offsets
        if not any(increasing) and not any(decreasing):
            return self.increasing, self.decreasing
        if isinstance(increasing, tuple):   # floats already (monotone_correction's)
            return (CorrectedBranch(self.increasing, increasing),
                    CorrectedBranch(self.decreasing, decreasing))
        return (CorrectedBranch(self.increasing, tuple(float(v) for v in increasing)),
                CorrectedBranch(self.decreasing, tuple(float(v) for v in decreasing)))

    # --- what it has learned --------------------------------------------------------

    @property
    def _lags(self) -> np.ndarray | None:
        """The creep lags' lengths (None before the first sample)."""
        if self._python_stale:   # read where the compiled step keeps them
            numbers = self._kernel.numbers
            return numbers[kernel.N_LAGS:kernel.N_LAGS + len(CREEP_TIME_CONSTANTS_S)].copy() \
                if numbers[kernel.N_LAGS_SET] else None
        return None if self._lag_values is None else np.array(self._lag_values)

    @property
    def _filter_now(self) -> _Filter:
        """The filter, for reading, without unpacking the compiled step's state."""
        return self._kernel.filter if self._python_stale else self._filter

    @property
    def drift(self) -> Drift:
        return _drift_of(self._filter_now, self.reference_length_m)

    @property
    def branch(self) -> int:
        return self._read_memory().branch

    @property
    def first_loading_ended(self) -> bool:
        """True once the muscle has travelled VIRGIN_END_PA since start."""
        return self._filter.blocks.virgin is None

    @property
    def virgin_term_m(self) -> float:
        """What the model adds for a rested muscle's first loading at the pressure travelled
        so far (0 once it has ended)."""
        virgin = self._filter.blocks.virgin
        if virgin is None:
            return 0.0
        return float(virgin_knot_weights(self._travel_pa) @ self._filter.mean[virgin])

    @property
    def samples_learned(self) -> int:
        return self._filter.samples

    # As a mix has them (OnlineRule): one rule, no weights, no local offset.
    @property
    def experts(self) -> tuple[OnlineModel, ...]:
        return (self,)

    def weights_by_rule(self) -> dict[str, float]:
        return {}

    local_offset_m: ClassVar[float] = 0.0

    def without_local_offset(self) -> OnlineModel:
        return self

    @property
    def samples_rejected(self) -> int:
        return self._filter.rejected

    def learned(self) -> IdentificationSettings:
        """The identification settings with what has been learned (for ModelParams).

        The drift at this moment is folded into the correction (it is this muscle, now);
        a model built from these settings starts from there with no drift.
        """
        state, blocks = self._filter.mean, self._filter.blocks
        correction, difference = state[blocks.correction], state[blocks.difference]
        creep, shift, gain_excess = state[blocks.creep], state[blocks.shift], state[blocks.gain]
        mean = correction + self._drift_directions() @ np.array([shift, gain_excess])
        increasing, decreasing = self._branch_offsets(mean, difference)
        if not (np.allclose(increasing, mean + 0.5 * difference, rtol=0.0, atol=ROUNDING_M)
                and np.allclose(decreasing, mean - 0.5 * difference, rtol=0.0,
                                atol=ROUNDING_M)):
            # A limit bound: save what the branches use. Otherwise the filter's own numbers,
            # so that a saved file gives them back to the last bit. Numbers saved from a
            # bound meet it again only to rounding, which must not count as a bound: their
            # mean +/- half the difference can land an ulp outside it, and then every
            # restart would save them an ulp off.
            mean, difference = 0.5 * (increasing + decreasing), increasing - decreasing
        (rising, falling), (slope_rising, slope_falling) = self._mid_shares_and_slopes()
        return replace(self.identification, play_share_rising=rising,
                       play_share_falling=falling, play_share_slope_rising=slope_rising,
                       play_share_slope_falling=slope_falling,
                       branch_correction_m=tuple(float(v) for v in mean),
                       branch_difference_m=tuple(float(v) for v in difference),
                       creep_gains=tuple(float(v) for v in creep))

    def _raw_corrections(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean correction, difference) as the filter has them (no drift, no limits)."""
        mean, blocks = self._filter.mean, self._filter.blocks
        return mean[blocks.correction], mean[blocks.difference].copy()

    # --- the online order -----------------------------------------------------------

    def step(self, pressure_pa: float, measured_length_m: float = math.nan,
             t_s: float | None = None) -> Prediction:
        """Predict this sample, then learn from its measured length (NaN: nothing to learn).

        A non-finite pressure gives a NaN prediction and changes nothing. One compiled call
        (kernel.online_step) on the packed state where the rule has one (`compiled`), else
        `reference_step`, which it is checked against.
        """
        if not self.compiled:
            return self.reference_step(pressure_pa, measured_length_m, t_s)
        packed = self._kernel or self._pack()
        if not self._python_stale:
            self._drop_python_state()
        pressure_pa = float(pressure_pa)
        state = packed.filter
        packed.path = None
        if not math.isfinite(pressure_pa):
            drift = _drift_of(state, self.reference_length_m)
            return Prediction(math.nan, int(packed.numbers[kernel.N_BRANCH]), math.nan,
                              drift.offset_m, drift.gain)
        predicted, branch, static, offset, gain, virgin_ended = kernel.online_step(
            pressure_pa, float(measured_length_m), 0.0 if t_s is None else float(t_s),
            t_s is not None, packed.numbers, packed.config, state.mean, state.covariance,
            packed.rows, packed.stack, packed.gradients)
        if virgin_ended:
            self._end_kernel_virgin_term(packed)
        return Prediction(predicted, int(branch), static, offset, gain)

    def _end_kernel_virgin_term(self, packed: _Packed) -> None:
        """The virgin term out of the packed filter, as the compiled step said it ended."""
        self._end_virgin_term(packed.filter)
        packed.config, packed.size = self._kernel_config(packed.filter), packed.filter.mean.size

    def reference_step(self, pressure_pa: float, measured_length_m: float = math.nan,
                       t_s: float | None = None) -> Prediction:
        """`step` in Python, the reference the compiled one is checked against (and the
        step of the rules it does not run)."""
        if self._python_stale:
            self._unpack()
        self._kernel = None
        pressure_pa = float(pressure_pa)
        drift = self.drift
        if not math.isfinite(pressure_pa):
            return Prediction(math.nan, self.model.branch, math.nan, drift.offset_m, drift.gain)
        static, branch = self.model.update(pressure_pa)
        virgin_weights = self._advance_travel(pressure_pa, self._filter)
        confidence = 1.0
        if self._doubt is not None:
            if self._doubt is not self.model:
                self._doubt.update(pressure_pa)
            held, rescaled = self._doubt.expert_lengths()
            confidence = 1.0 / (1.0 + ((held - rescaled) / SPREAD_SCALE_M) ** 2)
        dt = self._advance_lags(static, t_s)
        mean, blocks = self._filter.mean, self._filter.blocks
        creep = [lag - static for lag in self._lag_values]
        undrifted = static + sum(
            gain * lag for gain, lag in zip(mean[blocks.creep].tolist(), creep, strict=True))
        if virgin_weights is not None:
            k, share = virgin_weights
            virgin = mean[blocks.virgin]
            undrifted += (1.0 - share) * float(virgin[k]) + (
                share * float(virgin[k + 1]) if share != 0.0 and k + 1 < virgin.size else 0.0)
        predicted = float(drift.correct(undrifted))
        measured_length_m = float(measured_length_m)
        if (self._learning or self._drifting) and math.isfinite(measured_length_m):
            shape_difference = 0.0          # what the share learns from: only 'identify' has one
            if self._learns_share:
                play, madelung = self.model.expert_lengths()
                shape_difference = play - madelung
            self._learn(measured_length_m - predicted, creep=creep, undrifted=undrifted,
                        shape_difference=shape_difference, confidence=confidence,
                        gain=drift.gain, dt=dt, virgin_weights=virgin_weights)
        return Prediction(predicted, branch, static, drift.offset_m, drift.gain)

    def _advance_travel(self, pressure_pa: float, state: _Filter) -> tuple[int, float] | None:
        """Advance the pressure travelled since start; the virgin term's knot interval and
        share there (virgin_knot_weights' two weights), or None once it has ended (and left
        `state`, the filter)."""
        if state.blocks.virgin is None:
            return None
        if math.isnan(self._play_pa):
            self._play_pa = pressure_pa
        moved = kernel.through_play(self._play_pa, pressure_pa, 0.5 * self.deadband_pa)
        self._travel_pa += abs(moved - self._play_pa)
        self._play_pa = moved
        if self._travel_pa >= VIRGIN_END_PA:
            self._end_virgin_term(state)
            return None
        return _virgin_knot_share(self._travel_pa)

    def _advance_lags(self, static: float, t_s: float | None) -> float:
        """Move the creep lags to this sample's time; returns the step [s] (0 if unknown)."""
        if self._lag_values is None or t_s is None or self._time is None:
            dt = 0.0
            if self._lag_values is None:
                self._lag_values = [static] * len(CREEP_TIME_CONSTANTS_S)
        else:
            dt = elapsed_s(self._time, t_s)
        if dt > 0.0:
            self._lag_values = [kernel.creep_lag(lag, static, self._static, dt, tau)
                                for tau, lag in zip(CREEP_TIME_CONSTANTS_S, self._lag_values,
                                                    strict=True)]
        if t_s is not None:
            self._time = float(t_s)
        self._static = static
        return dt

    def _learn(self, residual: float, *, creep: list[float], undrifted: float,
               shape_difference: float, confidence: float, gain: float, dt: float,
               virgin_weights: tuple[int, float] | None) -> None:
        state = self._filter
        if abs(residual) > self.adaptation.outlier_m:
            state.rejected += 1
            return
        noise = self.identification.length_noise_m ** 2
        if self._learns_share:
            self._learn_share(residual, shape_difference * gain, noise, dt)
        blocks = state.blocks
        # d length / d knots, exact through the memory's turning points: on a scanning curve
        # the length is pinned to them, and their lengths came from earlier curves, often of
        # the other branch (the branch's own weights at this pressure had the difference's
        # sign wrong just after a reversal: docs/model-history.md).
        gradient = self.model.length_gradient(knot_sensitivity)
        size = state.mean.size
        regressor = np.empty(size)
        # gain * (increasing + decreasing), (gain / 2) * (increasing - decreasing), filled in
        # place (numpy's per-call cost is most of a step's: as few calls as possible).
        increasing, decreasing = gradient[INCREASING_KNOTS], gradient[DECREASING_KNOTS]
        correction = regressor[blocks.correction]
        np.add(increasing, decreasing, out=correction)
        correction *= gain
        difference = regressor[blocks.difference]
        np.subtract(increasing, decreasing, out=difference)
        difference *= 0.5 * gain
        regressor[blocks.creep] = [gain * lag for lag in creep]
        if virgin_weights is not None:
            k, share = virgin_weights
            virgin = regressor[blocks.virgin]
            virgin[:] = 0.0
            virgin[k] = gain * (1.0 - share)
            if share != 0.0 and k + 1 < virgin.size:
                virgin[k + 1] = gain * share
        regressor[blocks.shift] = 1.0
        regressor[blocks.gain] = undrifted - self.reference_length_m
        walk = state.walk_per_s * dt
        if self._drifting:
            walk[blocks.shift] = kernel.drift_walk_variance(
                noise, self.adaptation.time_constant_s, dt)
            walk[blocks.gain] = walk[blocks.shift] / GAIN_WALK_LENGTH_M ** 2
        covariance = state.covariance
        covariance.flat[::size + 1] += walk   # the diagonal, in place
        spread = covariance @ regressor
        innovation = noise / max(confidence, SPREAD_FLOOR) + float(regressor @ spread)
        state.mean = state.mean + spread * (residual / innovation)
        # The covariance's update as spread spread^T / innovation: symmetric to the last bit
        # (a product commutes), so it needs no symmetrising afterwards, and in place.
        update = np.multiply.outer(spread, spread)
        update /= innovation
        covariance -= update
        self._project_shape(state)
        mean = state.mean
        # Every bound at once (min/max select: the same as bounding each part).
        low, high = self._state_bounds(size, blocks.virgin is not None)
        bounded = mean[blocks.bounded]
        np.minimum(np.maximum(bounded, low, out=bounded), high, out=bounded)
        state.samples += 1
        self._commit_if_moved()

    def _state_bounds(self, size: int, has_virgin: bool) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) for the filter's state after the mean correction (difference, creep,
        the virgin term while it lasts, shift, gain - 1), for a state of `size` values."""
        cached = self.__dict__.get('_bounds')
        if cached is not None and cached[0] == size:
            return cached[1]
        knots = len(CORRECTION_KNOTS_PA)
        limits = self.adaptation
        low = [-MAX_DIFFERENCE_M] * knots + [-MAX_CREEP_GAIN] * len(CREEP_TIME_CONSTANTS_S)
        high = [MAX_DIFFERENCE_M] * knots + [MAX_CREEP_GAIN] * len(CREEP_TIME_CONSTANTS_S)
        if has_virgin:   # as large as a knot's correction may be
            virgins = len(VIRGIN_TRAVEL_KNOTS_PA)
            low += [-MAX_CORRECTION_M] * virgins
            high += [MAX_CORRECTION_M] * virgins
        low += [-limits.max_shift_m, limits.min_gain - 1.0]
        high += [limits.max_shift_m, limits.max_gain - 1.0]
        bounds = (np.array(low), np.array(high))
        self._bounds = (size, bounds)
        return bounds

    def _project_shape(self, state: _Filter) -> None:
        """Keep the filter's belief a correction the model can use (bounded, monotone).

        The branch-coordinate interpolation lets the correction go flat, so the limit
        binds only where the data ask for a branch that rises with pressure (noise, early
        on); the mean is moved back inside, the covariance is left alone.
        """
        correction = state.blocks.correction
        shape = state.mean[correction].tolist()
        projected = self._monotone(shape)
        if projected != tuple(shape):   # usually equal: compared as plain floats
            state.mean[correction] = projected

    def _learn_share(self, residual: float, difference: float, noise: float, dt: float) -> None:
        """RLS on the current direction's play share and its slope across the loop (the
        prediction is linear in both, through the curve's share; kernel.share_update)."""
        if difference == 0.0:
            return
        index = 0 if self.model.rising else 1
        var_share, cov, var_slope = self._share_covariance[index]
        share, slope, *covariance = kernel.share_update(
            float(self._shares[index, 0]), float(self._shares[index, 1]),
            var_share + _WALK_PER_S['share'] ** 2 * dt, cov,
            var_slope + _WALK_PER_S['share_slope'] ** 2 * dt, residual, difference,
            difference * (self.model.current_origin_depth() - MID_DEPTH), noise,
            _PRIOR['share'] ** 2, _PRIOR['share_slope'] ** 2)
        self._shares[index] = share, slope
        self._share_covariance[index] = covariance

    def _mid_shares_and_slopes(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((rising, falling) share mid-loop, (rising, falling) slope)."""
        return tuple(self._shares[:, 0].tolist()), tuple(self._shares[:, 1].tolist())

    def _commit_if_moved(self) -> None:
        # Plain floats: this runs on every sample, and numpy's per-call cost on 13 values
        # was most of it. The same test as comparing each part's largest change.
        knots = len(CORRECTION_KNOTS_PA)
        raw = self._filter.mean[self._filter.blocks.shape].tolist()
        shares = self._shares.ravel().tolist()
        if max(map(abs, map(operator.sub, raw, self._committed_raw))) < COMMIT_M and \
                max(map(abs, map(operator.sub, shares, self._committed_shares))) < COMMIT_SHARE:
            return
        self._committed_raw, self._committed_shares = raw, shares
        correction, difference = raw[:knots], raw[knots:]
        # mean +/- half the difference, as _branch_offsets computes it (the same operations
        # on floats), each bounded and monotone on its own branch.
        offsets = tuple(monotone_correction([m + half * d for m, d in zip(
            correction, difference, strict=True)], caps)
                        for half, caps in ((0.5, self._caps[0]), (-0.5, self._caps[1])))
        self.commits += 1
        new_shares, new_slopes = tuple(shares[0::2]), tuple(shares[1::2])
        branches = self._corrected(offsets)
        self.model.relearn(*branches, new_shares, new_slopes)
        if self._doubt is not None and self._doubt is not self.model:
            self._doubt.relearn(*branches, new_shares, new_slopes)

    # --- inverse --------------------------------------------------------------------

    def pressure_for_length(self, length_m: float, branch: int = BRANCH_AUTO) -> InverseResult:
        """The memory model's inverse (steady state: creep has settled), drift undone.

        Lengths in the answer's range are the drifted ones, as the muscle will show them.
        """
        drift = self.drift
        target = float(drift.uncorrect(length_m)) if math.isfinite(length_m) else length_m
        result = self._read_memory().pressure_for_length(target, branch)
        if self._drifting and math.isfinite(result.min_length_m):
            low, high = drift.correct([result.min_length_m, result.max_length_m])
            low, high = float(min(low, high)), float(max(low, high))
            message = result.message
            if not result.success:
                message += (f' (lengths without the drift correction; with it: reachable '
                            f'[{low:.6g}, {high:.6g}] m)')
            result = replace(result, message=message, min_length_m=low, max_length_m=high)
        return result

    def settled_aim_m(self, length_m: float, max_creep_share: float) -> float:
        """The settled length to give `pressure_for_length` so that the muscle is `length_m`
        long now, not once creep has settled: with creep's lags where they are, the share
        still lagging is asked for ahead (a lead that fades as the lags catch up).

        Creep makes the length (1 - G) static + sum_j k_j lag_j, G = sum_j k_j; solved for the
        static length. G is taken as at most `max_creep_share` (a lead of 1 / (1 - G) times
        the remaining change; a learned share near 1 is more likely a mistake than a muscle)
        and a negative G as none. Drift applied as in the inverse.
        """
        state, lags = self._filter_now, self._lags
        gains = state.mean[state.blocks.creep]
        share = float(gains.sum())
        if lags is None or not share > 0.0 or not math.isfinite(length_m):
            return length_m
        if share > max_creep_share:
            gains, share = gains * (max_creep_share / share), max_creep_share
        drift = self.drift
        static = (float(drift.uncorrect(length_m)) - float(gains @ lags)) / (1.0 - share)
        return float(drift.correct(static))

    def settled_map(self, rising: bool, path: bool = True) -> Callable[[float], float]:
        """length(p_pa) once creep has settled, drift applied: along the path pressure would
        follow from the current state one way (path), or on that direction's major branch.

        The forward map of `pressure_for_length`, for a caller that must search.
        """
        memory = self._read_memory()
        static = memory.path_map(rising) if path else memory.major(rising).length
        drift = self.drift
        return lambda p_pa: drift.correct(float(static(float(p_pa))))

    # --- run-time parameter changes -------------------------------------------------

    def resume_from(self, other: OnlineRule) -> None:
        """Continue `other`'s pressure history (and its creep lags) with these settings;
        from a mix.RuleMix, its first rule's."""
        other = other.experts[0]
        self.model.resume_from(other._read_memory())
        if self._doubt is not None and self._doubt is not self.model:
            self._doubt.resume_from(other._doubt if other._doubt is not None else other.model)
        self._lag_values = None if other._lag_values is None else list(other._lag_values)
        self._time, self._static = other._time, other._static
        # How far the muscle has travelled is its history too (what the old model learned of
        # a virgin term is not carried over: it lasts one loading).
        self._travel_pa, self._play_pa = other._travel_pa, other._play_pa
        if self._filter.blocks.virgin is not None and self._travel_pa >= VIRGIN_END_PA:
            self._end_virgin_term(self._filter)


@dataclass
class _Packed:
    """An OnlineModel's state as kernel.online_step moves it: its numbers (kernel.N_
    layout), constants (C_), the filter (its mean and covariance in place), the branch rows,
    the turning-point stack and their gradients; the branches the rows hold and the commits
    they were built for, the filter size the constants are for, and the memory's PathState
    until the next step moves it."""

    numbers: np.ndarray
    config: np.ndarray
    filter: _Filter
    rows: np.ndarray
    stack: np.ndarray
    gradients: np.ndarray
    branches: tuple[Branch, Branch]
    shown_commits: float
    size: int
    path: PathState | None = None


def _drift_of(state: _Filter, reference_length_m: float) -> Drift:
    """The drift a filter's state holds."""
    mean, blocks = state.mean, state.blocks
    return Drift(reference_length_m, float(mean[blocks.shift]), 1.0 + float(mean[blocks.gain]))


_VIRGIN_KNOTS = (*VIRGIN_TRAVEL_KNOTS_PA, VIRGIN_END_PA)


def _virgin_knot_share(travel_pa: float) -> tuple[int, float]:
    """(k, share): virgin_knot_weights' two nonzero weights are 1 - share at knot k and
    share at k + 1 (k + 1 may be VIRGIN_END_PA's, which is not in the state). travel_pa is
    within 0..VIRGIN_END_PA."""
    return kernel.virgin_knot_share(np.array(_VIRGIN_KNOTS), float(travel_pa))


def virgin_knot_weights(travel_pa: float) -> np.ndarray:
    """Hat-function weights of the virgin term's knots at a travel (all 0 from
    VIRGIN_END_PA on, where the term has ended)."""
    weights = np.zeros(len(_VIRGIN_KNOTS))
    if _VIRGIN_KNOTS[0] <= travel_pa < _VIRGIN_KNOTS[-1]:
        k, share = _virgin_knot_share(travel_pa)
        weights[k], weights[k + 1] = 1.0 - share, share
    return weights[:-1]


def elapsed_s(previous_s: float | None, t_s: float | None) -> float:
    """Time between two samples, for learning: 0 if either is unknown or time went back,
    at most MAX_STEP_S (a pause is not a long sample)."""
    if previous_s is None or t_s is None:
        return 0.0
    return kernel.elapsed(float(previous_s), float(t_s), MAX_STEP_S)


def run_online(online: OnlineModel, pressure_pa, measured_length_m, time_s) -> np.ndarray:
    """`step` along recorded arrays (predict, then learn, sample by sample); the predictions.

    The replay of a recording through the online model: what model_node would have
    published. `online` is advanced (and has learned) when it returns.
    """
    pressures = np.asarray(pressure_pa, dtype=float)
    lengths = np.asarray(measured_length_m, dtype=float)
    times = np.asarray(time_s, dtype=float)
    return np.array([online.step(p, length, t).length_m
                     for p, length, t in zip(pressures, lengths, times, strict=True)])
