"""Quantities the way people type and read them: `200kPa`, `2bar`, `26.5cm`, `5s`; plain = SI.

Every ROS interface of the project is SI with the unit in the name (gauge_pressure_pa,
length_m); only what a person types or reads goes through here. kPa and cm take their factors
from pma_model.units, the project's one home of the paper's units.
"""

from __future__ import annotations

import math
import re
import unicodedata

from pma_model.units import M_PER_CM, PA_PER_KPA

# Lower-case unit -> SI factor. Case is ignored: "mpa" is MPa (nobody means millipascal), and
# "mbar" is the millibar.
PRESSURE_UNITS = {'pa': 1.0, 'kpa': PA_PER_KPA, 'mpa': 1000.0 * PA_PER_KPA,
                  'bar': 100.0 * PA_PER_KPA, 'mbar': 0.1 * PA_PER_KPA,
                  'psi': 6894.757293168361}          # lbf/in^2, exact by definition
LENGTH_UNITS = {'m': 1.0, 'cm': M_PER_CM, 'mm': 0.1 * M_PER_CM}
TIME_UNITS = {'s': 1.0, 'ms': 1e-3, 'min': 60.0, 'h': 3600.0}
FREQUENCY_UNITS = {'hz': 1.0}
KINDS = {'pressure': (PRESSURE_UNITS, 'Pa', '200kPa, 2bar, 29psi'),
         'length': (LENGTH_UNITS, 'm', '26.5cm, 265mm, 0.265m'),
         'time': (TIME_UNITS, 's', '5s, 500ms, 2min'),
         'frequency': (FREQUENCY_UNITS, 'Hz', '0.5Hz, 0.1hz')}

# ASCII only (re.ASCII): a str pattern's \d and \s take every script's digits and spaces.
_QUANTITY = re.compile(r'^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zA-Z]*)\s*$',
                       re.ASCII)


class QuantityError(ValueError):
    """Text that is not a quantity of the kind asked for; the message says what would be."""


def ascii_only(text: str) -> None:
    """Refuse text with any character outside ASCII, naming the first one.

    Python's float() and int(), and a regex's \\d, take the decimal digits of every script:
    `٣٠٠` (Arabic-Indic) would be 300 Pa and `２００kPa` (full-width) 200 kPa. A quantity is
    typed in ASCII, so what is sent is what a reader of the command line sees.
    """
    for char in text:
        if char.isascii():
            continue
        name = unicodedata.name(char, f'U+{ord(char):04X}')
        if char.isdigit() or char.isnumeric():
            raise QuantityError(f'{text!r}: {char!r} ({name}) is not an ASCII digit: use '
                                'ASCII digits 0-9')
        raise QuantityError(f'{text!r}: {char!r} ({name}) is not ASCII: type quantities in '
                            'ASCII (digits 0-9, units such as kPa, cm, s)')


def parse(text: str, kind: str, *, minimum: float | None = None, strict: bool = False) -> float:
    """SI value of `text`: a number with a unit of `kind`, or a plain number in SI.

    `minimum` (exclusive when `strict`) bounds what `pma` uses itself: a timeout of -1 s is a
    typo, not a choice. What goes to a node is left to the node, which says why it refuses.
    """
    ascii_only(text)
    units, si_unit, examples = KINDS[kind]
    match = _QUANTITY.match(text)
    if match is None:
        raise QuantityError(f'{text!r} is not a {kind}: give a number with a unit ({examples}) '
                            f'or a plain number in {si_unit}')
    number, unit = float(match.group(1)), match.group(2).lower()
    if unit and unit not in units:
        known = ', '.join(sorted({_spelling(u) for u in units}))
        # `pma set 2cm`, `pma move 2bar`: say what the unit is for, and what this takes.
        other = next((k for k, (other_units, _, _) in KINDS.items() if unit in other_units), '')
        but = f' but of {other}' if other else ''
        raise QuantityError(f'{text!r}: {match.group(2)!r} is not a unit of {kind}{but} '
                            f'(units of {kind}: {known}; a plain number is {si_unit})')
    value = number * units[unit] if unit else number
    if not math.isfinite(value):
        raise QuantityError(f'{text!r} is not a finite {kind}')
    # Finite in SI but not in a unit it is printed in (1e308 m is inf cm): as good as inf.
    overflows = [u for u, factor in units.items() if not math.isfinite(value / factor)]
    if overflows:
        raise QuantityError(f'{text!r} is not a finite {kind} in {_spelling(overflows[0])}')
    if minimum is not None and (value <= minimum if strict else value < minimum):
        raise QuantityError(f'{text!r}: the {kind} must be {"more than" if strict else "at least"}'
                            f' {minimum:g} {si_unit}')
    return value


class Given(float):
    """An SI value that remembers the unit it was typed in (lower case; '' for a plain
    number), so that what is printed back about it is in the user's unit."""

    unit: str = ''

    def __new__(cls, value: float, unit: str = ''):
        given = super().__new__(cls, value)
        given.unit = unit
        return given


def parse_given(text: str, kind: str) -> Given:
    """parse(text, kind), with the unit it was typed in."""
    value = parse(text, kind)
    match = _QUANTITY.match(text)
    return Given(value, match.group(2).lower() if match else '')


# Every unit `pma` knows, of any kind, and a rate's `/time`: a word that, after a plain number,
# was meant as its unit (`pma set 2 bar`, `--max 500 kPa`, `--rate 50 kPa/s`).
_UNIT_WORD = re.compile(r'^([a-zA-Z]+)(/[a-zA-Z]+)?$', re.ASCII)
_NUMBER = re.compile(r'^[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$', re.ASCII)


def is_unit_word(text: str) -> bool:
    match = _UNIT_WORD.match(text)
    if match is None:
        return False
    per = (match.group(2) or '/s')[1:].lower()
    return any(match.group(1).lower() in units for units, _, _ in KINDS.values()) \
        and per in TIME_UNITS


def join_spaced_units(argv: list[str]) -> list[str]:
    """`2 bar` typed as two words becomes the one quantity `2 bar`: argparse would take the
    2 alone (2 Pa, with a note suggesting 2kPa) and refuse `bar` as an extra argument."""
    joined: list[str] = []
    for word in argv:
        if joined and is_unit_word(word) and _NUMBER.match(joined[-1]):
            joined[-1] = f'{joined[-1]} {word}'
        else:
            joined.append(word)
    return joined


# A plain number is SI, but a muscle is about 0.3 m long and inflates to hundreds of kPa: these
# look like a unit left out (`pma move 27`, `pma set 200`, `pma sweep --max 500`).
_UNIT_SLIPS = {'length': (lambda v: v >= 1.0, 'cm'), 'pressure': (lambda v: 0 < v < 1000, 'kPa')}


def unit_slip(text: str, kind: str, *, flag: str = '', per: str = '') -> str:
    """A note when a plain number of `kind` reads like a unit left out ('' otherwise).

    `flag` names the option it was given to (`--max`); `per` is a rate's time unit (`/s`).
    """
    match = _QUANTITY.match(text)
    if match is None or match.group(2) or kind not in _UNIT_SLIPS:
        return ''
    looks_wrong, unit = _UNIT_SLIPS[kind]
    value = float(match.group(1))
    if not (math.isfinite(value) and looks_wrong(value)):
        return ''
    _, si_unit, _ = KINDS[kind]
    option = f'{flag} ' if flag else ''
    return (f'{option}{text.strip()} is read as {value:g} {si_unit}{per} (a plain number is '
            f'SI): did you mean {option}{text.strip()}{unit}{per}?')


def parse_count(text: str, minimum: int = 0, maximum: int | None = None) -> int:
    """A whole number from `minimum` to `maximum`. A count that goes into a message field must
    fit the field: a uint32 wraps 4294967298 round to 2 without a word, and refuses -1 with a
    traceback."""
    ascii_only(text)
    try:
        value = int(text.strip())
    except ValueError:
        raise QuantityError(f'{text!r} is not a whole number') from None
    if value < minimum or (maximum is not None and value > maximum):
        raise QuantityError(f'{text!r} is out of range: give a whole number from {minimum}'
                            + (f' to {maximum}' if maximum is not None else ' up'))
    return value


def parse_rate(text: str, kind: str = 'pressure') -> float:
    """`50kPa/s`, `3bar/min` as SI per second; a plain number is SI per second."""
    ascii_only(text)
    amount, slash, per = text.partition('/')
    if not slash:
        match = _QUANTITY.match(text)
        if match is not None and match.group(2):
            raise QuantityError(f'{text!r} is not a rate: give it per time ({text.strip()}/s)'
                                f' or as a plain number in {KINDS[kind][1]}/s')
        return parse(text, kind)
    per = per.strip().lower()
    if per not in TIME_UNITS:
        raise QuantityError(f'{text!r}: {per!r} is not a unit of time (known: '
                            f'{", ".join(TIME_UNITS)})')
    rate = parse(amount, kind) / TIME_UNITS[per]
    if not math.isfinite(rate):
        raise QuantityError(f'{text!r} is not a finite rate')
    return rate


def parse_list(text: str, kind: str) -> list[float]:
    """`300kPa,150kPa` (commas or spaces) as SI values."""
    ascii_only(text)
    parts = [part for part in re.split(r'[,\s]+', text.strip()) if part]
    if not parts:
        raise QuantityError(f'{text!r} has no {kind} in it')
    return [parse(part, kind) for part in parts]


def _spelling(unit: str) -> str:
    return {'pa': 'Pa', 'kpa': 'kPa', 'mpa': 'MPa'}.get(unit, unit)


def unit_of_name(name: str) -> str | None:
    """The kind a parameter's SI suffix names ('pressure' for *_pa, ...), None for others.

    A suffix after another unit (`_pa_s`, `_m_s`, `_per_s`) is a rate, which takes plain SI.
    """
    tokens = name.rsplit('.', 1)[-1].split('_')
    if len(tokens) < 2:
        return None
    if tokens[-2] in ('pa', 'm', 'per', 's'):
        return None
    return {'pa': 'pressure', 'm': 'length', 's': 'time'}.get(tokens[-1])


def kpa(pressure_pa: float, digits: int = 1) -> str:
    """`212.3 kPa` (what a person reads); NaN as `-`."""
    if not math.isfinite(pressure_pa):
        return '-'
    return f'{pressure_pa / PA_PER_KPA:.{digits}f} kPa'


def cm(length_m: float, digits: int = 2) -> str:
    """`26.50 cm`; NaN (no echo) as `-`."""
    if not math.isfinite(length_m):
        return '-'
    return f'{length_m / M_PER_CM:.{digits}f} cm'


# A length printed in the unit it was asked in: the same 0.1 mm in each.
LENGTH_DIGITS = {'cm': 2, 'mm': 1, 'm': 4}


def length_unit(given) -> str:
    """The unit to print lengths in: the one `given` (a Given) was typed in, else cm."""
    unit = getattr(given, 'unit', '')
    return unit if unit in LENGTH_DIGITS else 'cm'


def length(length_m: float, unit: str = 'cm', *, number_only: bool = False) -> str:
    """`26.50 cm`, `265.0 mm` or `0.2650 m`; NaN as `-`."""
    if not math.isfinite(length_m):
        return '-'
    number = f'{length_m / LENGTH_UNITS[unit]:.{LENGTH_DIGITS[unit]}f}'
    return number if number_only else f'{number} {unit}'


def length_range(low_m: float, high_m: float, unit: str = 'cm') -> str:
    """`24.45 .. 30.04 cm`."""
    return f'{length(low_m, unit, number_only=True)} .. {length(high_m, unit)}'


_SI_NUMBER = r'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?'
# A node's message in SI (`reachable [0.2454, 0.3008] m with 0..500000 Pa`, `holding 0.2750
# m`): ranges first, then single values; a unit followed by `/` is a rate's, left alone.
_SI_LENGTH_RANGE = re.compile(rf'\[\s*({_SI_NUMBER})\s*,\s*({_SI_NUMBER})\s*\]\s*m\b(?!/)')
_SI_PRESSURE_RANGE = re.compile(rf'(?<![\w.])({_SI_NUMBER})\s*\.\.\s*({_SI_NUMBER})\s*Pa\b(?!/)')
_SI_LENGTH = re.compile(rf'(?<![\w.])({_SI_NUMBER})\s*m\b(?!/)')
_SI_PRESSURE = re.compile(rf'(?<![\w.])({_SI_NUMBER})\s*Pa\b(?!/)')


def in_units(message: str, unit: str = 'cm') -> str:
    """A node's message (SI: metres and pascals) with its lengths in `unit` and its
    pressures in kPa, as everything else `pma` prints: `holding 0.2750 m` -> `holding 27.50
    cm`, `reachable [0.2454, 0.3008] m with 0..500000 Pa` -> `reachable 24.54 .. 30.08 cm with
    0.0 .. 500.0 kPa`."""
    message = _SI_LENGTH_RANGE.sub(
        lambda m: length_range(float(m.group(1)), float(m.group(2)), unit), message)
    message = _SI_PRESSURE_RANGE.sub(
        lambda m: f'{float(m.group(1)) / PA_PER_KPA:.1f} .. {kpa(float(m.group(2)))}', message)
    message = _SI_LENGTH.sub(lambda m: length(float(m.group(1)), unit), message)
    return _SI_PRESSURE.sub(lambda m: kpa(float(m.group(1))), message)


def seconds(duration_s: float) -> str:
    """`4 s`, `2 min 05 s`, `1 h 02 min`."""
    if not math.isfinite(duration_s):
        return '-'
    whole = round(duration_s)
    if whole < 60:
        return f'{duration_s:.1f} s' if duration_s < 10 else f'{whole} s'
    minutes, secs = divmod(whole, 60)
    if minutes < 60:
        return f'{minutes} min {secs:02d} s'
    hours, minutes = divmod(minutes, 60)
    return f'{hours} h {minutes:02d} min'


def human(value: float, kind: str | None) -> str:
    """A parameter value with its human unit beside it, when its name has one."""
    if kind == 'pressure':
        return kpa(value, 3 if abs(value) < 1000 else 1)
    if kind == 'length':
        return cm(value, 2)
    if kind == 'time':
        # All its digits below a minute (0.15 s, not the 0.1 s a progress line would say).
        return seconds(value) if abs(value) >= 60 and value == round(value) \
            else f'{value:g} s'
    return ''
