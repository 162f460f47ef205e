"""The model's parameters: validated, in SI, loadable from and savable to a ROS params file.

One structure serves the node (flat dotted ROS parameters such as `increasing.sigmoid.a`),
the params file it loads with --params-file (nested under `/**: ros__parameters:`) and the
ModelParams message (YAML text). Both branch forms are always present and validated, so
switching `branch_form` never needs new numbers. The defaults live in the package data file
data/default_params.yaml (the paper's increasing fit and our least-squares fits of Table 1).
"""

from __future__ import annotations

import csv
import errno
import io
import math
import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from pma_model import units
from pma_model.adaptation import AdaptationSettings
from pma_model.branches import (
    BRANCH_FORMS,
    MAX_B_PER_PA,
    MAX_L0_M,
    MIN_K_PA,
    Branch,
    HillBranch,
    SigmoidBranch,
    branch_class,
)
from pma_model.detector import DEFAULT_DEADBAND_PA
from pma_model.identification import IdentificationSettings, OnlineModel, OnlineRule
from pma_model.memory import MEMORY_MODES, HysteresisModel
from pma_model.mix import MIX_MEMORY, MIX_RULES, RuleMix

# The memory setting: a registered rule (rules.MEMORY_RULES), or the rules mixed by their
# recent error (mix.py).
MEMORIES = (MIX_MEMORY, *MEMORY_MODES)
DIRECTIONS = ('increasing', 'decreasing')

# Sanity range that catches unit mix-ups (kPa for Pa); the branch ones live in branches.py.
MAX_GAUGE_PRESSURE_RANGE_PA = (10_000.0, 1_000_000.0)
# A params file is a few kB; anything past this is not one (and /dev/zero never ends).
MAX_PARAMS_FILE_BYTES = 1024 * 1024


class ParamsError(ValueError):
    """A parameter failed validation; the message names the field (dotted ROS name)."""


@dataclass(frozen=True)
class BranchParams:
    """Every registered form's parameters for one direction (increasing or decreasing
    pressure): `of_form('hill')`, or as an attribute, `.hill`."""

    forms: Mapping[str, Branch]

    def __post_init__(self):
        if set(self.forms) != set(BRANCH_FORMS):
            raise ParamsError(f'a direction needs the branch forms {tuple(BRANCH_FORMS)}, '
                              f'got {tuple(self.forms)}')
        object.__setattr__(self, 'forms', {form: self.forms[form] for form in BRANCH_FORMS})

    def __hash__(self):
        return hash(tuple(self.forms.items()))

    def __getattr__(self, name: str) -> Branch:
        forms = self.__dict__.get('forms')
        if forms is not None and name in forms:
            return forms[name]
        raise AttributeError(name)

    def of_form(self, form: str) -> Branch:
        return self.forms[form]

    def with_branch(self, branch: Branch) -> BranchParams:
        """A copy with `branch` replacing its form's numbers."""
        return BranchParams({**self.forms, branch.form: branch})


@dataclass(frozen=True)
class ModelParams:
    branch_form: str
    memory: str
    deadband_pa: float
    max_gauge_pressure_pa: float
    adaptation: AdaptationSettings
    increasing: BranchParams
    decreasing: BranchParams
    identification: IdentificationSettings = field(default_factory=IdentificationSettings)

    def __post_init__(self):
        if self.branch_form not in BRANCH_FORMS:
            raise ParamsError(f'branch_form must be one of {tuple(BRANCH_FORMS)}, '
                              f'got {self.branch_form!r}')
        if self.memory not in MEMORIES:
            raise ParamsError(f'memory must be one of {MEMORIES}, got {self.memory!r}')
        low, high = MAX_GAUGE_PRESSURE_RANGE_PA
        if not (math.isfinite(self.max_gauge_pressure_pa)
                and low <= self.max_gauge_pressure_pa <= high):
            raise ParamsError(f'max_gauge_pressure_pa must be in [{low:.0f}, {high:.0f}] Pa, '
                              f'got {self.max_gauge_pressure_pa!r} (Pa, not kPa)')
        if not (math.isfinite(self.deadband_pa)
                and 0 <= self.deadband_pa < 0.5 * self.max_gauge_pressure_pa):
            raise ParamsError('deadband_pa must be >= 0 and below half of '
                              f'max_gauge_pressure_pa, got {self.deadband_pa!r}')
        for direction in DIRECTIONS:
            pair = getattr(self, direction)
            for form in BRANCH_FORMS:
                _check_units(f'{direction}.{form}', pair.of_form(form))

    # --- building the pieces --------------------------------------------------------

    def branches(self) -> tuple[Branch, Branch]:
        """(increasing, decreasing) branches of the selected form."""
        return (self.increasing.of_form(self.branch_form),
                self.decreasing.of_form(self.branch_form))

    def build_model(self) -> HysteresisModel:
        """The memory model alone, with the branches as given (offline prediction, fits).

        The identified play shares are used; the learned branch correction, creep and
        drift are OnlineModel's (build_online). The 'mix' memory is online only: here it
        is its first rule, 'identify'.
        """
        increasing, decreasing = self.branches()
        memory = MIX_RULES[0] if self.memory == MIX_MEMORY else self.memory
        return HysteresisModel(increasing, decreasing, memory=memory,
                               deadband_pa=self.deadband_pa,
                               max_gauge_pressure_pa=self.max_gauge_pressure_pa,
                               play_shares=self.identification.play_shares,
                               share_slopes=self.identification.share_slopes)

    def build_online(self) -> OnlineRule:
        """The memory model with what it learns online (identification, drift adaptation);
        for the 'mix' memory, a RuleMix of an OnlineModel per rule, from the saved losses."""
        if self.memory == MIX_MEMORY:
            learned = self.identification
            return RuleMix.of_rules(
                lambda rule: replace(self, memory=rule, identification=learned.for_rule(rule))
                .build_online(),
                MIX_RULES, losses_m2s=[0.0, learned.play_rule_excess_loss_m2s],
                learning=learned.enabled)
        increasing, decreasing = self.branches()
        return OnlineModel(increasing, decreasing, memory=self.memory,
                           deadband_pa=self.deadband_pa,
                           max_gauge_pressure_pa=self.max_gauge_pressure_pa,
                           identification=self.identification, adaptation=self.adaptation)

    def with_learned(self, learned: IdentificationSettings) -> ModelParams:
        """A copy starting from what an OnlineModel has learned (shares, corrections, creep)."""
        return replace(self, identification=replace(self.identification,
                                                    **learned.learned_values()))

    def with_branches(self, increasing: Branch, decreasing: Branch) -> ModelParams:
        """A copy with the given branches (their form) replacing that form's numbers."""
        form = increasing.form
        if decreasing.form != form:
            raise ParamsError('both branches must have the same form')
        return replace(self, increasing=self.increasing.with_branch(increasing),
                       decreasing=self.decreasing.with_branch(decreasing))

    # --- flat ROS parameters --------------------------------------------------------

    def to_ros_parameters(self) -> dict[str, object]:
        """{dotted name: value}, the way rclpy sees the params file's nested keys."""
        flat: dict[str, object] = {
            'branch_form': self.branch_form,
            'memory': self.memory,
            'deadband_pa': float(self.deadband_pa),
            'max_gauge_pressure_pa': float(self.max_gauge_pressure_pa),
        }
        for group in ('adaptation', 'identification'):
            settings = getattr(self, group)
            for item in fields(settings):
                flat[f'{group}.{item.name}'] = _ros_value(getattr(settings, item.name))
        for direction in DIRECTIONS:
            for form in BRANCH_FORMS:
                for name, value in getattr(self, direction).of_form(form).to_dict().items():
                    flat[f'{direction}.{form}.{name}'] = float(value)
        return flat

    @classmethod
    def from_ros_parameters(cls, values: dict, base: ModelParams | None = None) -> ModelParams:
        """Parameters from {dotted name: value}; names not given keep `base` (the defaults).

        Unknown names, wrong types and out-of-range values raise ParamsError naming the field.
        Integers are accepted for float fields (a params file may say 10000 for 10000.0).
        """
        merged = (base or default_params()).to_ros_parameters()
        unknown = sorted(set(values) - set(merged))
        if unknown:
            raise ParamsError(f'unknown parameter(s) {unknown}; known: {sorted(merged)}')
        for name, value in values.items():
            merged[name] = _coerce(name, value, merged[name])
        pairs = {}
        for direction in DIRECTIONS:
            forms = {}
            for form in BRANCH_FORMS:
                prefix = f'{direction}.{form}.'
                branch_values = {key[len(prefix):]: value for key, value in merged.items()
                                 if key.startswith(prefix)}
                try:
                    forms[form] = branch_class(form).from_dict(branch_values)
                except ValueError as error:
                    raise ParamsError(f'{prefix}{error}') from None
            pairs[direction] = BranchParams(forms)
        groups = {}
        for group, settings in (('adaptation', AdaptationSettings),
                                ('identification', IdentificationSettings)):
            values = {item.name: merged[f'{group}.{item.name}'] for item in fields(settings)}
            try:
                groups[group] = settings(**values)
            except ValueError as error:
                raise ParamsError(f'{group}.{error}') from None
        return cls(branch_form=merged['branch_form'], memory=merged['memory'],
                   deadband_pa=merged['deadband_pa'],
                   max_gauge_pressure_pa=merged['max_gauge_pressure_pa'], **groups, **pairs)

    # --- YAML (ROS params-file format) ----------------------------------------------

    def to_nested(self, only: tuple[str, ...] = ()) -> dict:
        """The ros__parameters mapping: nested dicts, SI values, floats as floats.

        `only`: keep just the names equal to, or under, these (e.g. 'increasing').
        """
        nested: dict = {}
        for name, value in self.to_ros_parameters().items():
            if only and not any(name == key or name.startswith(f'{key}.') for key in only):
                continue
            node = nested
            *parents, leaf = name.split('.')
            for parent in parents:
                node = node.setdefault(parent, {})
            node[leaf] = value
        return nested

    def to_yaml(self, node_name: str = '/**', only: tuple[str, ...] = ()) -> str:
        """Params-file text that `model_node --ros-args --params-file` loads as is."""
        return yaml.safe_dump({node_name: {'ros__parameters': self.to_nested(only)}},
                              sort_keys=False, default_flow_style=False)

    def save_yaml(self, path, node_name: str = '/**', only: tuple[str, ...] = (),
                  header: str = '') -> None:
        """Write atomically (temp file + rename): model_node may be polling this very file."""
        path = Path(path)
        text = ''.join(f'# {line}\n' if line else '#\n' for line in header.splitlines())
        text += self.to_yaml(node_name, only)
        temporary = path.with_name(f'.{path.name}.tmp')
        temporary.write_text(text)
        os.replace(temporary, path)

    @classmethod
    def from_nested(cls, nested: dict, base: ModelParams | None = None) -> ModelParams:
        if not isinstance(nested, dict):
            raise ParamsError(f'ros__parameters must be a mapping, got {type(nested).__name__}')
        return cls.from_ros_parameters(_flatten(nested), base)

    @classmethod
    def from_yaml(cls, text: str, base: ModelParams | None = None) -> ModelParams:
        """From params-file text: `<node or /**>: {ros__parameters: {...}}`."""
        try:
            document = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise ParamsError(f'not valid YAML: {error}') from None
        if not isinstance(document, dict) or len(document) != 1:
            raise ParamsError('a params file must have exactly one top-level key '
                              "(a node name or '/**')")
        (section,) = document.values()
        if not isinstance(section, dict) or set(section) != {'ros__parameters'}:
            raise ParamsError("the top-level key must hold only 'ros__parameters'")
        return cls.from_nested(section['ros__parameters'], base)

    @classmethod
    def load_yaml(cls, path, base: ModelParams | None = None) -> ModelParams:
        """From a params file; never blocks or reads without bound (see read_params_text)."""
        text = read_params_text(path)
        try:
            return cls.from_yaml(text, base)
        except ParamsError as error:
            raise ParamsError(f'{path}: {error}') from None


def read_params_text(path, max_bytes: int = MAX_PARAMS_FILE_BYTES) -> str:
    """The text of a params file, or ParamsError saying why not, in one line.

    model_node reads this on its only executor thread, so the read must neither block nor
    run on without end: the file is opened non-blocking (a FIFO without a writer opens at
    once) and must be a regular file (not a FIFO, device or directory: /dev/zero would be
    read until memory runs out), of at most `max_bytes`, in UTF-8.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY)
    except OSError as error:
        raise ParamsError(f'cannot read params file {path}: {error.strerror}') from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ParamsError(f'params file {path} is {_file_kind(info.st_mode)}, not a regular '
                              'file')
        if info.st_size > max_bytes:
            raise ParamsError(f'params file {path} is {info.st_size} bytes, more than the '
                              f'{max_bytes} a params file may have')
        chunks, size = [], 0
        while size <= max_bytes:         # the file may grow after fstat: still stop
            try:
                chunk = os.read(fd, max_bytes + 1 - size)
            except OSError as error:
                if error.errno == errno.EAGAIN:
                    raise ParamsError(f'params file {path} has no data to read now') from None
                raise ParamsError(f'cannot read params file {path}: {error.strerror}') \
                    from None
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > max_bytes:
            raise ParamsError(f'params file {path} has more than the {max_bytes} bytes a params '
                              'file may have')
    finally:
        os.close(fd)
    data = b''.join(chunks)
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise ParamsError(f'params file {path} is not UTF-8 text: '
                          f'{utf8_error_position(data, error)}') from None


def utf8_error_position(data: bytes, error: UnicodeDecodeError) -> str:
    """Where `data` stops being UTF-8, for a person: 'byte 0xe9 at offset 5 (line 1)'."""
    line = data.count(b'\n', 0, error.start) + 1
    return f'byte 0x{data[error.start]:02x} at offset {error.start} (line {line})'


def _file_kind(mode: int) -> str:
    kinds = ((stat.S_ISFIFO, 'a FIFO'), (stat.S_ISDIR, 'a directory'),
             (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'),
             (stat.S_ISSOCK, 'a socket'))
    return next((name for test, name in kinds if test(mode)), 'a special file')


def _check_units(prefix: str, branch: Branch) -> None:
    if branch.l0_m > MAX_L0_M:
        raise ParamsError(f'{prefix}.l0_m must be <= {MAX_L0_M} m, got {branch.l0_m!r} '
                          '(metres, not cm)')
    if isinstance(branch, SigmoidBranch) and branch.b_per_pa > MAX_B_PER_PA:
        raise ParamsError(f'{prefix}.b_per_pa must be <= {MAX_B_PER_PA} per Pa, got '
                          f'{branch.b_per_pa!r} (per Pa, not per kPa)')
    if isinstance(branch, HillBranch) and branch.k_pa < MIN_K_PA:
        raise ParamsError(f'{prefix}.k_pa must be >= {MIN_K_PA} Pa, got {branch.k_pa!r} '
                          '(Pa, not kPa)')


def _ros_value(value):
    """A settings value as rclpy types it: bool, float, or a list of floats."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (tuple, list)):
        return [float(item) for item in value]
    return float(value)


def _coerce(name: str, value, template):
    """`value` as the type of the default `template`, or ParamsError naming the field."""
    if isinstance(template, list):
        if isinstance(value, (str, bytes)) or not hasattr(value, '__iter__'):
            raise ParamsError(f'{name} must be a list of {len(template)} numbers, '
                              f'got {value!r}')
        return [_coerce(name, item, 0.0) for item in value]
    if isinstance(template, bool):
        if isinstance(value, bool):
            return value
        raise ParamsError(f'{name} must be true or false, got {value!r}')
    if isinstance(template, str):
        if isinstance(value, str):
            return value
        raise ParamsError(f'{name} must be a string, got {value!r}')
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamsError(f'{name} must be a number, got {value!r}')
    if not math.isfinite(value):
        raise ParamsError(f'{name} must be finite, got {value!r}')
    return float(value)


def _flatten(nested: dict, prefix: str = '') -> dict:
    flat = {}
    for key, value in nested.items():
        name = f'{prefix}{key}'
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{name}.'))
        else:
            flat[name] = value
    return flat


@dataclass(frozen=True)
class PaperTable:
    """The paper's Table 1 in SI: one length per pressure for each branch."""

    pressure_pa: np.ndarray
    increasing_length_m: np.ndarray
    decreasing_length_m: np.ndarray

    @property
    def stroke_m(self) -> float:
        """The rest length (at 0 Pa) minus the shortest: 5.86 cm, the stroke that errors are
        given as a share of."""
        rest = self.increasing_length_m[np.argmin(self.pressure_pa)]
        return float(rest - min(self.increasing_length_m.min(), self.decreasing_length_m.min()))


def paper_table1() -> PaperTable:
    """Table 1 from the package data (kPa/cm in the file, SI here)."""
    text = resources.files('pma_model').joinpath('data', 'paper_table1.csv').read_text()
    rows = list(csv.DictReader(io.StringIO(text)))

    def column(name):
        return np.array([float(row[name]) for row in rows])

    return PaperTable(units.kpa_to_pa(column('pressure_kpa')),
                      units.cm_to_m(column('length_increasing_cm')),
                      units.cm_to_m(column('length_decreasing_cm')))


def default_params_path():
    """The packaged defaults (a Traversable; read it with .read_text())."""
    return resources.files('pma_model').joinpath('data', 'default_params.yaml')


def default_params() -> ModelParams:
    """The shipped defaults, read from the package data file every time (it is small)."""
    document = yaml.safe_load(default_params_path().read_text())
    (section,) = document.values()
    flat = _flatten(section['ros__parameters'])
    missing = sorted(set(_SEED.to_ros_parameters()) - set(flat))
    if missing:
        raise ParamsError(f'{default_params_path()} lacks {missing}')
    return ModelParams.from_ros_parameters(flat, base=_SEED)


# from_ros_parameters needs a complete base to merge into; this seed is only that scaffold
# (every value is overwritten by the data file, and the file must name every field).
_SEED = ModelParams(
    branch_form='sigmoid', memory='identify', deadband_pa=DEFAULT_DEADBAND_PA,
    max_gauge_pressure_pa=500_000.0, adaptation=AdaptationSettings(),
    increasing=BranchParams({name: form.seed for name, form in BRANCH_FORMS.items()}),
    decreasing=BranchParams({name: form.seed for name, form in BRANCH_FORMS.items()}))
