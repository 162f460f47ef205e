"""The `mix` memory: a rule built from rules, whole online models weighted by their recent error.

'identify' learns a continuous share between Madelung's rescaled branch and a curve that
holds, then runs parallel to the branch into the previous reversal T (it must end at T:
return-point memory). The 'play' rule (hold, then rejoin the major branch itself) is not in
that family, and on nested paths of Preisach-type muscles (narrow relays, creep) it is the
better rule (docs/model.md §3).
No single rule wins on every family, so RuleMix runs the candidates side by side, each a whole
OnlineModel learning its own branch correction from the same samples, and predicts their
mixture with exponential weights

    w_i ~ exp(-loss_i / MIX_TEMPERATURE_M2S),  loss_i = sum of e_i^2 dt, forgotten over
    MIX_TIME_CONSTANT_S,

e_i a rule's out-of-sample error against the measured length (each bounded by the outlier
limit, so one bad echo cannot decide). Discounted, this is the exponentially weighted average
forecaster, whose loss stays near the better rule's (Cesa-Bianchi and Lugosi, Prediction,
Learning, and Games, ch. 2-3). The time constant and temperature were chosen on the families
(docs/model-history.md, "The constants' figures": a faster forgetting let the play rule's
large errors on the asymmetric muscle into the mix).

The inverse (`pressure_for_length`) has no closed form: the mixture of monotone lengths along
the path is monotone, so it is bracketed and solved (scipy's brentq) on the lengths each rule
gives along the path pressure would follow from the current state, or on one direction's
major branches. Either is one compiled call (kernel.mixed_path_pressure,
kernel.mixed_major_pressure; brentq's steps as scipy takes them), as in Python the lengths'
evaluations were most of its cost.

The step, its rules' steps included, is one compiled call as well (kernel.mix_step on the
rules' packed state) when every rule has a compiled step; `reference_step` is the same in
Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from scipy.optimize import brentq

from pma_model import kernel
from pma_model.adaptation import Drift
from pma_model.curves import FLAT_SPAN_M, MID_DEPTH
from pma_model.detector import BRANCH_AUTO, BRANCH_DECREASING, BRANCH_INCREASING, BRANCH_NAMES
from pma_model.identification import (
    MAX_STEP_S,
    IdentificationSettings,
    OnlineModel,
    OnlineRule,
    Prediction,
    elapsed_s,
)
from pma_model.local_offset import FADE_PA, PLAY_PA, WALK_M2_PER_PA, LocalOffset
from pma_model.memory import NARROW_LOOP_M, InverseResult, expert_row

MIX_MEMORY = 'mix'            # the model's memory setting that runs MIX_RULES mixed
MIX_RULES = ('identify', 'play')
MIX_TIME_CONSTANT_S = 100.0   # how long a rule's errors count (5000 samples at 50 Hz)
MIX_TEMPERATURE_M2S = 2e-6    # a loss difference this large changes the weights by e
PRESSURE_TOLERANCE_PA = 1e-3
# Rules whose weight is below this move the mixed length by less than 1e-10 m (they differ by
# centimetres at most), less than the pressure tolerance does on the steepest branch.
NEGLIGIBLE_WEIGHT = 1e-9
# A target this close [m] to a reachable end counts as reached (rounding, not a gap).
REACH_ROUNDING_M = 1e-12
# scipy's brentq defaults, which the compiled root find (kernel.brentq) is given too.
BRENTQ_RTOL = 4.0 * np.finfo(float).eps
BRENTQ_MAXITER = 100
# The numbers the compiled inverse takes from the modules that own them (kernel.py says why),
# in the order of its scalars from S_HALF_PLAY on.
_KERNEL_CONSTANTS = (0.5 * PLAY_PA, FADE_PA, MID_DEPTH, NARROW_LOOP_M, FLAT_SPAN_M,
                     PRESSURE_TOLERANCE_PA, BRENTQ_RTOL, REACH_ROUNDING_M, BRENTQ_MAXITER)

def _first_rule(name: str) -> property:
    """A RuleMix attribute that is its first rule's (OnlineModel's of that name)."""
    return property(lambda mix: getattr(mix.experts[0], name),
                    doc=f"The first rule's `{name}`.")


@dataclass
class RuleMix:
    """Online models of several memory rules, mixed by their recent error; `step`,
    `pressure_for_length` and what model_node and the controller read (`learned`, `drift`,
    the branches) as OnlineModel's: the first rule's, or mixed."""

    experts: tuple[OnlineModel, ...]
    time_constant_s: float = MIX_TIME_CONSTANT_S
    temperature_m2s: float = MIX_TEMPERATURE_M2S
    losses_m2s: np.ndarray | None = None
    learning: bool = True       # False: the weights stay as given (identification off)
    # The local offset (local_offset.py) learns from the measured lengths; a caller with its
    # own measured-minus-model feedback (the length controller) turns it off.
    local_offset: bool = True
    memory: ClassVar[str] = MIX_MEMORY
    label: ClassVar[str] = 'learned mix of scanning curves and friction band'   # legends

    def __post_init__(self):
        if len(self.experts) < 1:
            raise ValueError('a mix needs at least one rule')
        pressures = {e.max_gauge_pressure_pa for e in self.experts}
        if len(pressures) != 1:
            raise ValueError(f'the rules disagree on the maximum pressure: {sorted(pressures)}')
        if not (math.isfinite(self.time_constant_s) and self.time_constant_s > 0.0):
            raise ValueError(f'time_constant_s must be > 0, got {self.time_constant_s!r}')
        if not (math.isfinite(self.temperature_m2s) and self.temperature_m2s > 0.0):
            raise ValueError(f'temperature_m2s must be > 0, got {self.temperature_m2s!r}')
        self.losses_m2s = (np.zeros(len(self.experts)) if self.losses_m2s is None
                           else np.array(self.losses_m2s, dtype=float))
        if self.losses_m2s.shape != (len(self.experts),) or \
                not np.all(np.isfinite(self.losses_m2s)):
            raise ValueError(f'losses_m2s must be {len(self.experts)} finite numbers, '
                             f'got {self.losses_m2s!r}')
        # Each rule's prediction at the last step (None: the compiled step's, in _outputs).
        self._last_predictions: list[Prediction] | None = []
        self._outputs = np.zeros((len(self.experts), kernel.P_GAIN + 1))
        # kernel.mix_step's constants (X_ layout), the losses array it was last given and the
        # rules' packed arrays (_kernel_arrays).
        self._mix_constants = np.array((
            self.temperature_m2s, self.time_constant_s,
            min(e.adaptation.outlier_m for e in self.experts), 0.5 * PLAY_PA, FADE_PA,
            WALK_M2_PER_PA, MAX_STEP_S))
        self._kernel_losses: np.ndarray | None = None
        self._kernel_cache: tuple | None = None
        first = self.experts[0]
        self.local = LocalOffset(first.identification.length_noise_m,
                                 first.adaptation.outlier_m)
        self._branch_table: tuple[tuple, np.ndarray | None] = ((), None)   # _path_arrays'

    def without_local_offset(self) -> RuleMix:
        """This mix with its local offset off and forgotten (for a caller that feeds the
        measured length back itself); returns self."""
        self.local_offset = False
        self.local = LocalOffset(self.local.noise_m, self.local.outlier_m)
        return self

    @classmethod
    def of_rules(cls, build, rules=MIX_RULES, **settings) -> RuleMix:
        """A mix of `build(memory)` for each rule (e.g. ModelParams with that memory)."""
        return cls(tuple(build(rule) for rule in rules), **settings)

    @property
    def weights(self) -> np.ndarray:
        excess = self.losses_m2s - self.losses_m2s.min()
        weights = np.exp(-excess / self.temperature_m2s)
        return weights / weights.sum()

    @property
    def rules(self) -> tuple[str, ...]:
        return tuple(expert.memory for expert in self.experts)

    # What stands for the mix where one value is needed: its first rule's.
    max_gauge_pressure_pa = _first_rule('max_gauge_pressure_pa')
    branch = _first_rule('branch')
    increasing = _first_rule('increasing')
    decreasing = _first_rule('decreasing')
    samples_learned = _first_rule('samples_learned')
    samples_rejected = _first_rule('samples_rejected')

    def weights_by_rule(self) -> dict[str, float]:
        """{rule: weight}, as published and reported."""
        return {rule: float(weight)
                for rule, weight in zip(self.rules, self.weights, strict=True)}

    @property
    def drift(self) -> Drift:
        """The rules' drift estimates, mixed (the prediction's offset and gain)."""
        drifts = [expert.drift for expert in self.experts]
        weights = self.weights
        return Drift(drifts[0].reference_length_m,
                     float(weights @ [d.shift_m for d in drifts]),
                     float(weights @ [d.gain for d in drifts]))

    @property
    def virgin_term_m(self) -> float:
        """The rules' first-loading terms, mixed."""
        return float(self.weights @ [expert.virgin_term_m for expert in self.experts])

    first_loading_ended = _first_rule('first_loading_ended')   # the rules share the travel

    def learned(self) -> IdentificationSettings:
        """Every rule's learned numbers and the play rule's weight, as the 'mix' memory
        saves them (IdentificationSettings.for_rule gives each rule its part back)."""
        if self.rules != MIX_RULES:
            raise ValueError(f'only the {MIX_RULES} mix is saved, not {self.rules}')
        identify, play = self.experts
        identify_loss, play_loss = self.losses_m2s
        return replace(identify.learned().with_play_rule_learned(play.learned()),
                       play_rule_excess_loss_m2s=float(play_loss - identify_loss))

    def _weights_floats(self) -> list[float]:
        """`weights` as plain floats (the step's: numpy's per-call cost on two values was
        most of the mixing)."""
        losses = self.losses_m2s.tolist()
        least = min(losses)
        weights = [math.exp(-(loss - least) / self.temperature_m2s) for loss in losses]
        total = sum(weights)
        return [weight / total for weight in weights]

    @property
    def last_predictions(self) -> list[Prediction]:
        """Each rule's prediction at the last step."""
        if self._last_predictions is None:   # the compiled step's, built when asked for
            self._last_predictions = [
                Prediction(length, int(branch), static, offset, gain)
                for length, branch, static, offset, gain in self._outputs.tolist()]
        return self._last_predictions

    def step(self, pressure_pa: float, measured_length_m: float = math.nan,
             t_s: float | None = None) -> Prediction:
        """Every rule predicts and learns; the weights learn from the predictions.

        One compiled call (kernel.mix_step) when every rule's step is compiled;
        `reference_step` is the same in Python.
        """
        pressure_pa = float(pressure_pa)
        arrays = self._kernel_arrays()
        if arrays is None or not math.isfinite(pressure_pa):
            return self._python_step(pressure_pa, measured_length_m, t_s, reference=False)
        local, losses = self.local, self.losses_m2s
        if losses is not self._kernel_losses:   # set anew: as the kernel takes it, in place
            self.losses_m2s = losses = np.ascontiguousarray(losses, dtype=float)
            self._kernel_losses = losses
        (length, branch, static, offset, gain, local_m, ended, local.offset_m, local.variance_m2,
         local._play_pa) = kernel.mix_step(
            pressure_pa, float(measured_length_m), 0.0 if t_s is None else float(t_s),
            t_s is not None, self.learning, self.local_offset, local.offset_m, local.variance_m2,
            local.play_pa, local.noise_m ** 2, local.outlier_m, self._mix_constants, losses,
            self._outputs, *arrays)
        self._last_predictions = None
        for packed in self._kernel_cache[0]:   # their states moved
            packed.path = None
        if ended:   # a rule's virgin term ended: out of its filter
            for i, expert in enumerate(self.experts):
                if ended >> i & 1:
                    expert._end_kernel_virgin_term(expert._kernel)
            self._kernel_cache = None
        return Prediction(length, int(branch), static, offset, gain, local_m)

    def reference_step(self, pressure_pa: float, measured_length_m: float = math.nan,
                       t_s: float | None = None) -> Prediction:
        """`step` in Python, every rule's too: the reference the compiled one is checked
        against."""
        return self._python_step(pressure_pa, measured_length_m, t_s, reference=True)

    def _kernel_arrays(self) -> tuple | None:
        """The rules' packed arrays as kernel.mix_step takes them (a tuple each of their
        numbers, constants, filter means and covariances, branch rows, stacks, gradients), or
        None unless every rule's step is compiled. Kept while the rules keep the same packed
        state."""
        cached = self._kernel_cache
        fresh = cached is None
        for i, expert in enumerate(self.experts):
            if not expert.compiled:
                return None
            packed = expert._kernel or expert._pack()
            if not expert._python_stale:
                expert._drop_python_state()
            if not fresh:
                arrays = cached[1]
                fresh = (packed is not cached[0][i] or packed.config is not arrays[1][i]
                         or packed.filter.mean is not arrays[2][i]
                         or packed.filter.covariance is not arrays[3][i])
        if not fresh:
            return cached[1]
        packs = tuple(expert._kernel for expert in self.experts)
        arrays = (tuple(p.numbers for p in packs), tuple(p.config for p in packs),
                  tuple(p.filter.mean for p in packs), tuple(p.filter.covariance for p in packs),
                  tuple(p.rows for p in packs), tuple(p.stack for p in packs),
                  tuple(p.gradients for p in packs))
        self._kernel_cache = (packs, arrays)
        return arrays

    def _python_step(self, pressure_pa: float, measured_length_m: float, t_s: float | None, *,
                     reference: bool) -> Prediction:
        """The step in Python, its rules' `reference_step` (reference) or `step`."""
        weights = self._weights_floats()
        previous_s = self.experts[0].clock_s   # the rules' clock, before they advance it
        predictions = [(e.reference_step if reference else e.step)(
            pressure_pa, measured_length_m, t_s) for e in self.experts]
        lengths = [p.length_m for p in predictions]
        first = predictions[0]
        self._last_predictions = predictions
        if not math.isfinite(float(pressure_pa)):
            return first
        dt = elapsed_s(previous_s, t_s)
        measured = float(measured_length_m)
        if self.learning and math.isfinite(measured) and dt > 0.0:
            # Outliers are capped at the limit the rules reject them at.
            cap = min(e.adaptation.outlier_m for e in self.experts)
            errors = [abs(length - measured) for length in lengths]
            if any(error <= cap for error in errors):   # one every rule rejects: says nothing
                forget = math.exp(-dt / self.time_constant_s)
                self.losses_m2s = np.array([
                    loss * forget + min(error, cap) ** 2 * dt
                    for loss, error in zip(self.losses_m2s.tolist(), errors, strict=True)])
        local = self.local.advance(float(pressure_pa))

        def mixed_of(values) -> float:
            return sum(w * v for w, v in zip(weights, values, strict=True))

        mixed = mixed_of(lengths)
        if self.learning and self.local_offset and math.isfinite(measured):
            self.local.learn(measured, mixed)
        # Built directly: dataclasses.replace costs as much as the mixing.
        return Prediction(
            length_m=mixed + local, branch=first.branch,
            static_length_m=mixed_of([p.static_length_m for p in predictions]),
            offset_m=mixed_of([p.offset_m for p in predictions]),
            gain=mixed_of([p.gain for p in predictions]), local_offset_m=local)

    # --- inverse --------------------------------------------------------------------

    @property
    def settled_length_m(self) -> float:
        """The mixture's length here once creep has settled (where every path starts), with
        the local offset."""
        return float(self.weights @ [float(e.drift.correct(e.path_state().length_m))
                                     for e in self.experts]) + self.local.offset_m

    def settled_aim_m(self, length_m: float, max_creep_share: float) -> float:
        """The rules' aims (OnlineModel.settled_aim_m), mixed: exact where they learned the
        same creep, close where they did not (their creep and lengths differ by millimetres).
        The local offset is in both lengths, so it is taken out and put back."""
        local = self.local.offset_m
        return float(self.weights @ [e.settled_aim_m(length_m - local, max_creep_share)
                                     for e in self.experts]) + local

    def pressure_for_length(self, length_m: float, branch: int = BRANCH_AUTO) -> InverseResult:
        """The pressure at which the mixture settles at length_m (see OnlineModel's).

        AUTO: along the path pressure would follow from the current state, in the
        direction the target needs (shorter than now: rising), the local offset fading along
        it as pressure travels (one compiled call, kernel.mixed_path_pressure);
        INCREASING / DECREASING: on that direction's major branches, mixed (no local offset:
        it belongs to the current state; kernel.mixed_major_pressure).
        """
        if branch not in (BRANCH_AUTO, BRANCH_INCREASING, BRANCH_DECREASING) or \
                not math.isfinite(float(length_m)):
            return self.experts[0].pressure_for_length(length_m, branch)   # its refusal
        length_m = float(length_m)
        weights = self.weights
        path = branch == BRANCH_AUTO
        carried = path and self.local.offset_m != 0.0    # the major branches have none
        if np.count_nonzero(weights > NEGLIGIBLE_WEIGHT) == 1 and not carried:
            # One rule carries the mix (the others move it by < 1e-10 m): its exact inverse.
            return self.experts[int(np.argmax(weights))].pressure_for_length(length_m, branch)
        experts, stacks, branches, scalars = self._path_arrays(weights)
        if path:
            status, pressure, low, high, rising = kernel.mixed_path_pressure(
                length_m, experts, stacks, branches, scalars)
        else:
            rising = branch == BRANCH_INCREASING
            status, pressure, low, high = kernel.mixed_major_pressure(
                length_m, rising, experts, branches, scalars)
        if status < 0:   # as scipy's brentq would have raised
            raise RuntimeError(f'the mixed root find did not converge for {length_m!r} m')
        return self._result(length_m, bool(rising), path, reached=status > 0,
                            pressure=pressure, low=low, high=high)

    def searched_pressure_for_length(self, length_m: float, rising: bool,
                                     path: bool = True) -> InverseResult:
        """The inverse found in Python (scipy's brentq on the rules' `settled_map`s): on the
        major branches of one direction, or along the path (`path`): what the compiled inverses
        are checked against."""
        weights = self.weights
        local = self.local.at if path and self.local.offset_m != 0.0 else (lambda _p_pa: 0.0)
        if path:
            rising = length_m < self.settled_length_m
        here = self.experts[0].pressure_pa
        start = here if path else (0.0 if rising else self.max_gauge_pressure_pa)
        end = self.max_gauge_pressure_pa if rising else 0.0
        maps = [(w, e.settled_map(rising, path))
                for w, e in zip(weights, self.experts, strict=True) if w > 0.0]

        def mixed(p_pa: float) -> float:
            return sum(w * length_at(p_pa) for w, length_at in maps) + local(p_pa)

        at_start, at_end = mixed(start), mixed(end)
        low, high = min(at_start, at_end), max(at_start, at_end)
        if not low - REACH_ROUNDING_M <= length_m <= high + REACH_ROUNDING_M:
            return self._result(length_m, rising, path, reached=False, pressure=math.nan,
                                low=low, high=high)
        if abs(at_start - length_m) <= REACH_ROUNDING_M:
            pressure = start
        elif abs(at_end - length_m) <= REACH_ROUNDING_M:
            pressure = end
        else:
            pressure = brentq(lambda p: mixed(p) - length_m, min(start, end), max(start, end),
                              xtol=PRESSURE_TOLERANCE_PA, rtol=BRENTQ_RTOL,
                              maxiter=BRENTQ_MAXITER)
        return self._result(length_m, rising, path, reached=True, pressure=float(pressure),
                            low=low, high=high)

    def _result(self, length_m: float, rising: bool, path: bool, *, reached: bool,
                pressure: float, low: float, high: float) -> InverseResult:
        name = BRANCH_NAMES[BRANCH_INCREASING if rising else BRANCH_DECREASING]
        where = (f'{name} path from the current state '
                 f'({self.experts[0].pressure_pa:.6g} Pa)' if path
                 else f'{name} major branch')
        if not reached:
            return InverseResult(
                False, f'length {length_m:.6g} m is not reachable on the mixed {where}: '
                f'reachable [{low:.6g}, {high:.6g}] m with 0..'
                f'{self.max_gauge_pressure_pa:.6g} Pa', math.nan, 0, low, high)
        code = BRANCH_INCREASING if rising else BRANCH_DECREASING
        return InverseResult(True, f'on the mixed {where}', pressure, code, low, high)

    def _path_arrays(self, weights: np.ndarray):
        """(experts, stacks, branches, scalars): the state kernel.mixed_path_pressure reads
        (its E_ and S_ layouts; kernel.mixed_major_pressure reads all but the stacks); the
        branch table is kept while the rules' branches are the same objects (a commit makes
        new ones). Built as lists and converted once: numpy's per-item cost was most of the
        call."""
        rows, stacks, branches, settled = [], [], [], []
        for i, (weight, expert) in enumerate(zip(weights.tolist(), self.experts, strict=True)):
            state = expert.path_state()
            drift = expert.drift
            settled.append(float(drift.correct(state.length_m)))
            rows.append(expert_row(state, weight, (drift.reference_length_m, drift.shift_m,
                                                   drift.gain), 2 * i, len(stacks)))
            stacks += state.turning_points
            branches += (state.increasing, state.decreasing)
        kept, table = self._branch_table
        if len(kept) != len(branches) or \
                any(a is not b for a, b in zip(kept, branches, strict=True)):
            table = kernel.branch_table([b.kernel_row for b in branches])
            self._branch_table = (branches, table)
        offset = self.local.offset_m
        scalars = np.array((rows[0][kernel.E_PRESSURE], self.max_gauge_pressure_pa,
                            float(weights @ settled) + offset, offset, self.local.play_pa,
                            *_KERNEL_CONSTANTS))
        return (np.array(rows, dtype=float), np.array(stacks, dtype=float).reshape(-1, 2),
                table, scalars)

    @property
    def local_offset_m(self) -> float:
        return self.local.offset_m

    def resume_from(self, other: OnlineRule) -> None:
        """Continue `other`'s pressure history with these rules' settings (and its weights,
        when it is a mix of the same rules)."""
        if isinstance(other, RuleMix) and other.rules == self.rules:
            for mine, theirs in zip(self.experts, other.experts, strict=True):
                mine.resume_from(theirs)
            self.losses_m2s = other.losses_m2s.copy()
            if self.local_offset and other.local_offset:
                self.local = replace(other.local, noise_m=self.local.noise_m,
                                     outlier_m=self.local.outlier_m)
        else:
            source = other.experts[0]
            for mine in self.experts:
                mine.resume_from(source)

