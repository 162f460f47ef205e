"""Scanning curves: the piece of the length-pressure map the memory is on between reversals.

A curve runs through its origin O (the last reversal) toward its target T (the reversal before,
or the anchor at the end of the major branch), shaped like the major branch it heads for
(memory.py's docstring has the rules that use them). With no O it is the major branch itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pma_model import kernel
from pma_model.branches import Branch

# Below this |B(P_O) - B(P_T)| [m] the rescaling is 0/0 (both points in the flat region
# below 0 Pa): the curve is then B shifted through O instead.
FLAT_SPAN_M = 1e-15

# The 'identify' share of a curve is play_share + slope * (origin_depth - MID_DEPTH): the
# shares are those of a reversal mid-loop, the slopes how they change across it.
MID_DEPTH = 0.5


def play_share_at(share: float, slope: float, depth: float) -> float:
    """The 'identify' share of a curve whose reversal lies at `depth` across the loop
    (HysteresisModel.origin_depth), within 0..1."""
    return kernel.play_share(share, slope, depth, MID_DEPTH)



@dataclass(frozen=True)
class CurveEnds:
    """Gradients a scanning curve's own gradient is made from: of its lengths at O and T,
    and of its major branch at their pressures."""

    origin: np.ndarray
    target: np.ndarray
    shape_at_origin: np.ndarray
    shape_at_target: np.ndarray


@dataclass(frozen=True)
class ScanningCurve:
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
        # q: where the play-like shape stops holding (1 when it would not reach T).
        flat, knee = kernel.curve_knee(l_origin, l_target, b_origin, b_target, FLAT_SPAN_M)
        object.__setattr__(self, '_span', (b_origin, b_target))
        object.__setattr__(self, '_is_flat', flat)
        object.__setattr__(self, '_knee', knee)
        object.__setattr__(self, '_knee_moves', not flat and knee < 1.0)

    def _flat(self) -> bool:
        return self._is_flat

    def length(self, p_pa):
        shape = self.major.length(p_pa)
        if self.origin is None:
            return shape
        (_, l_origin), (_, l_target) = self.origin, self.target
        b_origin, b_target = self._span
        if isinstance(shape, float):   # one sample: the compiled formula
            return kernel.curve_length(shape, l_origin, l_target, b_origin, b_target,
                                       self._is_flat, self.play_share, self._knee)
        # An array (Branch.length gives a float for one value): the same formula, compiled.
        return kernel.elementwise(kernel.curve_lengths, shape, l_origin, l_target, b_origin,
                                  b_target, self._is_flat, self.play_share, self._knee)

    def shapes_at(self, p_pa: float) -> tuple[float, float]:
        """(play-like, Madelung) lengths at p_pa: the two shapes the share mixes."""
        shape = float(self.major.length(p_pa))
        if self.origin is None:
            return shape, shape
        (_, l_origin), (_, l_target) = self.origin, self.target
        return kernel.curve_shapes(shape, l_origin, l_target, *self._span, self._is_flat,
                                   self._knee)

    def gradient(self, p_pa: float, shape_gradient: np.ndarray, ends: CurveEnds,
                 share_index: int | None) -> np.ndarray:
        """d length(p_pa) / d parameters, forward mode through the curve's two points.

        `shape_gradient`: d major(p_pa) / d parameters; `ends`: those of O and T and of the
        major branch at their pressures (the stack rules carry them along the stack).
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
        result = np.empty(shape_gradient.size)
        kernel.curve_gradient(result, shape_gradient, ends.origin, ends.target,
                              ends.shape_at_origin, ends.shape_at_target,
                              float(self.major.length(p_pa)), self.origin[1], self.target[1],
                              *self._span, self.play_share, self._knee, self._knee_moves,
                              -1 if share_index is None else share_index % result.size)
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
