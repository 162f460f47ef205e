"""The one registry of simulated muscle families: every name the simulated rig, the tests and
the benches accept, what each models and how it fits Table 1.

`fake_arduino --muscle NAME[+drift]` takes any of them and `fake_arduino --list-muscles`
prints this registry, one family a line (`describe`). A family is named by its name alone
(`wide`) or, when it takes parameters, `NAME:PARAMETERS` (`duhem:30:60`, `gpi:2`); every name
is parsed here (`parse_family`) and nowhere else. `+drift` appended gives it the default drift
(families.DriftSpec) where the family has a drift option.

Which families the model's defaults may be chosen on (the tuning set) and which are run only
to report (the validation set) is declared once, in pma_sim.splits (`TUNING`, `VALIDATION`:
families and seeds); `--list-muscles` labels each family with its set, and every registered
family must be in exactly one (checked at the end of this module). `FAMILY_NAMES`, the
simulator's own four (narrow, wide, asymmetric, creep), is the first of the tuning set.

To add a family: write its muscle, a class with the `families.Muscle` interface, in a
module of its own (as generalized_play.py does), and add one `_register(Family(...))` at the
end of this module, with a one-line summary and its fit to Table 1.
"""

from __future__ import annotations

import argparse
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pma_sim import families, family_fits, splits
from pma_sim.families import DriftingMuscle, DriftSpec, Muscle
from pma_sim.friction import DEFAULT_WIDEST_BAND
from pma_sim.generalized_play import DEFAULT_BULGE
from pma_sim.muscle import TABLE1_FIT, PreisachMuscle

DEFAULT_FAMILY = 'narrow'
DRIFT_SUFFIX = '+drift'


@dataclass(frozen=True)
class Family:
    """One muscle family: how to name it, what it models, how it fits Table 1, how to build it.

    `arguments(name)` turns a whole name (`gpi:2`) into `build`'s arguments, raising
    ValueError with the family's usage when they are wrong; None for a family that takes no
    parameters.
    """

    name: str
    summary: str                    # one line: what it models
    table1_fit: str                 # one line: its major loop against Table 1
    build: Callable[..., Muscle]    # build(*arguments) -> a fresh muscle, relaxed at 0 Pa
    usage: str = ''                 # its name with parameters ('gpi[:BULGE]'); '' takes none
    arguments: Callable[[str], tuple] | None = None
    drifts: bool = True             # accepts '+drift'
    rate_dependent: bool = False    # its length depends on time, not only on the pressure path
    # Its major loop minus Table 1 (22 values), from build's arguments; None: documented only.
    fit_errors_m: Callable[..., np.ndarray] | None = None

    @property
    def muscle_set(self) -> str:
        """'tuning' or 'validation': its set in pma_sim.splits."""
        return splits.set_of(self.name).name

    @property
    def syntax(self) -> str:
        return self.usage or self.name

    def line(self) -> str:
        """Its line of `--list-muscles`."""
        return f'{self.syntax:<25} [{self.muscle_set}] {self.summary}; Table 1: {self.table1_fit}'


FAMILIES: dict[str, Family] = {}


def _register(family: Family) -> None:
    assert family.name not in FAMILIES and ':' not in family.name and '+' not in family.name
    FAMILIES[family.name] = family


def describe() -> str:
    """Every family, one a line: what `fake_arduino --list-muscles` prints."""
    return '\n'.join(family.line() for family in FAMILIES.values())


def _choices() -> str:
    return ', '.join(family.syntax for family in FAMILIES.values())


def parse_family(name: str) -> tuple[Family, tuple]:
    """'gpi:2' -> (the gpi Family, (2.0,)): the family and its build arguments; ValueError
    for a name no family has or parameters it refuses."""
    prefix, colon, _ = name.partition(':')
    family = FAMILIES.get(prefix)
    if family is None:
        raise ValueError(f'unknown muscle family {name!r}; choose from {_choices()}')
    if family.arguments is None:
        if colon:
            raise ValueError(f'{name!r}: the {prefix} family takes no parameters')
        return family, ()
    return family, family.arguments(name)


def muscle_family(name: str = DEFAULT_FAMILY, drift: DriftSpec | None = None) -> Muscle:
    """A fresh muscle of the named family (relaxed, at 0 Pa), drifting if `drift` is given."""
    family, arguments = parse_family(name)
    if drift is not None and not family.drifts:
        raise ValueError(f'the {family.name} muscle has no drift option')
    muscle = family.build(*arguments)
    return muscle if drift is None else DriftingMuscle(muscle, drift)


def parse_muscle_spec(spec: str) -> tuple[str, DriftSpec | None]:
    """'wide' -> ('wide', None); 'wide+drift' -> ('wide', DriftSpec()). ValueError if unknown."""
    name = spec[:-len(DRIFT_SUFFIX)] if spec.endswith(DRIFT_SUFFIX) else spec
    family, _ = parse_family(name)
    drift = DriftSpec() if name != spec else None
    if drift is not None and not family.drifts:
        raise ValueError(f'the {family.name} muscle has no drift option '
                         f'({DRIFT_SUFFIX!r})')
    return name, drift


def muscle_from_spec(spec: str) -> Muscle:
    """The muscle a `parse_muscle_spec` string names: the fake_arduino --muscle syntax."""
    return muscle_family(*parse_muscle_spec(spec))


def family_argument(text: str) -> str:
    """argparse type of the benches' --families: any registered family, without drift."""
    try:
        parse_family(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def rate_dependent(name: str) -> bool:
    """Whether the family's length depends on time as well as on the pressure path."""
    return parse_family(name)[0].rate_dependent


def table1_fit_errors_m(name: str) -> np.ndarray | None:
    """A parameterised family's major loop minus Table 1 (22 values), fitted for its parameters;
    None for a family whose fit is documented only (the simulator's own in family_fits.py,
    Bouc-Wen in bouc_wen.py, creep variants, which settle on their inner family's loop)."""
    family, arguments = parse_family(name)
    return None if family.fit_errors_m is None else family.fit_errors_m(*arguments)


# --- the parameters of the parameterised families, parsed here only --------------------------

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


DUHEM_VARIANT = 'duhem'   # 'duhem:30:60': a Duhem muscle with other approach scales


def duhem_variant_scales_pa(family: str) -> tuple[float, float] | None:
    """'duhem:30:60' -> (30e3, 60e3): the rising and falling approach scales [kPa in the
    name, Pa returned] of a Duhem muscle of other scales; None for any other family name.

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


GENERALIZED_PLAY = 'gpi'   # 'gpi' or 'gpi:BULGE': pma_sim.generalized_play


def generalized_play_bulge(family: str) -> float | None:
    """'gpi' -> the default bulge, 'gpi:2' -> 2.0; None for any other family name."""
    return _named_number(family, GENERALIZED_PLAY, DEFAULT_BULGE,
                         lambda value: 0.0 <= value <= 10.0,
                         'a generalized play muscle is gpi or gpi:BULGE, BULGE within 0..10')


FRICTION = 'friction'   # 'friction' or 'friction:WIDEST': pma_sim.friction


def friction_widest_band(family: str) -> float | None:
    """'friction' -> the default widest band, 'friction:0.4' -> 0.4; None for any other
    family name."""
    return _named_number(family, FRICTION, DEFAULT_WIDEST_BAND,
                         lambda value: 0.0 < value < 1.0,
                         'a friction muscle is friction or friction:WIDEST, WIDEST within '
                         "0..1 (the widest fibre's band, a share of the pressure)")


CREEP_VARIANT = 'creep'   # 'creep:wide:0.3:1.5': a rate-independent family creeping
_CREEPING_FAMILIES = ('narrow', 'wide', 'asymmetric')


def creep_variant(family: str) -> tuple[str, families.CreepParams] | None:
    """'creep:wide:0.3:1.5' -> ('wide', CreepParams(share=0.3, time_constant_s=1.5)): a
    muscle, that family with a share of every length change arriving through a lag
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


# --- builders (the other modules are imported when first built: scipy, pma_model) ----------

def _creep(inner: str = 'narrow', params: families.CreepParams | None = None) -> Muscle:
    params = families.CreepParams(**family_fits.CREEP) if params is None else params
    return families.CreepMuscle(muscle_family(inner), params)


@functools.lru_cache(maxsize=8)
def _duhem_fit(rising_scale_pa: float, falling_scale_pa: float) -> families.DuhemParams:
    from pma_sim import fit_families

    return fit_families.fit_asymmetric(rising_scale_pa=rising_scale_pa,
                                       falling_scale_pa=falling_scale_pa)


def _duhem_errors_m(rising_scale_pa: float, falling_scale_pa: float) -> np.ndarray:
    from pma_sim import fit_families

    return fit_families.duhem_loop_errors_m(_duhem_fit(rising_scale_pa, falling_scale_pa))


def _generalized_play(bulge: float) -> Muscle:
    from pma_sim import generalized_play

    return generalized_play.GeneralizedPlayMuscle(generalized_play.fit(bulge))


def _generalized_play_errors_m(bulge: float) -> np.ndarray:
    from pma_sim import generalized_play

    return generalized_play.loop_errors_m(generalized_play.fit(bulge))


def _friction(widest_band: float) -> Muscle:
    from pma_sim import friction

    return friction.FrictionMuscle(friction.fit(widest_band))


def _friction_errors_m(widest_band: float) -> np.ndarray:
    from pma_sim import friction

    return friction.loop_errors_m(friction.fit(widest_band))


def _ratchet() -> Muscle:
    from pma_sim import ratchet

    return ratchet.RatchetMuscle(ratchet.fit())


def _ratchet_errors_m() -> np.ndarray:
    from pma_sim import ratchet

    return ratchet.loop_errors_m(ratchet.fit())


def _rate_width() -> Muscle:
    from pma_sim import rate_width

    return rate_width.RateWidthMuscle(rate_width.fit())


def _rate_width_errors_m() -> np.ndarray:
    from pma_sim import rate_width

    return rate_width.loop_errors_m(rate_width.fit())


def _bouc_wen() -> Muscle:
    from pma_sim.bouc_wen import BoucWenMuscle, bouc_wen_fit

    return BoucWenMuscle(bouc_wen_fit())


# --- the registry: the simulator's own families first, in this order -----------------------

_register(Family(
    'narrow', 'Preisach muscle (narrow relays): after a reversal the length holds for tens of '
    'kPa, then rejoins the other branch; return-point memory (muscle.py)',
    'RMSE 0.067 cm, max 0.176 cm (22 points)',
    lambda: PreisachMuscle(TABLE1_FIT)))
_register(Family(
    'wide', 'Prandtl-Ishlinskii, play operators on a warped pressure: after a reversal the '
    'length moves at once; return-point memory (families.PlayMuscle)',
    'RMSE 0.097 cm, max 0.259 cm (22 points)',
    lambda: families.PlayMuscle(families.wide_params())))
_register(Family(
    'asymmetric', 'Duhem: the length approaches the other envelope exponentially, fast when '
    'inflating, slow when deflating; loops close only approximately (families.DuhemMuscle)',
    'RMSE 0.092 cm, max 0.162 cm (22 points)',
    lambda: families.DuhemMuscle(families.asymmetric_params())))
_register(Family(
    'creep', 'the narrow muscle with a viscoelastic element in series (lag 0.6 s, share 0.25); '
    'creep:INNER:SHARE:TAU is another family creeping with another lag',
    "narrow's at the end of each hold (the inner family's for a variant)",
    _creep, usage='creep[:INNER:SHARE:TAU]',
    arguments=lambda name: creep_variant(name) or (), rate_dependent=True))
_register(Family(
    'bouc-wen', "the paper's nonlinear comparison model (pma_model.boucwen, Hill backbone): "
    'minor loops ratchet, no return-point memory, no drift option (bouc_wen.py)',
    'least squares on its loop, RMSE 0.14 cm, loop 4 mm wide',
    _bouc_wen, drifts=False))
_register(Family(
    'duhem', 'the asymmetric Duhem muscle with other approach scales RISING, FALLING [kPa], '
    'refitted when built (about 30 s)',
    'refitted like asymmetric; duhem:30:60 RMSE 0.105 cm, max 0.255 cm (22 points)',
    lambda rising, falling: families.DuhemMuscle(_duhem_fit(rising, falling)),
    usage='duhem:RISING:FALLING', arguments=duhem_variant_scales_pa,
    fit_errors_m=_duhem_errors_m))
_register(Family(
    'gpi', 'generalized Prandtl-Ishlinskii: rising and falling envelopes differ by BULGE '
    '(default 1), asymmetric like the Duhem muscle but with return-point memory '
    '(generalized_play.py)',
    'plays refitted (about 3 s); gpi RMSE 0.100 cm, max 0.203 cm (22 points)',
    _generalized_play, usage='gpi[:BULGE]',
    arguments=lambda name: (generalized_play_bulge(name),),
    fit_errors_m=_generalized_play_errors_m))
_register(Family(
    'friction', 'braid friction growing with the pressure, fibre bands up to WIDEST (default '
    '0.9) of it: at rest to about 70 kPa, then a sharp onset; return-point memory '
    '(friction.py)',
    'plays refitted (about 3 s); friction RMSE 0.095 cm, max 0.254 cm (22 points)',
    _friction, usage='friction[:WIDEST]',
    arguments=lambda name: (friction_widest_band(name),),
    fit_errors_m=_friction_errors_m))

# --- the validation set (pma_sim.splits): run only to report, never tuned on ---------------

_register(Family(
    'ratchet', 'loops that do not close: a play muscle (wide-like) that every fall of the '
    'pressure leaves a little longer, the set saturating at 2 mm (ratchet.py)',
    'plays refitted (about 3 s); first cycle RMSE 0.097 cm, max 0.262 cm (22 points)',
    _ratchet, fit_errors_m=_ratchet_errors_m))
_register(Family(
    'rate-width', 'plays whose bands widen with the filtered |dP/dt| (1.44x at 250 kPa/s), '
    'narrowing back on holds (rate_width.py)',
    'plays refitted (about 3 s); ends of 10 s holds RMSE 0.097 cm, max 0.259 cm (22 points)',
    _rate_width, rate_dependent=True, fit_errors_m=_rate_width_errors_m))

FAMILY_NAMES = splits.SIMULATOR_FAMILIES   # the simulator's own, first of the tuning set
assert tuple(FAMILIES)[:len(FAMILY_NAMES)] == FAMILY_NAMES
for _family in FAMILIES.values():
    splits.set_of(_family.name)   # in exactly one declared set, or the import fails
