"""The memory rules: one class per rule, each registered by name (MEMORY_RULES).

A rule is what HysteresisModel asks when the pressure moves: how its state (pressure,
length, direction, the turning-point stack) follows a sample or an array of them, which
curves a path from the current state follows (the inverse), what the length's gradient is
(the online learning), and how a state taken over from another model is fitted to it.
memory.py's docstring has the rules themselves. The rules keep no state of their own: the
model holds it, so a copy of the model is a copy of everything.

Adding a rule is one class implementing MemoryRule and one `register_memory_rule` line (with
its label for legends). The rules mixed by their recent error (the `mix` memory) are mix.py's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from pma_model.branches import Branch
from pma_model.curves import MID_DEPTH, CurveEnds, ScanningCurve, play_share_at
from pma_model.detector import BRANCH_INCREASING
from pma_model.kernel import PATH_BAND, PATH_STACK

if TYPE_CHECKING:
    from pma_model.memory import HysteresisModel

# (branch, rising, p_pa) -> d (that major branch's length at p_pa) / d the learned parameters,
# a vector whose last two entries are the rising and falling play shares (zero here: a branch
# does not depend on them). HysteresisModel.length_gradient carries it through the memory.
BranchSensitivity = Callable[[Branch, bool, float], np.ndarray]
# (curve, from_pa, to_pa): a piece of the path pressure would follow from the current state.
Segment = tuple[ScanningCurve, float, float]

# Monotone runs shorter than this are stepped sample by sample (noisy data reverses
# nearly every sample; one numpy evaluation per run would cost more than stepping).
_SHORT_RUN = 32


class MemoryRule(Protocol):
    """How one rule moves a HysteresisModel's state and what it answers from it."""

    # True: the AUTO inverse follows the path from the current state; False: that
    # direction's major branch (the paper's switch).
    follows_path: bool
    # True: its curves mix the play-like and Madelung shapes by a learned share.
    has_play_share: bool
    # How the path pressure would follow goes on from a state (HysteresisModel.path_segments,
    # built by kernel.path_segments): along the turning-point stack's curves (PATH_STACK) or
    # the friction band's hold, then the major branch (PATH_BAND).
    path_kind: int
    # True: a state taken over is rebuilt by replaying the other's turning points before
    # `resume`; False: `resume` needs only the other's pressure and length.
    replays_stack: bool

    def update(self, model: HysteresisModel, p_pa: float, branch: int) -> None:
        """Advance the state by one finite pressure (`branch`: the detector's, already
        updated)."""

    def advance(self, model: HysteresisModel, values: np.ndarray,
                branches: np.ndarray) -> np.ndarray:
        """Advance over finite pressures (`branches`: the detector's for them); the lengths."""

    def curve(self, model: HysteresisModel, rising: bool, major: Branch,
              origin: tuple[float, float], target: tuple[float, float]) -> ScanningCurve:
        """The scanning curve from a reversal `origin` toward `target`."""

    def resume(self, model: HysteresisModel, other: HysteresisModel) -> None:
        """Fit the state replayed from `other`'s turning points to this rule."""

    def origin_depth(self, model: HysteresisModel) -> float:
        """Where the curve in force starts across the loop (MID_DEPTH without one)."""

    def expert_lengths(self, model: HysteresisModel) -> tuple[float, float]:
        """(play-like, Madelung) lengths here; both the length for a rule without the pair."""

    def length_gradient(self, model: HysteresisModel,
                        sensitivity: BranchSensitivity) -> np.ndarray:
        """d length / d parameters at the current state."""



@dataclass(frozen=True)
class MemoryRuleEntry:
    """A registered rule: its class and its plain name in legends."""

    cls: type
    label: str


# The one registry of memory rules, by the `memory` setting's name, in menu order ('mix',
# the rules mixed, is mix.py's and comes first in params.MEMORIES).
MEMORY_RULES: dict[str, MemoryRuleEntry] = {}


def register_memory_rule(name: str, cls: type, label: str) -> None:
    MEMORY_RULES[name] = MemoryRuleEntry(cls, label)


def memory_rule(name: str) -> MemoryRule:
    """A rule by name (ValueError naming the known ones)."""
    if name not in MEMORY_RULES:
        raise ValueError(f'memory must be one of {tuple(MEMORY_RULES)}, got {name!r}')
    return MEMORY_RULES[name].cls()


def monotone_runs(model: HysteresisModel, values: np.ndarray):
    """(start, end, rising) of each run of one direction; holds keep the direction."""
    previous = np.concatenate(([model._p], values[:-1]))
    steps = np.sign(values - previous)
    last_move = np.maximum.accumulate(np.where(steps != 0, np.arange(values.size), -1))
    direction = np.where(last_move >= 0, steps[np.maximum(last_move, 0)],
                         1.0 if model._rising else -1.0)
    run_starts = np.concatenate(([0], np.flatnonzero(direction[1:] != direction[:-1]) + 1))
    run_ends = np.concatenate((run_starts[1:], [values.size]))
    return [(int(start), int(end), bool(direction[start] > 0))
            for start, end in zip(run_starts, run_ends, strict=True)]


class MadelungRule:
    """A stack of turning points with wiping-out; curves are the major branch rescaled."""

    follows_path = True
    has_play_share = False
    path_kind = PATH_STACK
    replays_stack = True

    def update(self, model, p_pa, branch):
        model._step_madelung(p_pa)

    def curve(self, model, rising, major, origin, target):
        return ScanningCurve(major, origin, target)

    def share_index(self, rising: bool) -> int | None:
        """Which entry of a gradient is this direction's play share (None: no share)."""
        return None

    def resume(self, model, other):
        pass   # the replayed stack is the state

    def origin_depth(self, model):
        return model._current_curve().origin_depth

    def expert_lengths(self, model):
        return model._current_curve().shapes_at(model._p)


    def advance(self, model, values, branches):
        """Madelung over finite pressures, one numpy evaluation per curve segment."""
        out = np.empty(values.size)
        for start, end, rising in monotone_runs(model, values):
            if end - start < _SHORT_RUN:  # numpy's per-call cost dominates: step instead
                for index in range(start, end):
                    model._step_madelung(float(values[index]))
                    out[index] = model._l
                continue
            if rising != model._rising:
                model._push((model._p, model._l))
                model._rising = rising
            position = start
            while position < end:
                stop = end
                if len(model._stack) >= 2:
                    target_pa = model._stack[-2][0]
                    run = values[position:end]
                    reached = (run >= target_pa) if rising else (run <= target_pa)
                    if reached.any():
                        stop = position + int(np.argmax(reached))
                if stop > position:
                    out[position:stop] = model._curve(rising, model._stack).length(
                        values[position:stop])
                if stop < end:
                    del model._stack[-2:]
                position = stop
            model._p, model._l = float(values[end - 1]), float(out[end - 1])
        return out

    def length_gradient(self, model, sensitivity):
        """Exact: carried through every remembered turning point, since a scanning curve's
        length is pinned to its turning points, whose lengths came from earlier curves,
        often on the other branch. Cost: the current curve's, plus the stack's once it
        changes."""
        gradients = self._turning_point_gradients(model, sensitivity)
        curve = model._current_curve()
        cached_curve, ends = model._gradient_ends
        if curve is not cached_curve:
            ends = _ends(curve, model._rising, gradients, sensitivity)
            model._gradient_ends = (curve, ends)
        return curve.gradient(model._p, sensitivity(curve.major, model._rising, model._p),
                              ends, self.share_index(model._rising))

    def _turning_point_gradients(self, model, sensitivity) -> list[np.ndarray]:
        """The gradient of each remembered turning point's length, oldest first (kept while
        the stack below the top is the same)."""
        stack = model._stack
        known, gradients = model._gradient_cache
        if known == stack:
            return gradients
        kept = 0
        while kept < min(len(known), len(stack)) and known[kept] == stack[kept]:
            kept += 1
        gradients = gradients[:kept]
        for depth in range(kept, len(stack)):
            # Turning points alternate: the top was reached moving against the current way.
            arriving = model._rising if (len(stack) - 1 - depth) % 2 else not model._rising
            curve = model._curve(arriving, stack[:depth])
            p_pa = stack[depth][0]
            gradients.append(curve.gradient(
                p_pa, sensitivity(curve.major, arriving, p_pa),
                _ends(curve, arriving, gradients, sensitivity),
                self.share_index(arriving)))
        model._gradient_cache = (list(stack), gradients)
        return gradients


def _ends(curve: ScanningCurve, rising: bool, gradients: list[np.ndarray],
          sensitivity: BranchSensitivity) -> CurveEnds | None:
    """The gradients at the curve's O and T; `gradients`: its turning points', oldest
    first (O is the last; T the one before, or the anchor on the major branch)."""
    if curve.origin is None:
        return None
    at_origin = sensitivity(curve.major, rising, curve.origin[0])
    at_target = sensitivity(curve.major, rising, curve.target[0])
    target = gradients[-2] if len(gradients) >= 2 else at_target
    return CurveEnds(gradients[-1], target, at_origin, at_target)


class IdentifyRule(MadelungRule):
    """The Madelung stack, each curve a learned share of play-like and Madelung shapes."""

    has_play_share = True

    def curve(self, model, rising, major, origin, target):
        depth = model.origin_depth(rising, origin)
        index = 0 if rising else 1
        share = play_share_at(model.play_shares[index], model.share_slopes[index], depth)
        return ScanningCurve(major, origin, target, share, depth)

    def share_index(self, rising):
        return -2 if rising else -1


class SwitchRule:
    """The paper's: the major branch of the detected direction."""

    follows_path = False
    has_play_share = False
    path_kind = PATH_STACK
    replays_stack = True   # its path walks the stack a resume_from replayed

    def update(self, model, p_pa, branch):
        model._p, model._l = p_pa, float(model.major(branch == BRANCH_INCREASING).length(p_pa))

    def advance(self, model, values, branches):
        rising = branches == BRANCH_INCREASING
        lengths = np.where(rising, model.increasing.length(values),
                           model.decreasing.length(values))
        model._p, model._l = float(values[-1]), float(lengths[-1])
        return lengths

    def curve(self, model, rising, major, origin, target):
        return ScanningCurve(major, origin, target)

    def resume(self, model, other):
        model._l = float(model.major(other.branch == BRANCH_INCREASING).length(model._p))

    def origin_depth(self, model):
        return MID_DEPTH

    def expert_lengths(self, model):
        return model._l, model._l

    def length_gradient(self, model, sensitivity):
        """The detector's branch at the current pressure."""
        rising = model._detector.branch == BRANCH_INCREASING
        return sensitivity(model.major(rising), rising, model._p)



class PlayRule:
    """Friction band: the length moves only when a major branch pushes it."""

    follows_path = True
    has_play_share = False
    path_kind = PATH_BAND
    replays_stack = False   # its state is the held length, which resume fits to the band

    def update(self, model, p_pa, branch):
        if p_pa > model._p:
            bound = float(model.increasing.length(p_pa))
            if bound <= model._l:
                model._l, model._play_source = bound, (True, p_pa)
            model._rising = True
        elif p_pa < model._p:
            bound = float(model.decreasing.length(p_pa))
            if bound >= model._l:
                model._l, model._play_source = bound, (False, p_pa)
            model._rising = False
        model._p = p_pa

    def advance(self, model, values, branches):
        """Within a monotone run the bound moves one way only."""
        out = np.empty(values.size)
        for start, end, rising in monotone_runs(model, values):
            run = values[start:end]
            bound = np.asarray(model.major(rising).length(run), dtype=float)
            out[start:end] = (np.minimum(model._l, bound) if rising
                              else np.maximum(model._l, bound))
            if out[end - 1] == bound[-1]:   # on the branch at the end of the run (it stays)
                model._play_source = (rising, float(run[-1]))
            model._rising = rising
            model._p, model._l = float(run[-1]), float(out[end - 1])
        return out

    def curve(self, model, rising, major, origin, target):
        return ScanningCurve(major, origin, target)

    def resume(self, model, other):
        # The play state is the length itself: kept, inside the new band at this pressure.
        model._stack = []
        model._rising = other._rising
        low = float(model.decreasing.length(model._p))
        high = float(model.increasing.length(model._p))
        model._l = min(max(other.length_m, low), high)
        # Moved onto a branch by the new band: that branch is what it depends on now.
        model._play_source = (other._play_source if low < other.length_m < high
                              else (other.length_m >= high, model._p))

    def origin_depth(self, model):
        return MID_DEPTH

    def expert_lengths(self, model):
        return model._l, model._l

    def length_gradient(self, model, sensitivity):
        """The branch and pressure its held length was set at."""
        rising, p_pa = model._play_source
        return sensitivity(model.major(rising), rising, p_pa)



register_memory_rule('identify', IdentifyRule, 'learned scanning curves')
register_memory_rule('madelung', MadelungRule, 'Madelung turning points')
register_memory_rule('switch', SwitchRule, "branch switch (the paper's)")
register_memory_rule('play', PlayRule, 'friction band (play)')
