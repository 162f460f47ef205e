"""The model on every simulated muscle family: scenarios, configurations and their scores.

Shared by tests/test_minor_loops.py, tests/test_drift_adaptation.py and
bench/bench_memory_families.py (which prints the table in docs/model.md). ROS-free.

A scenario is a family, a reversal-rich pressure path (`nested` or `random` ramps and holds,
or the smooth `sines` or `damped`, from pma_driver.sim.paths) and a seed; the muscle sees
the true pressure, the model the sensors' readings (noisy 10-bit pressure, HC-SR04 length),
sample by sample, online. Scores are the error against the true length from the third
reversal on, in % of the stroke of Table 1.
Every model starts from the shipped defaults: branches fitted to Table 1, no memory data.

Besides the simulator's families, one held out of everything the defaults were chosen on:
`bouc-wen`, the paper's nonlinear comparison model (pma_model.boucwen with a Hill backbone,
`refit`'s `bouc_wen_nonlinear`) fitted to Table 1 here. Its loop is up to 4 mm wide and it
has no return-point memory, like the `asymmetric` family, by another mechanism: its minor
loops ratchet. (With the sigmoid backbone the least-squares optimum has no loop at all, so
that fit would be a muscle without hysteresis.) It lives here, not in pma_driver.sim, so the
simulator does not depend on the model package.

More held-out muscles on demand: `duhem:RISING:FALLING` is a Duhem muscle like `asymmetric`
with other approach scales (kPa), fitted to Table 1 the same way; `gpi[:BULGE]` a generalized
Prandtl-Ishlinskii muscle (support.generalized_play), as asymmetric but with return-point
memory.

`return_point_oracle` is the yardstick for muscles without return-point memory: the muscle
itself, made to keep that property, which the model must.
"""

from __future__ import annotations

import argparse
import copy
import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from pma_driver.sim import families, fit_families, paths
from pma_model.boucwen import BoucWenModel, fit_bouc_wen
from pma_model.identification import OnlineModel, run_online
from pma_model.mix import MIX_MEMORY, RuleMix
from pma_model.params import ModelParams, default_params, paper_table1
from support import friction_muscle, generalized_play

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


MIX = MIX_MEMORY   # forecaster.RuleMix over 'identify' and 'play', each learning: the default
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


BOUC_WEN = 'bouc-wen'
SCORED_FAMILIES = (*families.FAMILY_NAMES, BOUC_WEN)   # bouc-wen has no drift option


@functools.lru_cache(maxsize=1)
def bouc_wen_fit() -> BoucWenModel:
    """Bouc-Wen with a Hill backbone, least squares on Table 1's loop (RMSE 0.14 cm)."""
    table = paper_table1()
    pressures = np.concatenate([table.pressure_pa, table.pressure_pa])
    lengths = np.concatenate([table.increasing_length_m, table.decreasing_length_m])
    rising = np.arange(pressures.size) < table.pressure_pa.size
    return fit_bouc_wen(pressures, lengths, rising, backbone='hill').model


class BoucWenMuscle:
    """A `families.Muscle` whose length is a Bouc-Wen model's (rate independent)."""

    def __init__(self, model: BoucWenModel):
        self.model = model
        self.reset()

    @property
    def rest_length_m(self) -> float:
        return float(self.model.length_m(0.0, 0.0))

    def reset(self) -> None:
        self._pressure_pa, self._state = 0.0, 0.0
        self.length_m = self.rest_length_m

    def update(self, pressure_pa: float, t_s: float = 0.0) -> float:
        pressure_pa = max(0.0, float(pressure_pa))
        self._state = self.model.advance_state(self._state, self._pressure_pa, pressure_pa)
        self._pressure_pa = pressure_pa
        self.length_m = float(self.model.length_m(pressure_pa, self._state))
        return self.length_m


DUHEM_VARIANT = 'duhem'   # 'duhem:30:60': a Duhem muscle with other approach scales


def duhem_variant_scales_pa(family: str) -> tuple[float, float] | None:
    """'duhem:30:60' -> (30e3, 60e3): the rising and falling approach scales [kPa in the
    name, Pa returned] of a held-out Duhem muscle; None for any other family name.

    The `asymmetric` family is the Duhem muscle with 15 and 100 kPa; any other pair, fitted
    to Table 1 the same way (fit_families.fit_asymmetric, about 30 s), is a muscle the
    defaults were not chosen on.
    """
    name, _, scales = family.partition(':')
    if name != DUHEM_VARIANT:
        return None
    try:
        rising_kpa, falling_kpa = (float(text) for text in scales.split(':'))
    except ValueError:
        raise ValueError(f'{family!r}: a Duhem variant is duhem:RISING:FALLING, its approach '
                         'scales in kPa (e.g. duhem:30:60)') from None
    if not (1.0 <= rising_kpa <= 1000.0 and 1.0 <= falling_kpa <= 1000.0):
        raise ValueError(f'{family!r}: approach scales must be within 1..1000 kPa')
    return 1e3 * rising_kpa, 1e3 * falling_kpa


@functools.lru_cache(maxsize=8)
def _duhem_variant_fit(rising_scale_pa: float, falling_scale_pa: float) -> families.DuhemParams:
    return fit_families.fit_asymmetric(rising_scale_pa=rising_scale_pa,
                                       falling_scale_pa=falling_scale_pa)


def held_out_fit_errors_m(family: str) -> np.ndarray | None:
    """A held-out Duhem variant's, generalized play or friction muscle's major loop minus
    Table 1 (22 values): how well it matches. None for the other families (their fits are
    documented in docs/simulated-rig.md and bouc_wen_fit)."""
    scales = duhem_variant_scales_pa(family)
    if scales is not None:
        return fit_families.duhem_loop_errors_m(_duhem_variant_fit(*scales))
    bulge = generalized_play_bulge(family)
    if bulge is not None:
        return generalized_play.loop_errors_m(generalized_play.fit(bulge))
    widest = friction_widest_band(family)
    if widest is not None:
        return friction_muscle.loop_errors_m(friction_muscle.fit(widest))
    return None


GENERALIZED_PLAY = 'gpi'   # 'gpi' or 'gpi:BULGE': support.generalized_play, held out


def _named_number(family: str, name: str, default: float, valid, usage: str) -> float | None:
    """'NAME' -> default, 'NAME:X' -> X when valid(X) (else ValueError with `usage`); None
    for a family of another name."""
    prefix, _, text = family.partition(':')
    if prefix != name:
        return None
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not valid(value):
        raise ValueError(f'{family!r}: {usage}')
    return value


def generalized_play_bulge(family: str) -> float | None:
    """'gpi' -> the default bulge, 'gpi:2' -> 2.0; None for any other family name."""
    return _named_number(family, GENERALIZED_PLAY, generalized_play.DEFAULT_BULGE,
                         lambda value: 0.0 <= value <= 10.0,
                         'a generalized play muscle is gpi or gpi:BULGE, BULGE within 0..10')


FRICTION = 'friction'   # 'friction' or 'friction:WIDEST': support.friction_muscle, held out


def friction_widest_band(family: str) -> float | None:
    """'friction' -> the default widest band, 'friction:0.4' -> 0.4; None for any other
    family name."""
    return _named_number(family, FRICTION, friction_muscle.DEFAULT_WIDEST_BAND,
                         lambda value: 0.0 < value < 1.0,
                         'a friction muscle is friction or friction:WIDEST, WIDEST within '
                         "0..1 (the widest fibre's band, a share of the pressure)")


CREEP_VARIANT = 'creep'   # 'creep:wide:0.3:1.5': a rate-independent family creeping, held out
_CREEPING_FAMILIES = ('narrow', 'wide', 'asymmetric')


def creep_variant(family: str) -> tuple[str, families.CreepParams] | None:
    """'creep:wide:0.3:1.5' -> ('wide', CreepParams(share=0.3, time_constant_s=1.5)): a
    held-out muscle, that family with a share of every length change arriving through a lag
    of that time constant; None for any other family name (`creep` itself is
    creep:narrow:0.25:0.6, the lag the defaults were measured on).

    The steady loop is the inner family's (Table 1); only the approach to it is slower.
    """
    name, _, spec = family.partition(':')
    if name != CREEP_VARIANT or family == CREEP_VARIANT:
        return None
    inner, _, numbers = spec.partition(':')
    try:
        share, time_constant_s = (float(text) for text in numbers.split(':'))
    except ValueError:
        share = time_constant_s = math.nan
    if inner not in _CREEPING_FAMILIES or not (0.0 < share < 1.0 and 0.05 <= time_constant_s
                                               <= 10.0):
        raise ValueError(f'{family!r}: a creep variant is creep:INNER:SHARE:TAU, INNER one of '
                         f'{", ".join(_CREEPING_FAMILIES)}, SHARE within 0..1, TAU within '
                         '0.05..10 s (e.g. creep:wide:0.3:1.5)')
    return inner, families.CreepParams(share=share, time_constant_s=time_constant_s)


def _held_out_muscle(family: str) -> families.Muscle | None:
    """A fresh held-out variant named by `family` (creep, generalized play, friction, Duhem);
    None for the simulator's families and Bouc-Wen."""
    creeping = creep_variant(family)
    if creeping is not None:
        inner, params = creeping
        return families.CreepMuscle(families.muscle_family(inner), params)
    bulge = generalized_play_bulge(family)
    if bulge is not None:
        return generalized_play.GeneralizedPlayMuscle(generalized_play.fit(bulge))
    widest = friction_widest_band(family)
    if widest is not None:
        return friction_muscle.FrictionMuscle(friction_muscle.fit(widest))
    scales = duhem_variant_scales_pa(family)
    if scales is not None:
        return families.DuhemMuscle(_duhem_variant_fit(*scales))
    return None


def muscle_for(family: str, drift: families.DriftSpec | None = None) -> families.Muscle:
    if family == BOUC_WEN:
        if drift is not None:
            raise ValueError('the held-out bouc-wen muscle has no drift option')
        return BoucWenMuscle(bouc_wen_fit())
    muscle = _held_out_muscle(family)
    if muscle is None:
        return families.muscle_family(family, drift)
    return muscle if drift is None else families.DriftingMuscle(muscle, drift)


def family_argument(text: str) -> str:
    """argparse type of the benches' --families: a scored family or a held-out one."""
    try:
        if text in SCORED_FAMILIES or duhem_variant_scales_pa(text) is not None or \
                generalized_play_bulge(text) is not None or creep_variant(text) is not None \
                or friction_widest_band(text) is not None:
            return text
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    raise argparse.ArgumentTypeError(f'{text!r}: choose from {", ".join(SCORED_FAMILIES)}, '
                                     'duhem:RISING:FALLING, gpi[:BULGE], '
                                     'friction[:WIDEST] or creep:INNER:SHARE:TAU')


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


def rate_dependent(family: str) -> bool:
    """Whether the family's length depends on time as well as on the pressure path."""
    return family == 'creep' or creep_variant(family) is not None


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
