"""The facts a methods section needs, carried into every bag's metadata.

`pma sweep`, `pma up`, the recorder and the bring-up launch file take the same flags (and
launch arguments of the same names, with underscores); each one given becomes a `custom_data`
entry of the bag (metadata.yaml), which `pma_bag info`, refit's report, every plot's footer
and the CSV export show. One registry, so every tool spells them alike: docs/bags.md lists
the keys.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass


class ExperimentError(ValueError):
    """A value that cannot be stored as asked (a negative load, non-ASCII digits, ...)."""


def _text(value: str) -> str:
    text = value.strip()
    if not text:
        raise ExperimentError('must not be empty')
    return text


def _non_negative(scale: float) -> Callable[[str], str]:
    def parse(value: str) -> str:
        text = value.strip()
        if not text.isascii():
            raise ExperimentError(f'{value!r} is not a number in ASCII digits')
        try:
            number = float(text)
        except ValueError:
            raise ExperimentError(f'{value!r} is not a number') from None
        if not (math.isfinite(number) and number >= 0):
            raise ExperimentError(f'must be a finite number >= 0, got {value!r}')
        return repr(number * scale)
    return parse


@dataclass(frozen=True)
class ExperimentField:
    name: str            # the launch argument, and the flag with '-' for '_'
    key: str             # the custom_data key (SI units, the unit in the name)
    parse: Callable[[str], str]    # what the user typed -> the stored text
    metavar: str
    help: str
    show: Callable[[str], str]     # the stored text -> what a person reads

    @property
    def flag(self) -> str:
        return '--' + self.name.replace('_', '-')


FIELDS = (
    ExperimentField('muscle', 'experiment.muscle', _text, 'ID',
                    "the muscle's ID (the label on its sleeve, say)", lambda v: f'muscle {v}'),
    ExperimentField('load_kg', 'experiment.load_kg', _non_negative(1.0), 'KG',
                    'the mass hanging on the muscle [kg]', lambda v: f'load {float(v):g} kg'),
    ExperimentField('supply_kpa', 'experiment.supply_gauge_pressure_pa', _non_negative(1e3),
                    'KPA', "the supply regulator's gauge pressure [kPa] (stored in Pa)",
                    lambda v: f'supply {float(v) / 1e3:g} kPa'),
    ExperimentField('operator', 'experiment.operator', _text, 'NAME', 'who ran it',
                    lambda v: f'operator {v}'),
)
KEYS = tuple(field.key for field in FIELDS)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags, each optional (a flag not given writes no entry)."""
    for field in FIELDS:
        parser.add_argument(field.flag, dest=f'experiment_{field.name}', metavar=field.metavar,
                            help=f'{field.help}; into the bag\'s custom_data as {field.key}')


def custom_data(values: Mapping[str, str | None]) -> dict[str, str]:
    """{key: stored text} of the given values ({name: typed text}; None or '' = not given);
    ExperimentError naming the flag for a value that cannot be stored."""
    data = {}
    for field in FIELDS:
        value = values.get(field.name)
        if value is None or value == '':
            continue
        try:
            data[field.key] = field.parse(str(value))
        except ExperimentError as error:
            raise ExperimentError(f'{field.flag}: {error}') from None
    return data


def typed(args: argparse.Namespace) -> dict[str, str]:
    """{name: the text typed} of the flags `add_arguments` added ('' for one not given)."""
    return {field.name: getattr(args, f'experiment_{field.name}', None) or ''
            for field in FIELDS}


def from_arguments(args: argparse.Namespace) -> dict[str, str]:
    """custom_data of the flags `add_arguments` added (ExperimentError: one cannot be)."""
    return custom_data(typed(args))


def summary(data: Mapping[str, str]) -> str:
    """One line for a person ('muscle m2, load 1.5 kg, supply 600 kPa, operator ada');
    '' when the bag says none of it."""
    return ', '.join(field.show(data[field.key]) for field in FIELDS if field.key in data)


# What a bring-up (bringup.launch.py, `pma up`) passes on to its recorder, by launch argument
# name (the recorder's flag: '--' + name with '-' for '_'): every field, and the note.
RECORDER_ARGUMENTS = {**{field.name: field.help for field in FIELDS},
                      'note': 'a free note for every bag it records'}


def recorder_flags(values: Mapping[str, str]) -> list[str]:
    """The recorder's command-line flags of the given values (empty ones left out)."""
    flags = []
    for name in RECORDER_ARGUMENTS:
        value = values.get(name, '')
        if value:
            flags += ['--' + name.replace('_', '-'), str(value)]
    return flags
