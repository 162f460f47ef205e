"""Hysteresis memory: how the two major branches combine into a length for any pressure path.

Four rules (docs/model.md has the full story and their errors on minor loops):

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

The Madelung stack follows every reversal of the pressure signal (loops smaller than the
noise close on themselves and are wiped out); the deadband detector gives the reported
branch, drives 'switch', and is the one the offline refit uses.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pma_model.branches import DEFAULT_MAX_GAUGE_PRESSURE_PA, Branch
from pma_model.detector import (
    BRANCH_AUTO,
    BRANCH_DECREASING,
    BRANCH_INCREASING,
    BRANCH_NAMES,
    DEFAULT_DEADBAND_PA,
    BranchDetector,
)

MEMORY_MODES = ('identify', 'madelung', 'switch', 'play')
# (branch, rising, p_pa) -> d (that major branch's length at p_pa) / d the learned parameters,
# a vector whose last two entries are the rising and falling play shares (zero here: a branch
# does not depend on them). HysteresisModel.length_gradient carries it through the memory.
BranchSensitivity = Callable[[Branch, bool, float], np.ndarray]
# Modes whose state is the Madelung turning-point stack.
_STACK_MODES = ('identify', 'madelung')

# Nested turning points need distinct pressures, so a 10-bit sensor cannot fill this; the
# cap only bounds memory for pathological input. Overflow forgets the oldest loop.
MAX_TURNING_POINTS = 512

# Monotone runs shorter than this are stepped sample by sample (noisy data reverses
# nearly every sample; one numpy evaluation per run would cost more than stepping).
_SHORT_RUN = 32

# Below this |B(P_O) - B(P_T)| [m] the rescaling is 0/0 (both points in the flat region
# below 0 Pa): the curve is then B shifted through O instead.
_FLAT_SPAN_M = 1e-15

# The 'identify' share of a curve is play_share + slope * (origin_depth - MID_DEPTH): the
# shares are those of a reversal mid-loop, the slopes how they change across it.
MID_DEPTH = 0.5
# Branches closer than this [m] at a reversal's pressure: no loop to place it in.
_NARROW_LOOP_M = 1e-4

# Lengths this close [m] count as equal when deciding whether a curve reaches a target: a
# curve evaluated at its own origin can differ from the stored length in the last bit.
ROUNDING_M = 1e-12


@dataclass(frozen=True)
class InverseResult:
    """The answer to 'which pressure makes the muscle this long?' (PressureForLength)."""

    success: bool
    message: str
    gauge_pressure_pa: float
    branch: int
    min_length_m: float
    max_length_m: float


@dataclass(frozen=True)
class _CurveEnds:
    """Gradients a scanning curve's own gradient is made from: of its lengths at O and T,
    and of its major branch at their pressures."""

    origin: np.ndarray
    target: np.ndarray
    shape_at_origin: np.ndarray
    shape_at_target: np.ndarray


@dataclass(frozen=True)
class _Curve:
    """A scanning curve through O and T shaped like `major`; O is None for the major itself.

    `play_share` mixes the play-like shape into Madelung's (the 'identify' rule; 0 is pure
    Madelung). The shape is Phi(s) = w * min(1, s / q) + (1 - w) * s in the branch
    coordinate s (1 at O, 0 at T), piecewise linear, so it inverts in closed form.
    """

    major: Branch
    origin: tuple[float, float] | None = None
    target: tuple[float, float] | None = None
    play_share: float = 0.0
    origin_depth: float = MID_DEPTH   # O's place across the loop (HysteresisModel.origin_depth)

    def __post_init__(self):
        # Computed once, here: every curve is evaluated, and a commit of the online learning
        # rebuilds the curves of the whole stack (cached_property's first access cost more).
        if self.origin is None:
            return
        (_, l_origin), (_, l_target) = self.origin, self.target
        b_origin = float(self.major.length(self.origin[0]))
        b_target = float(self.major.length(self.target[0]))
        flat = abs(b_origin - b_target) < _FLAT_SPAN_M
        ratio = 1.0 if flat else (l_origin - l_target) / (b_origin - b_target)
        object.__setattr__(self, '_span', (b_origin, b_target))
        object.__setattr__(self, '_is_flat', flat)
        # q: where the play-like shape stops holding (1 when it would not reach T).
        object.__setattr__(self, '_knee', ratio if 0.0 < ratio < 1.0 else 1.0)
        object.__setattr__(self, '_knee_moves', not flat and 0.0 < ratio < 1.0)

    def _flat(self) -> bool:
        return self._is_flat

    def _coordinate(self, shape):
        b_origin, b_target = self._span
        s = (shape - b_target) / (b_origin - b_target)
        if isinstance(s, float):
            return min(max(s, 0.0), 1.0)
        return np.clip(s, 0.0, 1.0)

    def length(self, p_pa):
        shape = self.major.length(p_pa)
        if self.origin is None:
            return shape
        (_, l_origin), (_, l_target) = self.origin, self.target
        b_origin, b_target = self._span
        if self._flat():
            return l_origin + (shape - b_origin)
        if self.play_share == 0.0:
            return l_target + (l_origin - l_target) * (shape - b_target) / (b_origin - b_target)
        s = self._coordinate(shape)
        w = self.play_share
        knee = self._knee
        held = min(1.0, s / knee) if isinstance(s, float) else np.minimum(1.0, s / knee)
        result = l_target + (l_origin - l_target) * (w * held + (1.0 - w) * s)
        if isinstance(result, float):   # one sample (np.ndim costs more than the curve)
            return float(result)
        return float(result) if np.ndim(result) == 0 else result

    def shapes_at(self, p_pa: float) -> tuple[float, float]:
        """(play-like, Madelung) lengths at p_pa: the two shapes the share mixes."""
        shape = float(self.major.length(p_pa))
        if self.origin is None:
            return shape, shape
        (_, l_origin), (_, l_target) = self.origin, self.target
        if self._flat():
            value = l_origin + (shape - self._span[0])
            return value, value
        s = float(self._coordinate(shape))
        return (l_target + (l_origin - l_target) * min(1.0, s / self._knee),
                l_target + (l_origin - l_target) * s)

    def gradient(self, p_pa: float, shape_gradient: np.ndarray, ends: _CurveEnds,
                 share_index: int | None) -> np.ndarray:
        """d length(p_pa) / d parameters, forward mode through the curve's two points.

        `shape_gradient`: d major(p_pa) / d parameters; `ends`: those of O and T and of the
        major branch at their pressures (`HysteresisModel` carries them along the stack).
        The play share is parameter `share_index` (None: the rule has none); the curve's
        share counts as a constant of the curve (through a slope it also depends on O's
        place across the loop, which is left out). With
        D = L_O - L_T, E = B(P_O) - B(P_T), s = (B(P) - B(P_T)) / E and
        Phi(s) = w min(1, s / q) + (1 - w) s, the length L_T + D Phi(s) moves by
        dL = dL_T + (dL_O - dL_T) Phi + D (Phi'(s) ds + (min(1, s / q) - s) dw + dPhi/dq dq).
        """
        if self.origin is None:
            return shape_gradient
        if self._flat():
            return ends.origin + shape_gradient - ends.shape_at_origin
        b_origin, b_target = self._span
        span = b_origin - b_target
        difference = self.origin[1] - self.target[1]
        raw = (float(self.major.length(p_pa)) - b_target) / span
        s = min(max(raw, 0.0), 1.0)
        w, knee = self.play_share, self._knee
        held = min(1.0, s / knee)
        linear = raw if w == 0.0 else s   # as length(): Madelung extrapolates, a mix clips
        between = ends.origin - ends.target
        result = ends.target + between * (w * held + (1.0 - w) * linear)
        span_gradient = ends.shape_at_origin - ends.shape_at_target
        if w == 0.0 or 0.0 < raw < 1.0:
            slope = (w / knee if s < knee else 0.0) + (1.0 - w)
            result += (difference * slope / span) * (
                shape_gradient - ends.shape_at_target - s * span_gradient)
        if w > 0.0 and s < knee and self._knee_moves:
            result -= (difference * w * s / (knee * knee * span)) * (
                between - knee * span_gradient)
        if share_index is not None:
            result[share_index] += difference * (held - s)
        return result

    def pressure(self, length_m: float) -> float:
        """P with length(P) == length_m, through B^-1 (NaN when the shape has none)."""
        if self.origin is None:
            return float(self.major.inverse_unchecked(length_m))
        (p_origin, l_origin), (_, l_target) = self.origin, self.target
        b_origin, b_target = self._span
        if self._flat():
            shape = length_m - l_origin + b_origin
        elif l_origin == l_target:
            return p_origin if length_m == l_origin else math.nan
        else:
            mixed = (length_m - l_target) / (l_origin - l_target)
            s = self._coordinate_for(mixed)
            if math.isnan(s):
                return math.nan
            if s == 1.0:
                return p_origin   # a held length is reached where it is: at O
            shape = b_target + s * (b_origin - b_target)
        return float(self.major.inverse_unchecked(shape))

    def _coordinate_for(self, mixed: float) -> float:
        """s with Phi(s) == mixed (NaN outside 0..1)."""
        w, knee = self.play_share, self._knee
        if w == 0.0:
            return mixed   # Madelung: linear, the caller keeps it within the curve's ends
        if not -1e-12 <= mixed <= 1.0 + 1e-12:
            return math.nan
        at_knee = w + (1.0 - w) * knee
        if mixed <= at_knee:
            return mixed / (w / knee + 1.0 - w)
        if w >= 1.0:
            return 1.0
        return min(1.0, (mixed - w) / (1.0 - w))


def _checked_shares(shares) -> tuple[float, float]:
    """(rising, falling) play shares of the 'identify' rule, each within 0..1."""
    rising, falling = (float(value) for value in shares)
    for name, value in (('rising', rising), ('falling', falling)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f'the {name} play share must be within 0..1, got {value!r}')
    return rising, falling


def play_share_at(share: float, slope: float, depth: float) -> float:
    """The 'identify' share of a curve whose reversal lies at `depth` across the loop
    (HysteresisModel.origin_depth), within 0..1."""
    return min(1.0, max(0.0, share + slope * (depth - MID_DEPTH)))


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
        if memory not in MEMORY_MODES:
            raise ValueError(f'memory must be one of {MEMORY_MODES}, got {memory!r}')
        if not (math.isfinite(max_gauge_pressure_pa) and max_gauge_pressure_pa > 0):
            raise ValueError('max_gauge_pressure_pa must be finite and > 0, '
                             f'got {max_gauge_pressure_pa!r}')
        self.increasing = increasing
        self.decreasing = decreasing
        self.memory = memory
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
        self._cached_curve: _Curve | None = None
        # Play: the branch (True increasing) and pressure the held length was last set on.
        self._play_source = (True, 0.0)
        # length_gradient's: the stack it was computed for and its turning points' gradients,
        # and the current curve with its ends' gradients.
        self._gradient_cache: tuple[list, list] = ([], [])
        self._gradient_ends: tuple[_Curve | None, _CurveEnds | None] = (None, None)

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
        for p_pa, _ in other._stack:
            self._step_madelung(p_pa)
        self._step_madelung(other.pressure_pa)
        if self.memory == 'switch':
            self._l = float(self.major(other.branch == BRANCH_INCREASING).length(self._p))
        elif self.memory == 'play':
            # The play state is the length itself: kept, inside the new band at this pressure.
            self._stack = []
            self._rising = other._rising
            low = float(self.decreasing.length(self._p))
            high = float(self.increasing.length(self._p))
            self._l = min(max(other.length_m, low), high)
            # Moved onto a branch by the new band: that branch is what it depends on now.
            self._play_source = (other._play_source if low < other.length_m < high
                                 else (other.length_m >= high, self._p))

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

    def major(self, rising: bool) -> Branch:
        """The major branch pressure follows when moving up (True) or down."""
        return self.increasing if rising else self.decreasing

    def _curve(self, rising: bool, stack: list[tuple[float, float]]) -> _Curve:
        major = self.major(rising)
        if not stack:
            return _Curve(major)
        if len(stack) >= 2:
            target = stack[-2]
        else:
            anchor_pa = self.max_gauge_pressure_pa if rising else 0.0
            target = (anchor_pa, float(major.length(anchor_pa)))
        if self.memory != 'identify':
            return _Curve(major, stack[-1], target)
        depth = self.origin_depth(rising, stack[-1])
        index = 0 if rising else 1
        share = play_share_at(self.play_shares[index], self.share_slopes[index], depth)
        return _Curve(major, stack[-1], target, share, depth)

    def origin_depth(self, rising: bool, origin: tuple[float, float]) -> float:
        """Where a reversal O lies across the major loop, seen from the branch its scanning
        curve heads for: 0 on that branch, 1 on the other (after a full excursion).

        The play share may depend on it (`share_slopes`): what a muscle does after a
        reversal differs between a full excursion and a short one, and how differs by
        mechanism (the learned slopes: docs/model.md §3.1). Where the branches meet (near
        0 Pa) every point is on both: 1, as after a full excursion.
        """
        p_origin, l_origin = origin
        toward = float(self.major(rising).length(p_origin))
        width = float(self.major(not rising).length(p_origin)) - toward
        if abs(width) < _NARROW_LOOP_M:
            return 1.0
        return min(1.0, max(0.0, (l_origin - toward) / width))

    def current_origin_depth(self) -> float:
        """origin_depth of the scanning curve in force (MID_DEPTH on a major branch)."""
        if self.memory not in _STACK_MODES:
            return MID_DEPTH
        return self._current_curve().origin_depth

    def expert_lengths(self) -> tuple[float, float]:
        """(play-like, Madelung) lengths at the current pressure on the current curve.

        The two shapes the 'identify' rule mixes, from the same turning points: they agree
        on a major branch and differ after a reversal, so their difference says how much
        the minor-loop rule matters here (and is the regressor that learns the share).
        Other rules have no such pair: both are the current length.
        """
        if self.memory not in _STACK_MODES:
            return self._l, self._l
        return self._current_curve().shapes_at(self._p)

    def length_gradient(self, sensitivity: BranchSensitivity) -> np.ndarray:
        """d length / d parameters at the current state, the parameters being those
        `sensitivity` gives the branches' derivatives over (its last two: the rising and the
        falling play share).

        What the online identification learns from. Exact for the stack rules: it is
        carried through every remembered turning point, since a scanning curve's length is
        pinned to its turning points, whose lengths came from earlier curves, often on the
        other branch. Play: the branch and pressure its held length was set at; switch: the
        detector's branch. Cost: the current curve's, plus the stack's once it changes.
        """
        if self.memory == 'switch':
            rising = self._detector.branch == BRANCH_INCREASING
            return sensitivity(self.major(rising), rising, self._p)
        if self.memory == 'play':
            rising, p_pa = self._play_source
            return sensitivity(self.major(rising), rising, p_pa)
        gradients = self._turning_point_gradients(sensitivity)
        curve = self._current_curve()
        cached_curve, ends = self._gradient_ends
        if curve is not cached_curve:
            ends = self._ends(curve, self._rising, gradients, sensitivity)
            self._gradient_ends = (curve, ends)
        return curve.gradient(self._p, sensitivity(curve.major, self._rising, self._p), ends,
                              self._share_index(self._rising))

    def _share_index(self, rising: bool) -> int | None:
        return (-2 if rising else -1) if self.memory == 'identify' else None

    def _turning_point_gradients(self, sensitivity: BranchSensitivity) -> list[np.ndarray]:
        """The gradient of each remembered turning point's length, oldest first (kept while
        the stack below the top is the same)."""
        stack = self._stack
        known, gradients = self._gradient_cache
        if known == stack:
            return gradients
        kept = 0
        while kept < min(len(known), len(stack)) and known[kept] == stack[kept]:
            kept += 1
        gradients = gradients[:kept]
        for depth in range(kept, len(stack)):
            # Turning points alternate: the top was reached moving against the current way.
            arriving = self._rising if (len(stack) - 1 - depth) % 2 else not self._rising
            curve = self._curve(arriving, stack[:depth])
            p_pa = stack[depth][0]
            gradients.append(curve.gradient(
                p_pa, sensitivity(curve.major, arriving, p_pa),
                self._ends(curve, arriving, gradients, sensitivity),
                self._share_index(arriving)))
        self._gradient_cache = (list(stack), gradients)
        return gradients

    @staticmethod
    def _ends(curve: _Curve, rising: bool, gradients: list[np.ndarray],
              sensitivity: BranchSensitivity) -> _CurveEnds | None:
        """The gradients at the curve's O and T; `gradients`: its turning points', oldest
        first (O is the last; T the one before, or the anchor on the major branch)."""
        if curve.origin is None:
            return None
        at_origin = sensitivity(curve.major, rising, curve.origin[0])
        at_target = sensitivity(curve.major, rising, curve.target[0])
        target = gradients[-2] if len(gradients) >= 2 else at_target
        return _CurveEnds(gradients[-1], target, at_origin, at_target)

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
        if self.memory == 'switch':
            self._p, self._l = p_pa, float(self.major(branch == BRANCH_INCREASING).length(p_pa))
            return self._l, branch
        if self.memory == 'play':
            self._step_play(p_pa)
            return self._l, branch
        self._step_madelung(p_pa)   # 'madelung' and 'identify'
        return self._l, branch

    def _step_play(self, p_pa: float) -> None:
        if p_pa > self._p:
            bound = float(self.increasing.length(p_pa))
            if bound <= self._l:
                self._l, self._play_source = bound, (True, p_pa)
            self._rising = True
        elif p_pa < self._p:
            bound = float(self.decreasing.length(p_pa))
            if bound >= self._l:
                self._l, self._play_source = bound, (False, p_pa)
            self._rising = False
        self._p = p_pa

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

    def _current_curve(self) -> _Curve:
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
        values = pressures[finite]
        if self.memory == 'switch':
            rising = branches[finite] == BRANCH_INCREASING
            lengths[finite] = np.where(rising, self.increasing.length(values),
                                       self.decreasing.length(values))
            self._p, self._l = float(values[-1]), float(lengths[finite[-1]])
            return lengths, branches
        if self.memory == 'play':
            lengths[finite] = self._advance_play(values)
            return lengths, branches
        lengths[finite] = self._advance_madelung(values)
        return lengths, branches

    def _monotone_runs(self, values: np.ndarray):
        """(start, end, rising) of each run of one direction; holds keep the direction."""
        previous = np.concatenate(([self._p], values[:-1]))
        steps = np.sign(values - previous)
        last_move = np.maximum.accumulate(np.where(steps != 0, np.arange(values.size), -1))
        direction = np.where(last_move >= 0, steps[np.maximum(last_move, 0)],
                             1.0 if self._rising else -1.0)
        run_starts = np.concatenate(([0], np.flatnonzero(direction[1:] != direction[:-1]) + 1))
        run_ends = np.concatenate((run_starts[1:], [values.size]))
        return [(int(start), int(end), bool(direction[start] > 0))
                for start, end in zip(run_starts, run_ends, strict=True)]

    def _advance_play(self, values: np.ndarray) -> np.ndarray:
        """Play over finite pressures: within a monotone run the bound moves one way only."""
        out = np.empty(values.size)
        for start, end, rising in self._monotone_runs(values):
            run = values[start:end]
            bound = np.asarray(self.major(rising).length(run), dtype=float)
            out[start:end] = np.minimum(self._l, bound) if rising else np.maximum(self._l, bound)
            if out[end - 1] == bound[-1]:   # on the branch at the end of the run (it stays)
                self._play_source = (rising, float(run[-1]))
            self._rising = rising
            self._p, self._l = float(run[-1]), float(out[end - 1])
        return out

    def predict(self, p_pa) -> np.ndarray:
        """Lengths [m] for a whole pressure path simulated from rest; this model is unchanged."""
        fresh = copy.deepcopy(self)
        fresh.reset()
        return fresh.advance(p_pa)[0]

    def _advance_madelung(self, values: np.ndarray) -> np.ndarray:
        """Madelung over finite pressures, one numpy evaluation per curve segment."""
        out = np.empty(values.size)
        for start, end, rising in self._monotone_runs(values):
            if end - start < _SHORT_RUN:  # numpy's per-call cost dominates: step instead
                for index in range(start, end):
                    self._step_madelung(float(values[index]))
                    out[index] = self._l
                continue
            if rising != self._rising:
                self._push((self._p, self._l))
                self._rising = rising
            position = start
            while position < end:
                stop = end
                if len(self._stack) >= 2:
                    target_pa = self._stack[-2][0]
                    run = values[position:end]
                    reached = (run >= target_pa) if rising else (run <= target_pa)
                    if reached.any():
                        stop = position + int(np.argmax(reached))
                if stop > position:
                    out[position:stop] = self._curve(rising, self._stack).length(
                        values[position:stop])
                if stop < end:
                    del self._stack[-2:]
                position = stop
            self._p, self._l = float(values[end - 1]), float(out[end - 1])
        return out

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
            if self.memory != 'switch':
                return self.path_pressure_for_length(length_m, rising)
        else:
            rising = branch == BRANCH_INCREASING
        ends = (0.0, self.max_gauge_pressure_pa)
        segments = [(_Curve(self.major(rising)), *(ends if rising else ends[::-1]))]
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
        return self._invert_along(self._path_segments(rising), rising, length_m, where)

    def _path_segments(self, rising: bool) -> list[tuple[_Curve, float, float]]:
        return (self._play_segments(rising) if self.memory == 'play'
                else self._future_segments(rising))

    def path_map(self, rising: bool) -> Callable[[float], float]:
        """length(p_pa) if pressure moved to p_pa one way from the current state.

        The forward map `path_pressure_for_length` inverts, for a caller that must search
        (a mix of rules has no closed-form inverse: forecaster.RuleMix). The pieces of the
        path are built once, here; the map is for the current state only.
        """
        segments = self._path_segments(rising)
        held_m = self._l

        def length_at(p_pa: float) -> float:
            for curve, p_from, p_to in segments:
                if (p_pa < p_from) if rising else (p_pa > p_from):
                    return held_m   # play's hold, before its branch is met
                if (p_pa <= p_to) if rising else (p_pa >= p_to):
                    return float(curve.length(float(p_pa)))
            return float(segments[-1][0].length(float(p_pa)))

        return length_at

    def _play_segments(self, rising: bool) -> list[tuple[_Curve, float, float]]:
        """Play: the length holds until the major branch reaches it, then follows it."""
        major = self.major(rising)
        meets_pa = float(major.inverse_unchecked(self._l))
        if math.isnan(meets_pa):
            meets_pa = self._p
        join_pa = max(self._p, meets_pa) if rising else min(self._p, meets_pa)
        return [(_Curve(major), join_pa, self.max_gauge_pressure_pa if rising else 0.0)]

    def _invert_along(self, segments: list[tuple[_Curve, float, float]], rising: bool,
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

    def _future_segments(self, rising: bool) -> list[tuple[_Curve, float, float]]:
        """(curve, from_pa, to_pa) pieces pressure would follow moving one way from here."""
        stack = list(self._stack)
        if rising != self._rising:
            stack.append((self._p, self._l))
        segments = []
        p_from = self._p
        limit_pa = self.max_gauge_pressure_pa if rising else 0.0
        while True:
            curve = self._curve(rising, stack)
            p_to = stack[-2][0] if len(stack) >= 2 else limit_pa
            final = len(stack) < 2 or ((p_to >= limit_pa) if rising else (p_to <= limit_pa))
            if final:
                p_to = limit_pa
            segments.append((curve, p_from, p_to))
            if final:
                return segments
            del stack[-2:]
            p_from = p_to
