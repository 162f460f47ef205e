"""Which hysteresis branch the muscle is on, from the pressure stream, with a deadband.

A reversal counts only once pressure has moved `deadband_pa` against the current direction
(measured from the extreme reached since the last reversal), so noise whose peak-to-peak
span is below the deadband cannot make the branch chatter. The sensor's +/-2 % of full
scale (+/-10 kPa) spans 20 kPa; Gaussian noise has no hard bound, and the extremes of an
hour-long hold reach further (the simulated rig's sigma of 2.5 kPa spans ~25 kPa over
360,000 samples), hence the 30 kPa default: a real reversal is confirmed 30 kPa late, which
only delays the reported branch (the Madelung memory follows every reversal). The online
detector (`update`) and the array form (`detect`, used by replay and the offline refit) run
the same rule and give identical labels; a test holds them to that.
"""

from __future__ import annotations

import math

import numpy as np

from pma_model import kernel

# The PmaPrediction / PressureForLength branch codes; the one home of these numbers here.
BRANCH_AUTO = 0
BRANCH_INCREASING = 1
BRANCH_DECREASING = 2
BRANCH_NAMES = {BRANCH_AUTO: 'auto', BRANCH_INCREASING: 'increasing',
                BRANCH_DECREASING: 'decreasing'}

DEFAULT_DEADBAND_PA = 30_000.0

_FIRST_WINDOW = 256


class BranchDetector:
    """Deadband reversal detector. Starts on the increasing branch (a muscle at rest)."""

    def __init__(self, deadband_pa: float = DEFAULT_DEADBAND_PA,
                 initial_branch: int = BRANCH_INCREASING):
        if not (math.isfinite(deadband_pa) and deadband_pa >= 0):
            raise ValueError(f'deadband_pa must be finite and >= 0, got {deadband_pa!r}')
        if initial_branch not in (BRANCH_INCREASING, BRANCH_DECREASING):
            raise ValueError(f'initial_branch must be 1 or 2, got {initial_branch!r}')
        self.deadband_pa = float(deadband_pa)
        self._initial_branch = initial_branch
        self.reset()

    def reset(self) -> None:
        self.branch = self._initial_branch
        self._extreme_pa = math.nan  # highest (increasing) or lowest (decreasing) since reversal

    def __copy__(self) -> BranchDetector:
        # As HysteresisModel.__copy__: the default costs five times this, once per commit.
        clone = object.__new__(type(self))
        clone.__dict__.update(self.__dict__)
        return clone

    def resume_from(self, other: BranchDetector) -> None:
        """Continue where `other` is (branch and extreme), keeping this deadband."""
        self.branch = other.branch
        self._extreme_pa = other._extreme_pa

    def update(self, p_pa: float) -> int:
        """Feed one gauge pressure [Pa]; returns the branch code for it.

        Raises ValueError for NaN or inf and leaves the state as it was.
        """
        p_pa = float(p_pa)
        if not math.isfinite(p_pa):
            raise ValueError(f'gauge pressure must be finite, got {p_pa!r}')
        self.branch, self._extreme_pa = kernel.detector_step(
            self.branch, self._extreme_pa, p_pa, self.deadband_pa, BRANCH_INCREASING,
            BRANCH_DECREASING)
        return self.branch

    def detect(self, p_pa) -> np.ndarray:
        """Branch codes (uint8) for a whole pressure array, continuing from the current state.

        Equivalent to calling `update` on each finite sample; NaN/inf samples are skipped
        (they get the branch in force). Work per reversal is a numpy scan, so long smooth
        recordings run at numpy speed.
        """
        pressures = np.asarray(p_pa, dtype=float).ravel()
        labels = np.empty(pressures.size, dtype=np.uint8)
        finite = np.isfinite(pressures)
        pressures = np.where(finite, pressures, np.nan)
        start = 0
        if math.isnan(self._extreme_pa):
            first = np.flatnonzero(finite)
            if first.size == 0:
                labels[:] = self.branch
                return labels
            self._extreme_pa = float(pressures[first[0]])
        while start < pressures.size:
            reversal, extreme = self._next_reversal(pressures, start)
            labels[start:reversal] = self.branch
            if reversal >= pressures.size:
                self._extreme_pa = extreme
                break
            self.branch = BRANCH_DECREASING if self.branch == BRANCH_INCREASING \
                else BRANCH_INCREASING
            self._extreme_pa = float(pressures[reversal])
            labels[reversal] = self.branch
            start = reversal + 1
        return labels

    def _next_reversal(self, pressures: np.ndarray, start: int) -> tuple[int, float]:
        """Index of the first sample at or after `start` that confirms a reversal.

        Scans growing windows with a running extreme (fmax/fmin skip NaN), so the cost is
        proportional to the distance to the reversal. Returns (len, extreme) if none.
        """
        rising = self.branch == BRANCH_INCREASING
        running = np.fmax if rising else np.fmin
        extreme = self._extreme_pa
        window = _FIRST_WINDOW
        position = start
        while position < pressures.size:
            segment = pressures[position:position + window]
            extremes = running.accumulate(np.concatenate(([extreme], segment)))
            # A sample is compared with the extreme reached before it, as in update().
            moved = (extremes[:-1] - segment) if rising else (segment - extremes[:-1])
            with np.errstate(invalid='ignore'):
                hits = np.flatnonzero((moved > 0) & (moved >= self.deadband_pa))
            if hits.size:
                return position + int(hits[0]), extreme
            extreme = float(extremes[-1])
            position += segment.size
            window *= 2
        return pressures.size, extreme


def detect_branches(p_pa, deadband_pa: float = DEFAULT_DEADBAND_PA,
                    initial_branch: int = BRANCH_INCREASING) -> np.ndarray:
    """Branch codes for a pressure array from a fresh detector (the offline refit's labeller)."""
    return BranchDetector(deadband_pa, initial_branch).detect(p_pa)
