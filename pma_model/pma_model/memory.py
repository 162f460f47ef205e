"""Hysteresis memory: how the two major branches combine into a length for any pressure path.

Four rules (docs/model.md §3 has them and the accuracy; docs/model-history.md has the full
story and their errors on minor loops):

- 'switch' (the paper): the length is the major branch of the detected direction, so it
  jumps by the loop width at every reversal.
- 'madelung': a stack of turning points with wiping-out. Each scanning curve is
  the current direction's major branch B rescaled through the last reversal O and the
  previous opposite reversal T:
      L(P) = L_T + (L_O - L_T) * (B(P) - B(P_T)) / (B(P_O) - B(P_T))
  and when P passes P_T, O and T are popped and the older curve continues. With no turning
  point the state is on the increasing major branch; a single turning point (a maximum)
  heads for the permanent anchor (0 Pa, decreasing branch at 0 Pa). This gives
  return-point memory, no jump at a reversal, and a closed-form inverse through B^-1.
- 'play' (friction band): rising pressure can only shorten the muscle down to the
  increasing branch, falling pressure only lengthen it up to the decreasing one:
      rising: L = min(L, B_inc(P))        falling: L = max(L, B_dec(P))
  so after a reversal the length holds until pressure has crossed the band between the
  branches, then follows the other branch. The backlash (play) operator between the major
  branches: Coulomb friction in the braid, no parameter beyond the branches, no jump,
  quiet under noise narrower than the band, and a closed-form inverse.

- 'identify' (the default): the Madelung stack, with scanning curves that mix two shapes from
  the same two points O and T: Madelung's rescaled branch and a play-like curve that holds
  at L_O and then runs parallel to the (rescaled) branch into T. With s = (B(P) - B(P_T)) /
  (B(P_O) - B(P_T)), q = min(1, (L_O - L_T) / (B(P_O) - B(P_T))) and w the curve's play
  share:
      L(P) = L_T + (L_O - L_T) * (w * min(1, s / q) + (1 - w) * s)
  w = 0 is Madelung, w = 1 hold-then-branch. w depends on the direction and on where O lies
  across the loop (play_share_at, origin_depth), so it is fixed for the curve. Every curve
  passes through O and T, so the rule keeps return-point memory, wiping-out and continuity
  for any w, and the shape is piecewise linear in s, so the inverse stays closed-form.
  `identification.OnlineModel` learns the shares and slopes from the measured length.

Each rule is a class in rules.py, registered by name (rules.MEMORY_RULES); HysteresisModel
holds the state (pressure, length, direction, the turning-point stack) and asks its rule how
it moves. The scanning curves are curves.py's.

The Madelung stack follows every reversal of the pressure signal (loops smaller than the
noise close on themselves and are wiped out); the deadband detector gives the reported
branch, drives 'switch', and is the one the offline refit uses.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from pma_model import kernel
from pma_model.branches import DEFAULT_MAX_GAUGE_PRESSURE_PA, Branch
from pma_model.curves import FLAT_SPAN_M, MID_DEPTH, ScanningCurve
from pma_model.detector import (
    BRANCH_AUTO,
    BRANCH_DECREASING,
    BRANCH_INCREASING,
    BRANCH_NAMES,
    DEFAULT_DEADBAND_PA,
    BranchDetector,
)
from pma_model.rules import MEMORY_RULES, BranchSensitivity, Segment, memory_rule

# The single rules' names (the `memory` setting also has 'mix': mix.py).
MEMORY_MODES = tuple(MEMORY_RULES)

# Nested turning points need distinct pressures, so a 10-bit sensor cannot fill this; the
# cap only bounds memory for pathological input. Overflow forgets the oldest loop.
MAX_TURNING_POINTS = 512

# Branches closer than this [m] at a reversal's pressure: no loop to place it in.
NARROW_LOOP_M = 1e-4

# Lengths this close [m] count as equal when deciding whether a curve reaches a target: a
# curve evaluated at its own origin can differ from the stored length in the last bit.
ROUNDING_M = 1e-12

# The numbers kernel.path_segments takes from the modules that own them (kernel.py says why);
# the rest of its scalars are the inverse's (mix.py).
PATH_SCALARS = np.zeros(kernel.SCALARS)
PATH_SCALARS[[kernel.S_MID_DEPTH, kernel.S_NARROW, kernel.S_FLAT_SPAN]] = (
    MID_DEPTH, NARROW_LOOP_M, FLAT_SPAN_M)


class PathState(NamedTuple):
    """What the path pressure would follow from the current state depends on
    (`HysteresisModel.path_state`; kernel.mixed_path_pressure builds the path from it)."""

    pressure_pa: float
    length_m: float
    rising: bool                 # pressure last moved up
    turning_points: tuple[tuple[float, float], ...]   # (pressure_pa, length_m), oldest first
    increasing: Branch
    decreasing: Branch
    path_kind: int               # the rule's (kernel.PATH_STACK or kernel.PATH_BAND)
    has_play_share: bool         # its curves mix two shapes by the shares ('identify')
    play_shares: tuple[float, float]    # (rising, falling)
    share_slopes: tuple[float, float]
    max_gauge_pressure_pa: float


def expert_row(state: PathState, weight: float = 1.0, drift: tuple = (0.0, 0.0, 1.0),
               first_branch: int = 0, first_point: int = 0) -> tuple:
    """A rule's path state as a row of the kernel's expert table (kernel.E_ layout): its
    branches are rows first_branch (increasing) and first_branch + 1 of the branch table, its
    turning points rows first_point... of the stack table; `drift`: (reference length, shift,
    gain), `weight`: its share of a mix."""
    return (weight, *drift, state.pressure_pa, state.length_m, state.rising, state.path_kind,
            state.has_play_share, *state.play_shares, *state.share_slopes, first_branch,
            first_branch + 1, first_point, len(state.turning_points),
            state.max_gauge_pressure_pa)


@dataclass(frozen=True)
class InverseResult:
    """The answer to 'which pressure makes the muscle this long?' (PressureForLength)."""

    success: bool
    message: str
    gauge_pressure_pa: float
    branch: int
    min_length_m: float
    max_length_m: float


def _checked_shares(shares) -> tuple[float, float]:
    """(rising, falling) play shares of the 'identify' rule, each within 0..1."""
    rising, falling = (float(value) for value in shares)
    for name, value in (('rising', rising), ('falling', falling)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f'the {name} play share must be within 0..1, got {value!r}')
    return rising, falling


def _checked_slopes(slopes) -> tuple[float, float]:
    """(rising, falling) change of the play share across the loop (finite; the share a
    curve gets is clipped to 0..1)."""
    rising, falling = (float(value) for value in slopes)
    for name, value in (('rising', rising), ('falling', falling)):
        if not math.isfinite(value):
            raise ValueError(f'the {name} play share slope must be finite, got {value!r}')
    return rising, falling


def _as_float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan




class HysteresisModel:
    """Length of the muscle for a pressure history, and the inverse for a target length.

    The state starts at rest: 0 Pa on the increasing major branch.
    """

    def __init__(self, increasing: Branch, decreasing: Branch, memory: str = 'madelung',
                 deadband_pa: float = DEFAULT_DEADBAND_PA,
                 max_gauge_pressure_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA, *,
                 play_shares: tuple[float, float] = (0.5, 0.5),
                 share_slopes: tuple[float, float] = (0.0, 0.0)):
        rule = memory_rule(memory)     # ValueError naming the rules
        if not (math.isfinite(max_gauge_pressure_pa) and max_gauge_pressure_pa > 0):
            raise ValueError('max_gauge_pressure_pa must be finite and > 0, '
                             f'got {max_gauge_pressure_pa!r}')
        self.increasing = increasing
        self.decreasing = decreasing
        self.memory = memory
        self._rule = rule
        self.play_shares = _checked_shares(play_shares)
        self.share_slopes = _checked_slopes(share_slopes)
        self.max_gauge_pressure_pa = float(max_gauge_pressure_pa)
        self._detector = BranchDetector(deadband_pa)
        self.reset()

    # --- state ----------------------------------------------------------------------

    def reset(self) -> None:
        """Back to rest: 0 Pa, increasing major branch, no turning points."""
        self._detector.reset()
        self._reset_memory()

    def _reset_memory(self) -> None:
        """reset() but the detector's."""
        self._p = 0.0
        self._l = float(self.increasing.length(0.0))
        self._rising = True
        self._stack: list[tuple[float, float]] = []
        self._cached_key = None
        self._cached_curve: ScanningCurve | None = None
        # Play: the branch (True increasing) and pressure the held length was last set on.
        self._play_source = (True, 0.0)
        # length_gradient's: the stack it was computed for and its turning points' gradients,
        # and the current curve with its ends' gradients.
        self._gradient_cache: tuple[list, list] = ([], [])
        self._gradient_ends: tuple = (None, None)
        # path_segments': (increasing, decreasing, their kernel branch table).
        self._kernel_branches: tuple = (None, None, None)

    def __copy__(self) -> HysteresisModel:
        # copy.copy's default goes through pickling's reduce protocol, five times the cost
        # of this, and every commit of the online learning copies the model (relearn).
        clone = object.__new__(type(self))
        clone.__dict__.update(self.__dict__)
        return clone

    def relearn(self, increasing: Branch, decreasing: Branch,
                play_shares: tuple[float, float] | None = None,
                share_slopes: tuple[float, float] | None = None) -> None:
        """New branches (and 'identify' shares) for the same pressure history.

        The state is rebuilt from the remembered turning points (resume_from), so what
        the model learns applies to the whole memory at once, and a small change of the
        learned numbers moves the length by a small amount.
        """
        old = copy.copy(self)
        old._stack = list(self._stack)
        self.increasing, self.decreasing = increasing, decreasing
        if play_shares is not None:
            self.play_shares = _checked_shares(play_shares)
        if share_slopes is not None:
            self.share_slopes = _checked_slopes(share_slopes)
        # The detector stays as it is (resume_from would reset it and then take back what
        # it had): only the memory's state is rebuilt.
        self._resume_memory(old)

    def resume_from(self, other: HysteresisModel) -> None:
        """Take over another model's state, recomputed with this model's branches.

        The Madelung state is fully given by the turning-point pressures and the current
        pressure, so replaying those rebuilds it; the detector keeps its branch and extreme.
        A parameter change at run time thus keeps the muscle's history instead of
        pretending it is at rest.
        """
        self._detector.reset()
        self._resume_memory(other)
        self._detector.resume_from(other._detector)

    def _resume_memory(self, other: HysteresisModel) -> None:
        """resume_from's memory part: everything but the detector."""
        self._reset_memory()
        if self._rule.replays_stack:
            for p_pa, _ in other._stack:
                self._step_madelung(p_pa)
            self._step_madelung(other.pressure_pa)
        else:
            self._p = other.pressure_pa
        self._rule.resume(self, other)

    @property
    def has_play_share(self) -> bool:
        """True when the rule's curves mix two shapes by a learned share ('identify')."""
        return self._rule.has_play_share

    @property
    def deadband_pa(self) -> float:
        return self._detector.deadband_pa

    @property
    def pressure_pa(self) -> float:
        return self._p

    @property
    def length_m(self) -> float:
        return self._l

    @property
    def rising(self) -> bool:
        """Direction of the current scanning curve: pressure last moved up."""
        return self._rising

    @property
    def branch(self) -> int:
        """The detector's branch (1 increasing, 2 decreasing), as published."""
        return self._detector.branch

    @property
    def rest_length_m(self) -> float:
        return float(self.increasing.length(0.0))

    @property
    def turning_points(self) -> tuple[tuple[float, float], ...]:
        """Madelung stack (pressure_pa, length_m), oldest first."""
        return tuple(self._stack)

    def path_state(self) -> PathState:
        """The state a path from here is built from, as named public values."""
        rule = self._rule
        return PathState(self._p, self._l, self._rising, tuple(self._stack), self.increasing,
                         self.decreasing, rule.path_kind, rule.has_play_share,
                         self.play_shares, self.share_slopes, self.max_gauge_pressure_pa)

    def kernel_numbers(self, numbers: np.ndarray, stack: np.ndarray) -> None:
        """This state into a compiled step's numbers (kernel.N_P to N_SLOPE_DOWN) and stack
        (its turning points, oldest first)."""
        numbers[kernel.N_P], numbers[kernel.N_L], numbers[kernel.N_RISING] = (
            self._p, self._l, self._rising)
        numbers[kernel.N_PLAY_RISING], numbers[kernel.N_PLAY_P] = self._play_source
        numbers[kernel.N_BRANCH] = self._detector.branch
        numbers[kernel.N_EXTREME] = self._detector._extreme_pa
        numbers[kernel.N_COUNT], numbers[kernel.N_VALID] = len(self._stack), 0.0
        numbers[kernel.N_SHARE_UP], numbers[kernel.N_SHARE_DOWN] = self.play_shares
        numbers[kernel.N_SLOPE_UP], numbers[kernel.N_SLOPE_DOWN] = self.share_slopes
        if self._stack:
            stack[:len(self._stack)] = self._stack

    def load_kernel_numbers(self, numbers: np.ndarray, stack: np.ndarray, increasing: Branch,
                            decreasing: Branch) -> None:
        """The state a compiled step left in its numbers and stack (kernel_numbers' layout),
        on these branches."""
        values = numbers[:kernel.N_SLOPE_DOWN + 1].tolist()
        self.increasing, self.decreasing = increasing, decreasing
        self._p, self._l = values[kernel.N_P], values[kernel.N_L]
        self._rising = values[kernel.N_RISING] != 0.0
        self._play_source = (values[kernel.N_PLAY_RISING] != 0.0, values[kernel.N_PLAY_P])
        self._detector.branch = int(values[kernel.N_BRANCH])
        self._detector._extreme_pa = values[kernel.N_EXTREME]
        self._stack = [tuple(point) for point in stack[:int(values[kernel.N_COUNT])].tolist()]
        self.play_shares = (values[kernel.N_SHARE_UP], values[kernel.N_SHARE_DOWN])
        self.share_slopes = (values[kernel.N_SLOPE_UP], values[kernel.N_SLOPE_DOWN])
        self._cached_key, self._cached_curve = None, None
        self._gradient_cache, self._gradient_ends = ([], []), (None, None)

    def major(self, rising: bool) -> Branch:
        """The major branch pressure follows when moving up (True) or down."""
        return self.increasing if rising else self.decreasing

    def _curve(self, rising: bool, stack: list[tuple[float, float]]) -> ScanningCurve:
        major = self.major(rising)
        if not stack:
            return ScanningCurve(major)
        if len(stack) >= 2:
            target = stack[-2]
        else:
            anchor_pa = self.max_gauge_pressure_pa if rising else 0.0
            target = (anchor_pa, float(major.length(anchor_pa)))
        return self._rule.curve(self, rising, major, stack[-1], target)

    def origin_depth(self, rising: bool, origin: tuple[float, float]) -> float:
        """Where a reversal O lies across the major loop, seen from the branch its scanning
        curve heads for: 0 on that branch, 1 on the other (after a full excursion).

        The play share may depend on it (`share_slopes`): what a muscle does after a
        reversal differs between a full excursion and a short one, and how differs by
        mechanism (the learned slopes: docs/model-history.md, "The share's slope across the
        loop"). Where the branches meet (near 0 Pa) every point is on both: 1, as after a full
        excursion.
        """
        p_origin, l_origin = origin
        return kernel.origin_depth(float(self.major(rising).length(p_origin)),
                                   float(self.major(not rising).length(p_origin)), l_origin,
                                   NARROW_LOOP_M)

    def current_origin_depth(self) -> float:
        """origin_depth of the scanning curve in force (MID_DEPTH on a major branch)."""
        return self._rule.origin_depth(self)

    def expert_lengths(self) -> tuple[float, float]:
        """(play-like, Madelung) lengths at the current pressure on the current curve.

        The two shapes the 'identify' rule mixes, from the same turning points: they agree
        on a major branch and differ after a reversal, so their difference says how much
        the minor-loop rule matters here (and is the regressor that learns the share).
        Other rules have no such pair: both are the current length.
        """
        return self._rule.expert_lengths(self)

    def length_gradient(self, sensitivity: BranchSensitivity) -> np.ndarray:
        """d length / d parameters at the current state, the parameters being those
        `sensitivity` gives the branches' derivatives over (its last two: the rising and the
        falling play share).

        What the online identification learns from: the rule's (rules.py; exact for the
        stack rules, through every remembered turning point).
        """
        return self._rule.length_gradient(self, sensitivity)

    def _push(self, point: tuple[float, float]) -> None:
        self._stack.append(point)
        if len(self._stack) > MAX_TURNING_POINTS:
            del self._stack[:2]

    def _wipe_out(self, p_pa: float) -> bool:
        """Pop (O, T) if p_pa has reached P_T; True when something was popped."""
        if len(self._stack) < 2:
            return False
        target_pa = self._stack[-2][0]
        if (p_pa >= target_pa) if self._rising else (p_pa <= target_pa):
            del self._stack[-2:]
            return True
        return False

    # --- forward --------------------------------------------------------------------

    def update(self, p_pa: float) -> tuple[float, int]:
        """Advance by one gauge pressure [Pa]; returns (length_m, branch).

        NaN or inf raises ValueError and leaves the state untouched.
        """
        p_pa = float(p_pa)
        if not math.isfinite(p_pa):
            raise ValueError(f'gauge pressure must be finite, got {p_pa!r}')
        branch = self._detector.update(p_pa)
        self._rule.update(self, p_pa, branch)
        return self._l, branch

    def _step_madelung(self, p_pa: float) -> None:
        if p_pa != self._p:
            rising = p_pa > self._p
            if rising != self._rising:
                self._push((self._p, self._l))
                self._rising = rising
            while self._wipe_out(p_pa):
                pass
            self._l = float(self._current_curve().length(p_pa))
            self._p = p_pa

    def _current_curve(self) -> ScanningCurve:
        """The curve in force, rebuilt only when the direction or the stack's top changes."""
        key = (self._rising, len(self._stack), tuple(self._stack[-2:]))
        if key != self._cached_key:
            self._cached_key = key
            self._cached_curve = self._curve(self._rising, self._stack)
        return self._cached_curve

    def advance(self, p_pa) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised `update` over an array: (lengths_m, branches), state advanced.

        Same result as calling update() per sample, except that NaN/inf samples give a NaN
        length (and the branch in force) instead of raising.
        """
        pressures = np.asarray(p_pa, dtype=float).ravel()
        branches = self._detector.detect(pressures)
        lengths = np.full(pressures.size, np.nan)
        finite = np.flatnonzero(np.isfinite(pressures))
        if finite.size == 0:
            return lengths, branches
        lengths[finite] = self._rule.advance(self, pressures[finite], branches[finite])
        return lengths, branches

    def predict(self, p_pa) -> np.ndarray:
        """Lengths [m] for a whole pressure path simulated from rest; this model is unchanged."""
        fresh = copy.deepcopy(self)
        fresh.reset()
        return fresh.advance(p_pa)[0]

    # --- inverse --------------------------------------------------------------------

    def auto_branch(self, length_m: float) -> int:
        """AUTO rule: a target shorter than now needs more pressure -> increasing."""
        return BRANCH_INCREASING if length_m < self._l else BRANCH_DECREASING

    def pressure_for_length(self, length_m: float, branch: int = BRANCH_AUTO) -> InverseResult:
        """Gauge pressure [Pa] that gives length_m, never outside 0..max_gauge_pressure_pa.

        INCREASING / DECREASING: that direction's major branch over 0..max (the paper's
        per-branch inverse; the state does not matter). AUTO: from the current state, in
        the direction the target needs (shorter -> rising); with 'identify', 'madelung' or
        'play' memory along the path pressure would really follow
        (`path_pressure_for_length`), with 'switch' on that direction's major branch.
        Refusals carry the reachable range.
        """
        if branch not in (BRANCH_AUTO, BRANCH_INCREASING, BRANCH_DECREASING):
            return InverseResult(False, f'unknown branch {branch!r}: use 0 (auto), '
                                 '1 (increasing) or 2 (decreasing)', math.nan, 0, math.nan,
                                 math.nan)
        length_m = _as_float(length_m)
        if not math.isfinite(length_m):
            return InverseResult(False, f'target length must be finite, got {length_m!r}',
                                 math.nan, 0, math.nan, math.nan)
        if branch == BRANCH_AUTO:
            rising = self.auto_branch(length_m) == BRANCH_INCREASING
            if self._rule.follows_path:
                return self.path_pressure_for_length(length_m, rising)
        else:
            rising = branch == BRANCH_INCREASING
        ends = (0.0, self.max_gauge_pressure_pa)
        segments = [(ScanningCurve(self.major(rising)), *(ends if rising else ends[::-1]))]
        name = BRANCH_NAMES[BRANCH_INCREASING if rising else BRANCH_DECREASING]
        return self._invert_along(segments, rising, length_m, f'{name} major branch')

    def path_pressure_for_length(self, length_m: float, rising: bool) -> InverseResult:
        """The pressure at which length_m is reached if pressure moves from the current state.

        The path is the current scanning curve if the state already moves that way, else
        the curve a reversal right now would start, continuing through wiping-out to 0 Pa
        or the maximum: what a controller needs, since that is what the muscle will do.
        """
        length_m = _as_float(length_m)
        if not math.isfinite(length_m):
            return InverseResult(False, f'target length must be finite, got {length_m!r}',
                                 math.nan, 0, math.nan, math.nan)
        name = BRANCH_NAMES[BRANCH_INCREASING if rising else BRANCH_DECREASING]
        where = f'{name} path from the current state ({self._p:.6g} Pa, {self._l:.6g} m)'
        return self._invert_along(self.path_segments(rising), rising, length_m,
                                  where)

    def path_segments(self, rising: bool) -> list[Segment]:
        """The pieces (curve, from_pa, to_pa) of the path pressure would follow moving one
        way from here, as kernel.path_segments builds them for the rule's `path_kind`: the
        turning-point stack's curves through wiping-out to 0 Pa or the maximum, or the band's
        hold until the major branch meets the length, then that branch."""
        state = self.path_state()
        kept = self._kernel_branches
        if kept[0] is not self.increasing or kept[1] is not self.decreasing:
            kept = (self.increasing, self.decreasing, kernel.branch_table(
                [self.increasing.kernel_row, self.decreasing.kernel_row]))
            self._kernel_branches = kept
        rows = kernel.path_of(np.array(expert_row(state), dtype=float),
                              np.array(state.turning_points, dtype=float).reshape(-1, 2),
                              kept[2], rising, PATH_SCALARS).tolist()
        major = self.major(rising)
        return [(ScanningCurve(major) if row[kernel.G_ORIGIN] == 0.0 else ScanningCurve(
                     major, (row[kernel.G_P_ORIGIN], row[kernel.G_L_ORIGIN]),
                     (row[kernel.G_P_TARGET], row[kernel.G_L_TARGET]), row[kernel.G_SHARE],
                     row[kernel.G_DEPTH]),
                 row[kernel.G_FROM], row[kernel.G_TO]) for row in rows]

    def path_map(self, rising: bool) -> Callable[[float], float]:
        """length(p_pa) if pressure moved to p_pa one way from the current state.

        The forward map `path_pressure_for_length` inverts, for a caller that must search
        (a mix of rules has no closed-form inverse: mix.RuleMix). The pieces of the
        path are built once, here; the map is for the current state only.
        """
        segments = self.path_segments(rising)
        held_m = self._l

        def length_at(p_pa: float) -> float:
            for curve, p_from, p_to in segments:
                if (p_pa < p_from) if rising else (p_pa > p_from):
                    return held_m   # play's hold, before its branch is met
                if (p_pa <= p_to) if rising else (p_pa >= p_to):
                    return float(curve.length(float(p_pa)))
            return float(segments[-1][0].length(float(p_pa)))

        return length_at

    def _invert_along(self, segments: list[Segment], rising: bool,
                      length_m: float, where: str) -> InverseResult:
        branch = BRANCH_INCREASING if rising else BRANCH_DECREASING
        pieces = []
        for curve, p_from, p_to in segments:
            # Only the part of each piece that lies ahead of us and inside 0..limit counts.
            limit_pa = curve.major.invertible_pressure_limit(self.max_gauge_pressure_pa)
            low_pa, high_pa = (p_from, p_to) if rising else (p_to, p_from)
            low_pa, high_pa = max(low_pa, 0.0), min(high_pa, limit_pa)
            if low_pa <= high_pa:
                pieces.append((curve, low_pa, high_pa, float(curve.length(low_pa)),
                               float(curve.length(high_pa))))
        if not pieces:
            return InverseResult(False, f'no pressure within 0..{self.max_gauge_pressure_pa:.6g}'
                                 f' Pa is reachable on the {where}', math.nan, 0, math.nan,
                                 math.nan)
        ends = [value for piece in pieces for value in piece[3:]]
        min_length_m, max_length_m = min(ends), max(ends)
        for curve, low_pa, high_pa, l_low, l_high in pieces:
            if min(l_low, l_high) - ROUNDING_M <= length_m <= max(l_low, l_high) + ROUNDING_M:
                pressure = curve.pressure(length_m)
                if math.isnan(pressure):
                    pressure = low_pa if abs(length_m - l_low) <= abs(length_m - l_high) \
                        else high_pa
                pressure = min(max(pressure, low_pa), high_pa)
                return InverseResult(True, f'on the {where}', pressure, branch,
                                     min_length_m, max_length_m)
        return InverseResult(
            False, f'length {length_m:.6g} m is not reachable on the {where}: reachable '
            f'[{min_length_m:.6g}, {max_length_m:.6g}] m with 0..'
            f'{self.max_gauge_pressure_pa:.6g} Pa', math.nan, 0, min_length_m, max_length_m)
