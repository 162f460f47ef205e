"""Which sequence numbers of a stream never arrived, told apart from late, repeated and stray ones.

The driver counts the device's samples by their `seq`, the recorder and `info` count
`pma/state` by the same number. Counting "how far did the number jump" turns one repeated,
late or corrupt-but-valid number into thousands of lost samples (a frame numbered 65546
between 10 and 11 once made 65,535 of them). Here a number is lost only when the stream
moves on without it:

* a step ahead is believed only when the next number continues from it: 10, 15, 16 loses
  11-14; 10, 500, 11 loses nothing (500 was early or stray, and is kept in case the stream
  gets there);
* a number within `window` behind the newest fills a gap (late) or is a duplicate;
* a step of more than `window` either way is a jump if the next number continues from it
  (forward: the skipped numbers are lost; backward: the counter restarted), else a stray;
* two consecutive numbers more than `reorder` behind the newest are a restart too (a counter
  that started again without anybody saying so).
"""

from __future__ import annotations

from dataclasses import dataclass

U32 = 2 ** 32


@dataclass(frozen=True)
class SequenceStats:
    received: int      # numbers seen, of every kind
    lost: int          # skipped by the stream (a late arrival within the window takes one back)
    gaps: int          # runs of lost numbers
    late: int          # arrived behind the newest, filling a gap
    duplicates: int    # seen before
    stray: int         # far from the stream and not followed by it
    restarts: int      # the counter started again


class SequenceTracker:
    """Feed every received number to `add`; `stats()` says what is missing."""

    def __init__(self, modulus: int = U32, window: int = 4096, reorder: int = 64):
        if not 1 <= window < modulus // 4:
            raise ValueError(f'window must be in [1, {modulus // 4}), got {window}')
        if reorder < 0:
            raise ValueError(f'reorder must be >= 0, got {reorder}')
        self.modulus = modulus
        self.window = window
        self.reorder = min(reorder, window)
        self._received = self._late = self._duplicates = 0
        self._stray = self._restarts = 0
        self._lost_final = self._gaps_final = 0
        self._missing: set[int] = set()
        self._gaps: list[list[int]] = []    # open gaps, oldest first: [first, last, missing]
        self.reset()

    def reset(self) -> None:
        """Forget the stream's position (the sender restarted and said so); counts stay."""
        self._retire_gaps(everything=True)
        self._newest: int | None = None
        self._previous: int | None = None
        self._previous_was_far_behind = False
        self._ahead: set[int] = set()        # received ahead of the newest, not yet confirmed
        self._far: int | None = None         # a far number waiting for its successor

    # -- feeding -----------------------------------------------------------------------

    def add(self, seq: int) -> None:
        self._received += 1
        seq %= self.modulus
        far_behind = False
        if self._newest is None:
            self._newest = seq
        elif self._far is not None and seq == self._next(self._far):
            self._jump(self._far, seq)
        else:
            if self._far is not None:
                self._stray += 1
            self._far = None
            step = self._step(seq)
            if step == 1:
                self._advance_to(seq)
            elif 1 < step <= self.window:
                self._ahead_of_stream(seq)
            elif -self.window <= step <= 0:
                far_behind = step < -self.reorder
                self._behind_stream(seq)
            else:
                self._far = seq
        self._previous = seq
        self._previous_was_far_behind = far_behind

    def _next(self, seq: int) -> int:
        return (seq + 1) % self.modulus

    def _step(self, seq: int) -> int:
        """Signed distance from the newest number, in (-modulus/2, modulus/2]."""
        step = (seq - self._newest) % self.modulus
        return step - self.modulus if step > self.modulus // 2 else step

    def _ahead_of_stream(self, seq: int) -> None:
        previous = self._previous
        if previous is not None and previous in self._ahead and seq == self._next(previous):
            self._advance_to(seq)        # the stream did skip: what is not ahead is lost
        elif seq in self._ahead:
            self._duplicates += 1
        else:
            self._ahead.add(seq)

    def _behind_stream(self, seq: int) -> None:
        if seq in self._missing:
            self._missing.discard(seq)
            self._late += 1
            self._fill(seq)
        elif self._previous_was_far_behind and seq == self._next(self._previous):
            self._duplicates -= 1        # the previous one was the restart, not a repeat
            self._restarted(seq)
        else:
            self._duplicates += 1

    # -- moving the stream -------------------------------------------------------------

    def _advance_to(self, seq: int) -> None:
        """Move the newest number to `seq`; numbers skipped and not seen ahead are missing."""
        step = self._step(seq)
        run: list[int] | None = None
        for k in range(1, step):
            number = (self._newest + k) % self.modulus
            if number in self._ahead:
                self._ahead.discard(number)
                run = None
                continue
            self._missing.add(number)
            if run is None:
                run = [number, number, 0]
                self._gaps.append(run)
            run[1] = number
            run[2] += 1
        self._ahead.discard(seq)
        self._newest = seq
        while self._next(self._newest) in self._ahead:      # early arrivals now in line
            self._newest = self._next(self._newest)
            self._ahead.discard(self._newest)
        self._retire_gaps()
        if len(self._ahead) > self.window:                   # strays that never came due
            self._ahead = {n for n in self._ahead if 0 < self._step(n) <= self.window}

    def _jump(self, far: int, seq: int) -> None:
        step = self._step(far)
        if step > 0:             # the stream really skipped ahead: all of it is lost
            self._retire_gaps(everything=True)
            self._lost_final += step - 1
            self._gaps_final += 1
            self._newest = seq
            self._ahead.clear()
        else:
            self._restarted(seq)
        self._far = None

    def _restarted(self, seq: int) -> None:
        self._restarts += 1
        self._retire_gaps(everything=True)
        self._newest = seq
        self._ahead.clear()

    def _fill(self, seq: int) -> None:
        for gap in self._gaps:
            if (seq - gap[0]) % self.modulus <= (gap[1] - gap[0]) % self.modulus:
                gap[2] -= 1
                if gap[2] == 0:
                    self._gaps.remove(gap)
                return

    def _retire_gaps(self, everything: bool = False) -> None:
        """Gaps wholly older than the window can no longer be filled: their loss is final."""
        while self._gaps:
            first, last, missing = self._gaps[0]
            if not everything and self._step(last) >= -self.window:
                return
            self._gaps.pop(0)
            for k in range((last - first) % self.modulus + 1):
                self._missing.discard((first + k) % self.modulus)
            if missing:
                self._lost_final += missing
                self._gaps_final += 1

    def stats(self) -> SequenceStats:
        return SequenceStats(
            received=self._received,
            lost=self._lost_final + sum(gap[2] for gap in self._gaps),
            gaps=self._gaps_final + len(self._gaps), late=self._late,
            duplicates=self._duplicates, stray=self._stray, restarts=self._restarts)
