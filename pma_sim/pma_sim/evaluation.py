"""The model on every simulated muscle family: scenarios, configurations and their scores.

Shared by tests/test_minor_loops.py, tests/test_drift_adaptation.py and
bench/bench_memory_families.py (which prints the acceptance table of docs/model.md §3.1 and
the tables of docs/model-history.md, "The family bench in detail"). ROS-free.

A scenario is a family (any of pma_sim.registry), a reversal-rich pressure path (`nested` or
`random` ramps and holds, or the smooth `sines` or `damped`, from pma_sim.paths) and a seed;
the muscle sees the true pressure, the model the sensors' readings (noisy 10-bit pressure,
HC-SR04 length), sample by sample, online. Scores are the error against the true length
from the third reversal on, in % of the stroke of Table 1.
Every model starts from the shipped defaults: branches fitted to Table 1, no memory data.

It lives in pma_sim, not in pma_model, because it needs the simulated muscles and paths, and
pma_model must not depend on the simulator (pma_sim depends on pma_model, not the reverse).

`return_point_oracle` is the yardstick for muscles without return-point memory: the muscle
itself, made to keep that property, which the model must.
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, replace

import numpy as np

from pma_model.identification import OnlineModel, run_online
from pma_model.mix import MIX_MEMORY, RuleMix
from pma_model.params import ModelParams, default_params, paper_table1
from pma_sim import families, paths, splits
from pma_sim.registry import muscle_family, rate_dependent

STROKE_M = paper_table1().stroke_m   # Table 1: 30.06 - 24.20 cm
SCORED_FROM_REVERSAL = 3     # "after the first three reversals"
# Samples per second of the scenarios: the firmware's maximum; driver_node asks for 20 Hz by
# default.
DEFAULT_RATE_HZ = 50.0
PATH_KINDS = ('nested', 'random')   # ramps and holds: the tables' paths
ALL_PATH_KINDS = (*PATH_KINDS, *paths.SMOOTH_KINDS)   # and smooth ones (paths.smooth_path)
FORMS = ('sigmoid', 'hill')


@dataclass(frozen=True)
class Config:
    """A model configuration: memory rule, online identification, drift adaptation."""

    memory: str
    learn: bool
    adapt: bool = False
    local_offset: bool = True     # the mix's (pma_model.local_offset); False: without it

    @property
    def label(self) -> str:
        if self.memory == MIX:
            return 'mix (identify + play)' + ('' if self.local_offset else ', no local offset')
        name = {'switch': 'switch (paper)'}.get(self.memory, self.memory) \
            if not self.learn else f'{self.memory} + learned'
        if self.memory == 'identify':
            name = 'identify' if self.learn else 'identify (shares 0.5, not learned)'
        return name

    def params(self, form: str) -> ModelParams:
        base = default_params()
        return replace(base, branch_form=form, memory=self.memory,
                       identification=replace(base.identification, enabled=self.learn),
                       adaptation=replace(base.adaptation, enabled=self.adapt))

    def build(self, form: str) -> OnlineModel | RuleMix:
        """The online model this configuration runs (a RuleMix for MIX)."""
        model = self.params(form).build_online()
        return model if self.local_offset else model.without_local_offset()


MIX = MIX_MEMORY   # mix.RuleMix over 'identify' and 'play', each learning: the default
PAPER = Config('switch', learn=False)
STATIC_RULES = (Config('madelung', False), Config('play', False))
LEARNED_RULES = (Config('switch', True), Config('madelung', True), Config('play', True))
IDENTIFY = Config('identify', True)
MIXED = Config(MIX, True)
MIXED_WITHOUT_LOCAL_OFFSET = Config(MIX, True, local_offset=False)
ALL_CONFIGS = (PAPER, *STATIC_RULES, *LEARNED_RULES, IDENTIFY, MIXED)


@dataclass(frozen=True)
class Scenario:
    family: str
    kind: str = 'random'
    seed: int = 1
    duration_s: float = 180.0
    drift_start_s: float | None = None   # None: no drift
    rate_hz: float = DEFAULT_RATE_HZ
    # A diagnosis, not a rig: the models read the true pressure instead of the sensor's
    # (what a noise-free pressure reading would leave of their errors).
    noise_free_pressure: bool = False

    @property
    def label(self) -> str:
        drift = f', drift from {self.drift_start_s:.0f} s' if self.drift_start_s is not None \
            else ''
        rate = '' if self.rate_hz == DEFAULT_RATE_HZ else f', {self.rate_hz:g} Hz'
        noise_free = ', noise-free pressure' if self.noise_free_pressure else ''
        return f'{self.family}/{self.kind}/seed {self.seed}{drift}{rate}{noise_free}'

    @property
    def drift(self) -> families.DriftSpec | None:
        """The default drift (DriftSpec), from drift_start_s on."""
        return None if self.drift_start_s is None else families.DriftSpec(
            start_s=self.drift_start_s)


# The acceptance table's default families (pma_sim.splits, tuning set): the simulator's four
# and Bouc-Wen; the rest of either declared set on demand.
BOUC_WEN = splits.BOUC_WEN
SCORED_FAMILIES = splits.ACCEPTANCE_FAMILIES


def muscle_for(family: str, drift: families.DriftSpec | None = None) -> families.Muscle:
    """A fresh muscle of any registered family (pma_sim.registry), drifting if asked."""
    return muscle_family(family, drift)


@functools.lru_cache(maxsize=64)
def simulate(scenario: Scenario) -> paths.Run:
    if scenario.kind in paths.SMOOTH_KINDS:
        path = paths.smooth_path(scenario.kind, scenario.duration_s, seed=scenario.seed,
                                 rate_hz=scenario.rate_hz)
    else:
        turns = (paths.nested_turns if scenario.kind == 'nested' else paths.random_turns)(
            scenario.duration_s, seed=scenario.seed)
        path = paths.ramp_path(turns, rate_hz=scenario.rate_hz, seed=scenario.seed)
    return paths.simulate(muscle_for(scenario.family, scenario.drift), path,
                          seed=scenario.seed)


@functools.lru_cache(maxsize=64)
def return_point_oracle(scenario: Scenario) -> np.ndarray:
    """The scenario's muscle made to keep return-point memory: its length along the true path
    when every closed loop restores the muscle's own state at the loop's start.

    What a model with return-point memory that knew this muscle exactly would predict: the
    muscle between reversals, a Madelung stack of its states at the turning points, and
    wiping-out when the pressure passes the turning point before the last. On a muscle that
    has return-point memory it is the muscle itself; on one that has not (`asymmetric`,
    `bouc-wen`) its error is what keeping the property costs, with perfect knowledge. It
    needs a rate-independent muscle without drift (a creeping or drifting one's state
    depends on time too).
    """
    if rate_dependent(scenario.family) or scenario.drift is not None:
        raise ValueError(f'{scenario.label}: the oracle needs a rate-independent muscle '
                         'without drift')
    muscle = muscle_for(scenario.family)
    turning_points = [(0.0, copy.deepcopy(muscle))]   # (pressure, the muscle's state there)
    rising, previous = True, 0.0
    pressures = np.maximum(simulate(scenario).pressure_pa, 0.0)
    lengths = np.empty(pressures.size)
    for i, pressure in enumerate(pressures.tolist()):
        if pressure != previous:
            if (pressure > previous) != rising:   # a reversal at `previous`
                turning_points.append((previous, copy.deepcopy(muscle)))
                rising = not rising
            closed = False
            while len(turning_points) >= 3 and (
                    pressure > turning_points[-2][0] if rising
                    else pressure < turning_points[-2][0]):
                del turning_points[-2:]   # the loop closed: back on the curve before it
                closed = True
            if closed:
                muscle = copy.deepcopy(turning_points[-1][1])
            muscle.update(pressure)
        lengths[i] = muscle.length_m
        previous = pressure
    return lengths


@functools.lru_cache(maxsize=1024)
def predict(scenario: Scenario, config: Config, form: str = 'sigmoid') -> np.ndarray:
    """What the model would publish for every sample of the scenario (online)."""
    run = simulate(scenario)
    pressure_pa = run.pressure_pa if scenario.noise_free_pressure else run.measured_pressure_pa
    return run_online(config.build(form), pressure_pa, run.measured_length_m,
                      run.time_s)


@dataclass(frozen=True)
class Score:
    rmse_m: float
    max_m: float

    @property
    def rmse_pct(self) -> float:
        return 100.0 * self.rmse_m / STROKE_M

    @property
    def max_pct(self) -> float:
        return 100.0 * self.max_m / STROKE_M


def score(scenario: Scenario, config: Config, form: str = 'sigmoid',
          window_s: tuple[float, float] | None = None) -> Score:
    """Error against the true length: from the third reversal on, or within `window_s`."""
    run = simulate(scenario)
    return _score(predict(scenario, config, form) - run.length_m, run, window_s)


def oracle_score(scenario: Scenario) -> Score:
    """`return_point_oracle`'s error against the true length, from the third reversal on."""
    run = simulate(scenario)
    return _score(return_point_oracle(scenario) - run.length_m, run, None)


def _scored(run: paths.Run) -> np.ndarray:
    """The samples the criteria count: from the third reversal on."""
    return run.time_s >= run.reversal_times_s[SCORED_FROM_REVERSAL - 1]


def _score(error: np.ndarray, run: paths.Run, window_s: tuple[float, float] | None) -> Score:
    if window_s is None:
        keep = _scored(run)
    else:
        keep = (run.time_s >= window_s[0]) & (run.time_s < window_s[1])
    error = error[keep]
    return Score(float(np.sqrt(np.mean(error ** 2))), float(np.max(np.abs(error))))


def worst_moment_s(scenario: Scenario, config: Config, form: str = 'sigmoid') -> float:
    """When, from the third reversal on, the model errs most (its `score`'s max_m)."""
    run = simulate(scenario)
    error = np.abs(predict(scenario, config, form) - run.length_m)
    return float(run.time_s[np.argmax(np.where(_scored(run), error, -1.0))])


def oracle_error_near_m(scenario: Scenario, time_s: float) -> float:
    """`return_point_oracle`'s largest error within a sample of `time_s`.

    Whether a model's largest error is the price of return-point memory: when the muscle
    itself, made to keep that property, errs as much at that moment, no model with it can
    do better there. A sample either side, because the oracle closes its loops on the true
    pressure and the model on the measured one.
    """
    run = simulate(scenario)
    near = np.abs(run.time_s - time_s) <= 1.5 / scenario.rate_hz
    return float(np.max(np.abs(return_point_oracle(scenario) - run.length_m)[near]))


def perfectly_corrected(scenario: Scenario, config: Config, form: str = 'sigmoid',
                        window_s: tuple[float, float] | None = None) -> Score:
    """What a perfect drift correction would leave on a drifting scenario: the drift-free
    run's predictions through the muscle's true drift, against the drifting truth.

    The noise floor for a drifting muscle: its stroke has grown (x1.08 by default), so the
    same shape error is that much larger in metres (1.08x the drift-free error).
    """
    clean, drift = replace(scenario, drift_start_s=None), scenario.drift
    rest = muscle_for(scenario.family).rest_length_m
    run = simulate(clean)
    corrected = np.array([drift.drifted(length, rest, t) for length, t in
                          zip(predict(clean, config, form), run.time_s, strict=True)])
    return _score(corrected - simulate(scenario).length_m, run, window_s)


def largest_step_m(scenario: Scenario, config: Config, form: str = 'sigmoid') -> float:
    """Largest change of the prediction between two samples (a jump shows here)."""
    return float(np.max(np.abs(np.diff(predict(scenario, config, form)))))
