"""What `pma`'s verbs share on the command line: argparse types for quantities and ROS names,
the parser that takes negative quantities, and the flags every ROS verb has."""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from pma_cli import quantities as q
from pma_cli.session import namespace_of

DEFAULT_TIMEOUT_S = 10.0


def argument(parse, name: str):
    """An argparse type from a quantities parser: its refusal becomes argparse's message."""
    def convert(text: str):
        try:
            return parse(text)
        except q.QuantityError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    convert.__name__ = name
    return convert


def note_slip(text: str, kind: str, **where) -> None:
    """A note on stderr when a plain number reads like a unit left out (`pma set 200`,
    `--max 500`); it is still taken as SI (quantities.unit_slip)."""
    slip = q.unit_slip(text, kind, **where)
    if slip:
        print(f'pma: note: {slip}', file=sys.stderr)


def quantity(kind: str, flag: str = '', **bounds):
    """A quantity of `kind`; `bounds` as for quantities.parse (minimum=, strict=). With
    `flag`, a plain number that reads like a unit left out gets a note (note_slip)."""
    def parse(text: str) -> float:
        value = q.parse(text, kind, **bounds)
        if flag:
            note_slip(text, kind, flag=flag)
        return value
    return argument(parse, kind)


def target(kind: str):
    """A verb's own quantity (`pma set 200`, `pma move 27`): a quantities.Given (what is
    printed about it is in its unit), with note_slip's note."""
    def parse(text: str) -> q.Given:
        value = q.parse_given(text, kind)
        note_slip(text, kind)
        return value
    return argument(parse, kind)


def quantities(kind: str, flag: str = ''):
    def parse(text: str) -> list[float]:
        values = q.parse_list(text, kind)
        for part in (p for p in re.split(r'[,\s]+', text.strip()) if p):
            if flag:
                note_slip(part, kind, flag=flag)
        return values
    return argument(parse, f'{kind} list')


def rate(kind: str, flag: str = ''):
    def parse(text: str) -> float:
        value = q.parse_rate(text, kind)
        if flag and '/' not in text:
            note_slip(text, kind, flag=flag, per='/s')
        return value
    return argument(parse, f'{kind} rate')


def field_count(message, field: str, minimum: int):
    """A whole number the message's integer field can hold (else it wraps or raises), from
    `minimum` (the field's own rule) up."""
    field_type = message.get_fields_and_field_types()[field]        # 'uint32', 'int64', ...
    bits = int(field_type.removeprefix('u').removeprefix('int'))
    top = 2 ** bits - 1 if field_type.startswith('u') else 2 ** (bits - 1) - 1
    return argument(lambda text: q.parse_count(text, minimum, top), 'count')


def rcl_name(what: str, check):
    """An argparse type for a name rcl validates, checked here: a node or client made with
    `bad name!` or `1abc` in its name ends in rclpy's traceback. `check` raises rclpy's
    NameValidationException, whose first line has the reason."""
    from rclpy.exceptions import NameValidationException

    def convert(text: str) -> str:
        try:
            check(text)
        except NameValidationException as error:
            first = str(error).splitlines()[0]          # 'Invalid namespace: namespace must ...:'
            kind, _, reason = first.removeprefix('Invalid ').partition(': ')
            raise argparse.ArgumentTypeError(
                f'{text!r} is not a {what}: {reason.removeprefix(kind + " ").rstrip(":")}'
                ) from None
        return text
    convert.__name__ = what
    return convert


def check_namespace(text: str) -> None:
    from rclpy.validate_namespace import validate_namespace
    validate_namespace(namespace_of(text))


def check_node(text: str) -> None:
    """`driver_node`, `left/driver_node` or `/left/driver_node`."""
    from rclpy.validate_node_name import validate_node_name
    namespace, _, name = text.rpartition('/')
    validate_node_name(name)
    if namespace:
        check_namespace(namespace)


def output_file(text: str) -> Path:
    """A file to write. Path() drops a trailing slash, so `out/` would become a file `out`:
    a directory is refused. (Whether the directory it is in exists is the verb's to check when
    it runs: an earlier command may make it.)"""
    path = Path(text)
    if text != '-' and (text.endswith(('/', os.sep)) or path.is_dir()):
        raise argparse.ArgumentTypeError(f'{text!r} is a directory: give a file name to write')
    return path


class Parser(argparse.ArgumentParser):
    """Takes `-5kPa`, `-inf` and `-nan` as (negative) quantities: argparse alone takes only a
    bare number such as `-5` for a value, calls `-5kPa` a missing argument and `-nan` the
    option `-n an`. No option of pma starts with a digit or is `-inf` or `-nan`, so nothing
    that does can be one; the quantity parser then says what is wrong with it. (Sets argparse's
    `_negative_number_matcher` and checks it before `_parse_optional`'s prefix matching;
    should a Python drop them, `-5kPa` needs `--` again.)"""

    NEGATIVE = re.compile(r'^-(\.?\d|(inf|infinity|nan)$)', re.IGNORECASE)

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = self.NEGATIVE

    def _parse_optional(self, arg_string):
        if self.NEGATIVE.match(arg_string):
            return None              # a positional value
        return super()._parse_optional(arg_string)

    joins_units = False          # the top parser: it sees the whole command line

    def parse_known_args(self, args=None, namespace=None):
        """`pma set 2 bar`: a unit typed apart from its number is joined to it
        (quantities.join_spaced_units); never in `pma run`'s arguments, which are the
        executable's own."""
        args = sys.argv[1:] if args is None else list(args)
        if self.joins_units and args[:1] != ['run']:
            args = q.join_spaced_units(args)
        return super().parse_known_args(args, namespace)


def common_parser() -> Parser:
    """--namespace and --timeout, the flags of every verb that talks to the rig."""
    common = Parser(add_help=False)
    common.add_argument('-n', '--namespace', type=rcl_name('ROS namespace', check_namespace),
                        default=os.environ.get('PMA_NAMESPACE', ''),
                        help="the muscle's namespace (left, /right, / for the root; default: "
                             '$PMA_NAMESPACE, else the root)')
    common.add_argument('--timeout', type=quantity('time', minimum=0.0, strict=True),
                        default=DEFAULT_TIMEOUT_S,
                        metavar='TIME', help='how long to wait for the node to answer '
                        f'(default {DEFAULT_TIMEOUT_S:g}s)')
    return common
