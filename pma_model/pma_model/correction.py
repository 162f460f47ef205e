"""The learned branch correction: offsets given at knots, added inside a branch.

`CorrectedBranch` is a base branch plus a correction given at CORRECTION_KNOTS_PA,
interpolated between knots along the base branch's own length, so it stays monotone under a
simple bound (`monotone_correction`) and inverts in closed form. identification.OnlineModel
learns the offsets (a mean for both branches and their difference) and builds corrected
branches from them; `knot_sensitivity` is the derivative it learns through.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pma_model import kernel
from pma_model.branches import DEFAULT_MAX_GAUGE_PRESSURE_PA, Branch

# Every 50 kPa (Table 1's pressures) and 75 kPa: between 50 and 100 kPa the muscle leaves its
# dead zone (Table 1: flat to 50 kPa, then 9-15 mm of its 59 mm stroke by 100 kPa), where the
# slope changes most and where the onset lies differs from muscle to muscle; a correction that
# follows the sigmoid's own shape across that interval misses a sharp onset by millimetres
# (docs/model.md §5, "The knots").
CORRECTION_KNOTS_PA = (0.0, 50_000.0, 75_000.0, *(float(p) for p in range(100_000, 500_001,
                                                                            50_000)))
MAX_CORRECTION_M = 0.01      # |delta| limit at any knot
MAX_DIFFERENCE_M = 2 * MAX_CORRECTION_M   # each branch's own correction stays within the above
# knot_sensitivity's layout: [increasing knots, decreasing knots, rising share, falling share].
INCREASING_KNOTS = slice(0, len(CORRECTION_KNOTS_PA))
DECREASING_KNOTS = slice(len(CORRECTION_KNOTS_PA), 2 * len(CORRECTION_KNOTS_PA))


_MAX_KNOWN_LENGTHS = 256     # single-pressure lengths a CorrectedBranch keeps


@functools.lru_cache(maxsize=64)
def _lengths_at_knots(branch: Branch) -> tuple[float, ...]:
    """The branch's lengths at the knots: every commit makes new corrected branches over the
    same two base branches, so this is computed once per base, not once per commit."""
    return tuple(float(v) for v in branch.length(np.array(CORRECTION_KNOTS_PA)))


_MAX_BASE_POINTS = 4096      # single-pressure gradients a base branch keeps (_base_memo)


def _base_memo(branch: Branch) -> tuple[np.ndarray, dict]:
    """A base branch's memo: its kernel row with the knots and its lengths there
    (`_knot_row`) and {(rising, pressure): knot_sensitivity}, which does not depend on the
    learned offsets: kept on the base branch, so shared by every corrected branch over it (a
    commit makes new corrected branches and its replay asks for the same turning pressures
    again)."""
    memo = branch.__dict__.get('_points')
    if memo is None:   # a memo, not a field (frozen); with the knots' lengths (no hashing)
        memo = (_knot_row(branch), {})
        object.__setattr__(branch, '_points', memo)
    return memo


def _knot_row(branch: Branch) -> np.ndarray:
    """The base branch's kernel row with the knots and its lengths at them (a corrected
    branch's row, but for the offsets)."""
    knots = len(CORRECTION_KNOTS_PA)
    row = np.concatenate((branch.kernel_row[:kernel.ROW_HEAD], CORRECTION_KNOTS_PA,
                          _lengths_at_knots(branch), np.zeros(knots)))
    row[kernel.ROW_KNOTS] = knots
    return row


@dataclass(frozen=True)
class CorrectedBranch(Branch):
    """`base` plus a correction given at CORRECTION_KNOTS_PA, flat beyond them.

    Between two knots the correction is interpolated along the base branch's own length,
    not along pressure: with B_k the base length at knot k,
        delta(P) = d_k + (d_{k+1} - d_k) * (B_k - B(P)) / (B_k - B_{k+1}).
    So the corrected branch stays monotone exactly when d_{k+1} - d_k <= B_k - B_{k+1}
    (`monotone_correction`), it can go flat where the muscle is (the sigmoid's slope in the
    0-50 kPa dead zone), and its inverse is closed form: on interval k,
        B(P) = (L - d_k - r B_k) / (1 - r),  r = (d_{k+1} - d_k) / (B_k - B_{k+1}),
    then P = B^-1.
    """

    form: ClassVar[str] = 'corrected'

    base: Branch
    offsets_m: tuple[float, ...]

    @functools.cached_property
    def kernel_row(self) -> np.ndarray:
        """The base branch's row with the knots, its lengths there and the offsets."""
        if isinstance(self.base, CorrectedBranch):
            raise TypeError('a corrected branch corrects a branch form, not another correction')
        row = _base_memo(self.base)[0].copy()   # a commit makes new ones: the base's is kept
        row[kernel.ROW_HEAD + 2 * len(CORRECTION_KNOTS_PA):] = self.offsets_m
        return row

    def __post_init__(self):
        # Lengths already computed at single pressures. A sample asks for the same few (its
        # pressure for the length, the two memory shapes and the regressor; the knots around
        # it), and a commit's replay asks for each turning pressure three times; a commit
        # makes new branches, so this never goes stale.
        object.__setattr__(self, '_known_lengths', {})
        if len(self.offsets_m) != len(CORRECTION_KNOTS_PA):
            raise ValueError(f'a branch correction needs {len(CORRECTION_KNOTS_PA)} values '
                             f'(one per knot), got {len(self.offsets_m)}')

    def length(self, p_pa):
        if isinstance(p_pa, float):   # the online path: one sample, no numpy round trip
            known = self._known_lengths
            length = known.get(p_pa)
            if length is None:
                length = kernel.branch_length(self.kernel_row, p_pa)
                if len(known) >= _MAX_KNOWN_LENGTHS:   # a long noisy hold: start again
                    known.clear()
                known[p_pa] = length
            return length
        return super().length(p_pa)

    def invertible_pressure_limit(self, p_max_pa: float = DEFAULT_MAX_GAUGE_PRESSURE_PA):
        """The base branch's: a learned flat stretch (a plateau) is answered with its least
        pressure, it does not end the range the inverse answers for."""
        return self.base.invertible_pressure_limit(p_max_pa)

    def stroke_m(self) -> float:
        return self.base.stroke_m() + self.offsets_m[0] - self.offsets_m[-1]

    def saturation_length_m(self) -> float:
        return self.base.saturation_length_m() + self.offsets_m[-1]

    @classmethod
    def bounds(cls):
        raise TypeError('a corrected branch is learned online, not fitted')


def knot_row(branch: Branch) -> np.ndarray:
    """A branch's kernel row with the knots, as a corrected branch's (no correction: offsets
    0), a copy to change in place (kernel.online_step's commits write the offsets)."""
    if isinstance(branch, CorrectedBranch):
        return branch.kernel_row.copy()
    return _base_memo(branch)[0].copy()


def correction_caps(branch: Branch) -> np.ndarray:
    """Per knot interval: how much the correction may rise and keep the branch monotone."""
    return np.maximum(-np.diff(_lengths_at_knots(branch)), 0.0)


def monotone_correction(offsets, caps) -> tuple[float, ...]:
    """The offsets, bounded, each knot lowered only as needed (from 0 Pa upward) so that
    the corrected branch stays non-increasing. `caps`: correction_caps, as an array or a
    tuple of floats."""
    values = np.array(offsets, dtype=float)
    result = np.empty(values.size)
    kernel.monotone_offsets(values, np.asarray(caps, dtype=float), MAX_CORRECTION_M, result)
    return tuple(result.tolist())


def knot_sensitivity(branch: Branch, rising: bool, p_pa: float) -> np.ndarray:
    """d branch length(p_pa) / d [increasing knots, decreasing knots, the two play shares]
    (memory.BranchSensitivity): the interpolation weights of the branch's own correction,
    whichever branch of the pair `rising` says it is. Read-only: it is kept on the base
    branch (it does not depend on the learned offsets, and after a commit every turning
    point's is asked for again)."""
    base = branch.base if isinstance(branch, CorrectedBranch) else branch
    row, known = _base_memo(base)
    gradient = known.get((rising, p_pa))
    if gradient is None:
        knots = len(CORRECTION_KNOTS_PA)
        gradient = np.zeros(2 * knots + 2)
        kernel.add_knot_weights(gradient, row, 0 if rising else knots, float(p_pa))
        gradient.flags.writeable = False
        if len(known) >= _MAX_BASE_POINTS:   # a long noisy run: start again
            known.clear()
        known[rising, p_pa] = gradient
    return gradient
