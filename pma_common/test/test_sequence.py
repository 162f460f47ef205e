"""SequenceTracker counts what never arrived, whatever else the stream does."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pma_common.sequence import U32, SequenceTracker

pytestmark = pytest.mark.in_process


def feed(numbers, **kwargs) -> SequenceTracker:
    tracker = SequenceTracker(**kwargs)
    for number in numbers:
        tracker.add(number)
    return tracker


def test_consecutive_numbers_lose_nothing():
    stats = feed(range(1000)).stats()
    assert (stats.received, stats.lost, stats.gaps, stats.duplicates) == (1000, 0, 0, 0)


def test_a_skip_confirmed_by_the_next_number_is_lost():
    stats = feed([10, 15, 16, 17]).stats()
    assert (stats.lost, stats.gaps) == (4, 1)


def test_a_stray_number_ahead_loses_nothing():
    """The fuzzed case: one valid frame numbered 65546 between 10 and 11."""
    stats = feed([10, 65546, *range(11, 200)]).stats()
    assert stats.lost == 0 and stats.gaps == 0 and stats.stray == 1


def test_a_stray_number_within_the_window_loses_nothing():
    stats = feed([10, 500, *range(11, 600)]).stats()
    assert stats.lost == 0
    assert stats.duplicates == 1        # the stray 500, then the real one


def test_late_numbers_take_their_loss_back():
    tracker = feed([1, 2, 5, 6])
    assert tracker.stats().lost == 2
    tracker.add(3)
    tracker.add(4)
    stats = tracker.stats()
    assert (stats.lost, stats.gaps, stats.late) == (0, 0, 2)


def test_repeats_are_duplicates_not_gaps():
    stats = feed([1, 2, 2, 3, 3, 3, 4, 2, 5]).stats()
    assert (stats.lost, stats.gaps, stats.duplicates) == (0, 0, 4)


def test_a_counter_that_restarts_is_a_restart_not_a_loss():
    stats = feed([*range(0, 1000), *range(0, 500)]).stats()
    assert (stats.lost, stats.restarts) == (0, 1)
    stats = feed([*range(0, 10_000), *range(0, 500)]).stats()     # further than the window
    assert (stats.lost, stats.restarts) == (0, 1)


def test_wrapping_the_counter_is_not_a_jump():
    stats = feed([U32 - 3, U32 - 2, U32 - 1, 0, 1, 3, 4]).stats()
    assert (stats.lost, stats.gaps, stats.restarts) == (1, 1, 0)


def test_a_real_jump_beyond_the_window_is_lost():
    stats = feed([1, 2, 10_002, 10_003], window=100).stats()
    assert (stats.lost, stats.gaps) == (9_999, 1)


def test_gaps_older_than_the_window_are_final():
    tracker = feed([1, 5, 6, *range(7, 200)], window=50)
    tracker.add(2)                     # far too late: a duplicate of nothing, not a fill
    assert tracker.stats().lost == 3


def test_reset_keeps_the_counts():
    tracker = feed([1, 2, 5, 6])
    tracker.reset()
    for number in range(0, 10):
        tracker.add(number)
    stats = tracker.stats()
    assert (stats.lost, stats.gaps, stats.restarts) == (2, 1, 0)


def test_window_is_checked():
    with pytest.raises(ValueError, match='window'):
        SequenceTracker(window=0)


@settings(max_examples=300, deadline=None)
@given(length=st.integers(50, 3000), seed=st.integers(0, 2 ** 32 - 1),
       drop=st.floats(0.0, 0.3), duplicate=st.floats(0.0, 0.05), stray=st.floats(0.0, 0.01),
       reorder=st.integers(0, 8), start=st.integers(0, U32 - 1))
def test_lost_is_exactly_what_never_arrived(length, seed, drop, duplicate, stray,  # noqa: PLR0917
                                            reorder, start):
    """Drops, repeats, local reordering and stray far numbers: only drops count as lost."""
    rng = random.Random(seed)
    numbers = [(start + k) % U32 for k in range(length)]
    kept = [n for i, n in enumerate(numbers)
            if i in (0, length - 1) or i > length - 3 or rng.random() >= drop]
    dropped = length - len(kept)
    # Local reordering: swap neighbours at most `reorder` apart (never the first or last two).
    for i in range(1, len(kept) - 3):
        if reorder and rng.random() < 0.05:
            j = min(len(kept) - 3, i + rng.randint(1, reorder))
            kept[i], kept[j] = kept[j], kept[i]
    stream: list[int] = []
    for number in kept[:-2]:
        stream.append(number)
        if rng.random() < duplicate:
            stream.append(number)
        if rng.random() < stray:
            stream.append((number + rng.randint(10_000, U32 // 2)) % U32)
    stream += kept[-2:]
    stats = feed(stream).stats()
    assert stats.lost == dropped
