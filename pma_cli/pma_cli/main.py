"""`pma VERB ...`: the rig from a shell, with or without the `ros2` command line.

Every verb is a small client of the project's own topics, services and actions (docs/cli.md
lists what each one calls, beside its `ros2` spelling). Quantities are typed the way people
say them (200kPa, 26.5cm, 5s; a plain number is SI) and printed in kPa and cm. Exit codes:
0 done, 1 refused or failed (the message says why), 2 bad arguments, 3 nothing answered (not
running, or another namespace), 130 interrupted (the goal was cancelled first); a reader that
closes the pipe early (`pma watch | head`) ends it quietly with 141, as SIGPIPE ends a shell tool.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from pma_cli import quantities as q
from pma_cli.session import FAILED, INTERRUPTED, USAGE, CliError, Interrupted, namespace_of
from pma_common import experiment
from pma_common.console import closed_pipe_ends_quietly
from pma_driver.sweep import FORC_FAMILIES, PROFILES
from pma_interfaces.action import Sweep

DEFAULT_TIMEOUT_S = 10.0
# `pma status` listens at most this long for every node's diagnostics (usually ~4 s:
# observe.MIN_LISTEN_S).
STATUS_LISTEN_S = 8.0


def _argument(parse, name: str):
    """An argparse type from a quantities parser: its refusal becomes argparse's message."""
    def convert(text: str):
        try:
            return parse(text)
        except q.QuantityError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    convert.__name__ = name
    return convert


def _note_slip(text: str, kind: str, **where) -> None:
    """A note on stderr when a plain number reads like a unit left out (`pma set 200`,
    `--max 500`); it is still taken as SI (quantities.unit_slip)."""
    slip = q.unit_slip(text, kind, **where)
    if slip:
        print(f'pma: note: {slip}', file=sys.stderr)


def _quantity(kind: str, flag: str = '', **bounds):
    """A quantity of `kind`; `bounds` as for quantities.parse (minimum=, strict=). With
    `flag`, a plain number that reads like a unit left out gets a note (_note_slip)."""
    def parse(text: str) -> float:
        value = q.parse(text, kind, **bounds)
        if flag:
            _note_slip(text, kind, flag=flag)
        return value
    return _argument(parse, kind)


def _target(kind: str):
    """A verb's own quantity (`pma set 200`, `pma move 27`): a quantities.Given (what is
    printed about it is in its unit), with _note_slip's note."""
    def parse(text: str) -> q.Given:
        value = q.parse_given(text, kind)
        _note_slip(text, kind)
        return value
    return _argument(parse, kind)


def _quantities(kind: str, flag: str = ''):
    def parse(text: str) -> list[float]:
        values = q.parse_list(text, kind)
        for part in (p for p in re.split(r'[,\s]+', text.strip()) if p):
            if flag:
                _note_slip(part, kind, flag=flag)
        return values
    return _argument(parse, f'{kind} list')


def _rate(kind: str, flag: str = ''):
    def parse(text: str) -> float:
        value = q.parse_rate(text, kind)
        if flag and '/' not in text:
            _note_slip(text, kind, flag=flag, per='/s')
        return value
    return _argument(parse, f'{kind} rate')


def _field_count(message, field: str, minimum: int):
    """A whole number the message's integer field can hold (else it wraps or raises), from
    `minimum` (the field's own rule) up."""
    field_type = message.get_fields_and_field_types()[field]        # 'uint32', 'int64', ...
    bits = int(field_type.removeprefix('u').removeprefix('int'))
    top = 2 ** bits - 1 if field_type.startswith('u') else 2 ** (bits - 1) - 1
    return _argument(lambda text: q.parse_count(text, minimum, top), 'count')


def _rcl_name(what: str, check):
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


def _check_namespace(text: str) -> None:
    from rclpy.validate_namespace import validate_namespace
    validate_namespace(namespace_of(text))


def _check_node(text: str) -> None:
    """`driver_node`, `left/driver_node` or `/left/driver_node`."""
    from rclpy.validate_node_name import validate_node_name
    namespace, _, name = text.rpartition('/')
    validate_node_name(name)
    if namespace:
        _check_namespace(namespace)


def _output_file(text: str) -> Path:
    """A file to write. Path() drops a trailing slash, so `out/` would become a file `out`:
    a directory is refused. (Whether the directory it is in exists is the verb's to check when
    it runs: an earlier command may make it.)"""
    path = Path(text)
    if text != '-' and (text.endswith(('/', os.sep)) or path.is_dir()):
        raise argparse.ArgumentTypeError(f'{text!r} is a directory: give a file name to write')
    return path


class _Parser(argparse.ArgumentParser):
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


def parser() -> argparse.ArgumentParser:
    common = _Parser(add_help=False)
    common.add_argument('-n', '--namespace', type=_rcl_name('ROS namespace', _check_namespace),
                        default=os.environ.get('PMA_NAMESPACE', ''),
                        help="the muscle's namespace (left, /right, / for the root; default: "
                             '$PMA_NAMESPACE, else the root)')
    common.add_argument('--timeout', type=_quantity('time', minimum=0.0, strict=True),
                        default=DEFAULT_TIMEOUT_S,
                        metavar='TIME', help='how long to wait for the node to answer '
                        f'(default {DEFAULT_TIMEOUT_S:g}s)')
    top = _Parser(
        prog='pma', description='The PMA rig from a shell: status, setpoints, sweeps, the '
        'inverse model, parameters, calibration and CSV export. Quantities: 200kPa, 2bar, '
        '26.5cm, 5s; a plain number is SI (Pa, m, s).',
        epilog='exit codes: 0 done, 1 refused or failed, 2 bad arguments, 3 nothing answered, '
               '130 interrupted. docs/cli.md has the details and the ros2 equivalents.')
    top.joins_units = True
    verbs = top.add_subparsers(dest='verb', required=True, metavar='VERB')

    def verb(name: str, text: str, **kwargs) -> argparse.ArgumentParser:
        return verbs.add_parser(name, help=text, description=text, parents=[common], **kwargs)

    p = verb('status', 'link, rate, pressure, length, model and controller, from /diagnostics '
             'and the topics; exit 0 when the driver streams without an error')
    p.add_argument('--wait', type=_quantity('time', minimum=0.0), nargs='?', const=30.0,
                   default=0.0,
                   metavar='TIME', help='first wait until the driver streams (default 30s)')
    p = verb('watch', 'one line per sample: pressure, setpoint, length, the model\'s prediction '
             '(Ctrl-C ends it)')
    p.add_argument('--count', type=_argument(q.parse_count, 'count'), default=0,
                   help='stop after this many lines (default 0: until Ctrl-C)')
    p.add_argument('--max-rate', type=_quantity('frequency', minimum=0.0), default=20.0,
                   metavar='HZ', help='at most about this many lines a second; a stream at '
                   'that rate shows every sample (default 20; 0 = no limit)')
    p.add_argument('--si', action='store_true', help='columns in Pa and m instead of kPa and cm')
    p = verb('set', 'command a gauge pressure (pma/pressure_setpoint) and confirm the device '
             'took it; a length controller that holds a length is released first')
    p.add_argument('pressure', type=_target('pressure'), help='e.g. 200kPa, 2bar, 200000')
    p.add_argument('--wait', action='store_true', help='also wait until the pressure is there '
                   '(up to 30s, or --timeout if longer)')
    p.add_argument('--tolerance', type=_quantity('pressure', '--tolerance', minimum=0.0,
                                                 strict=True),
                   default=10_000.0,
                   help='for --wait (default 10kPa)')
    p = verb('vent', 'cancel any sweep or move and command 0 Pa')
    p.add_argument('--wait', action='store_true', help='wait until the pressure is near 0')
    p = verb('tare', "zero the pressure reading at rest (the driver's ~/tare)")
    p.add_argument('--vent', action='store_true',
                   help='vent first and wait until the pressure is steady')
    p = verb('sweep', 'run a pressure profile (the Sweep action: a staircase by default) with a '
             'progress bar (a length controller that holds a length is released first); '
             'Ctrl-C cancels it and the driver vents',
             epilog='profiles and their flags: staircase --max --step [--hold] [--reversals]; '
             'forc --max --step --forc-count [--forc-family] [--hold]; ramp --max --rate '
             '[--reversals] [--hold]; sine --amplitude --offset --frequency [--max]; csv --csv '
             '[--max]. All take --cycles and --rest. A flag the profile does not use is refused '
             'by the driver, with the reason.')
    p.add_argument('--profile', choices=PROFILES, default='staircase',
                   help='the path of the pressure (default staircase)')
    p.add_argument('--max', type=_quantity('pressure', '--max'), default=0.0, dest='max_pa',
                   metavar='PRESSURE', help='top of a staircase, FORC set or ramp, e.g. 500kPa; '
                   'sine, csv: an optional bound')
    p.add_argument('--step', type=_quantity('pressure', '--step'), default=0.0, dest='step_pa',
                   metavar='PRESSURE', help='staircase, forc: step height, e.g. 50kPa')
    p.add_argument('--hold', type=_quantity('time'), default=None, dest='hold_s',
                   metavar='TIME', help='staircase, forc: hold at each step (default 5s); '
                   'ramp: at each turning point (default 0)')
    p.add_argument('--cycles', type=_field_count(Sweep.Goal, 'cycles', 1), default=1,
                   help='repetitions of the whole profile; sine: periods (default 1)')
    p.add_argument('--rest', type=_quantity('time'), default=0.0, dest='rest_s',
                   metavar='TIME', help='rest at 0 Pa between cycles (default none)')
    p.add_argument('--reversals', type=_quantities('pressure', '--reversals'), default=[],
                   help='staircase, ramp: minor loops, turn at these pressures, e.g. '
                        '300kPa,150kPa')
    p.add_argument('--rate', type=_rate('pressure', '--rate'), default=0.0, dest='rate_pa_s',
                   metavar='RATE', help='ramp: rise and fall rate, e.g. 50kPa/s')
    p.add_argument('--amplitude', type=_quantity('pressure', '--amplitude'), default=0.0,
                   dest='amplitude_pa', metavar='PRESSURE', help='sine: amplitude, e.g. 100kPa')
    p.add_argument('--offset', type=_quantity('pressure', '--offset'), default=0.0,
                   dest='offset_pa',
                   metavar='PRESSURE', help='sine: mean pressure, e.g. 200kPa')
    p.add_argument('--frequency', type=_quantity('frequency'), default=0.0,
                   dest='frequency_hz', metavar='FREQUENCY', help='sine: e.g. 0.1Hz')
    p.add_argument('--csv', type=Path, dest='profile_csv', metavar='FILE',
                   help='csv: a file with columns time_s,gauge_pressure_pa (SI; a sample log '
                        'replays as a profile)')
    p.add_argument('--forc-count', type=_field_count(Sweep.Goal, 'forc_count', 1), default=0,
                   help='forc: number of reversal curves')
    p.add_argument('--forc-family', choices=FORC_FAMILIES, default='',
                   help='forc: ascending (default), descending or both (for refit '
                        '--memory-check)')
    p.add_argument('--record', nargs='?', const='', metavar='BAG',
                   help='record the run to its own bag (a relative path is taken from here; '
                        'no path = auto-named); needs a recorder: pma run pma_bag record --idle')
    p.add_argument('--note', default='', help="operator's note for the bag's metadata")
    experiment.add_arguments(p)
    p.add_argument('--start-pressurised', action='store_true',
                   help='start from the pressure the muscle has, without venting and waiting '
                        'for rest first (the first level may then be on the falling branch)')
    p = verb('length', 'which pressure gives this length? (the inverse model service)')
    p.add_argument('length', type=_target('length'), help='e.g. 26.5cm, 0.265')
    p.add_argument('--branch', choices=('auto', 'inc', 'dec', 'increasing', 'decreasing'),
                   default='auto', help='inc/dec: that major branch; auto (default): from the '
                   'current state along the path the muscle will follow')
    p.add_argument('--si', action='store_true', help='print only the pressure in Pa')
    p = verb('move', 'move to a length and hold it (the length controller\'s MoveToLength); '
             'Ctrl-C cancels')
    p.add_argument('length', type=_target('length'), help='e.g. 26.5cm')
    p.add_argument('--tolerance', type=_quantity('length', '--tolerance'), default=0.0,
                   help='settled within this (default: the action\'s 2mm)')
    p.add_argument('--settle', type=_quantity('time'), default=0.0,
                   help='for this long (default: the action\'s 1s)')
    p.add_argument('--goal-timeout', type=_quantity('time'), default=0.0,
                   help='abort if not settled by then (default: the action\'s 30s)')
    p.add_argument('--record', nargs='?', const='', metavar='BAG',
                   help='record the move to its own bag (a relative path is taken from here; '
                        'no path = auto-named); needs a recorder: pma run pma_bag record --idle')
    p.add_argument('--note', default='', help="operator's note for the bag's metadata")
    experiment.add_arguments(p)
    p = verb('param', "get, set or list a node's parameters (what `ros2 param` does)")
    p.add_argument('action', choices=('get', 'set', 'list'))
    p.add_argument('node', type=_rcl_name('ROS node name', _check_node),
                   help='driver_node, model_node, length_controller, recorder, ... '
                   '(relative to --namespace, or absolute)')
    p.add_argument('name', nargs='?', help='parameter name (get, set)')
    p.add_argument('value', nargs='?', help='new value (set); units where the name has one: '
                   'max_gauge_pressure_pa 450kPa')
    p = verb('calibrate', 'guided calibration: pressure zero and span against a reference '
             'gauge, length offset from a tape measurement; writes a driver params file')
    p.add_argument('-o', '--params-out', type=_output_file,
                   default=Path('pma_calibration.yaml'),
                   help='params file to write (default pma_calibration.yaml)')
    p.add_argument('--check-pressure', type=_quantity('pressure', '--check-pressure'),
                   default=None,
                   help='span check pressure (default 60 %% of max_gauge_pressure_pa)')
    p.add_argument('--skip-pressure', action='store_true', help='no tare, no span check')
    p.add_argument('--skip-length', action='store_true', help='no length offset')
    p.add_argument('--bag', type=Path, help='also record the calibration run to this bag, '
                   'with the result in its metadata')
    p.add_argument('-y', '--yes', action='store_true', help='do not ask for confirmations '
                   '(the gauge and tape readings are still asked)')
    p = verb('export', 'a bag as CSV: one row per pma/state with its prediction, SI columns')
    p.add_argument('bag', type=Path, help='bag directory or .mcap')
    p.add_argument('--csv', type=_output_file, required=True,
                   metavar='OUT', help="CSV file to write, in a directory that exists ('-' = "
                   'standard output)')
    p.add_argument('--topic', default='pma/state', help='PmaState topic (default pma/state, in '
                   'any namespace)')
    p.add_argument('--no-comments', action='store_true',
                   help='no # metadata lines above the header: the metadata goes to '
                        'OUT.metadata.yaml instead')
    p = verb('plot', 'a figure of any bag: pressure and length against time (setpoint, the '
             "model's prediction, the controller's target) and the loop; no ROS graph")
    p.add_argument('bag', type=Path, help='bag directory or .mcap (one still being written too)')
    p.add_argument('-o', '--output', type=_output_file, metavar='FILE.png',
                   help='PNG to write (default: BAG.png beside the bag)')
    p.add_argument('--topic', default='pma/state', help='PmaState topic (default pma/state, in '
                   'any namespace)')
    p.add_argument('--show', action='store_true',
                   help='also open it in a window (needs a display)')
    p = verb('up', "start one muscle's nodes (what bringup.launch.py starts), each logging "
             'into runs/<timestamp>/logs, wait until the driver streams, and keep them '
             'running; Ctrl-C stops them all (the driver vents)')
    from pma_cli import up
    up.add_arguments(p, _quantity('time', minimum=0.0, strict=True))
    p = verbs.add_parser('run', help='`ros2 run` without the ros2 CLI: run PACKAGE EXECUTABLE',
                         description='Start ros2_ws/install/PACKAGE/lib/PACKAGE/EXECUTABLE with '
                         'ARGS, exactly what `ros2 run PACKAGE EXECUTABLE ARGS` starts.')
    p.add_argument('package')
    p.add_argument('executable')
    p.add_argument('args', nargs=argparse.REMAINDER)
    return top


def installed_executable(package: str, executable: str) -> Path:
    """Where `ros2 run package executable` finds it: install/PKG/lib/PKG/EXE (CliError,
    USAGE, naming what the package has, if it is not there)."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        prefix = Path(get_package_prefix(package))
    except PackageNotFoundError:
        raise CliError(f'no package {package} (is the workspace sourced: . tools/env.sh?)',
                       USAGE) from None
    path = prefix / 'lib' / package / executable
    if not os.access(path, os.X_OK):
        found = sorted(p.name for p in (prefix / 'lib' / package).glob('*')
                       if os.access(p, os.X_OK))
        raise CliError(f'{package} has no executable {executable} (it has: '
                       f'{", ".join(found) or "none"})', USAGE)
    return path


def run_executable(package: str, executable: str, args: list[str]) -> int:
    """exec the installed executable, as `ros2 run` does (same process: signals go to it)."""
    try:
        path = installed_executable(package, executable)
    except CliError as error:
        print(f'pma run: {error}', file=sys.stderr)
        return error.code
    sys.stdout.flush()
    os.execv(path, [str(path), *args])
    return FAILED    # not reached


def dispatch(args, session) -> int:
    from pma_cli import calibrate, commands, goals, observe
    if args.verb == 'status':
        return observe.status(session, args.wait, listen_s=STATUS_LISTEN_S)
    if args.verb == 'watch':
        return observe.Watch(session, args.si, args.max_rate).run(args.count, args.timeout)
    if args.verb == 'set':
        return commands.set_pressure(session, args.pressure, args.wait, args.tolerance,
                                     args.timeout)
    if args.verb == 'vent':
        return commands.vent(session, args.wait, args.timeout)
    if args.verb == 'tare':
        return commands.tare(session, args.vent, args.timeout)
    if args.verb == 'sweep':
        return goals.sweep(session, args.goal, timeout_s=args.timeout)
    if args.verb == 'length':
        return commands.pressure_for_length(session, float(args.length), args.branch, args.si,
                                            args.timeout, unit=q.length_unit(args.length))
    if args.verb == 'move':
        return goals.move(session, length_m=float(args.length), tolerance_m=args.tolerance,
                          settle_s=args.settle, goal_timeout_s=args.goal_timeout,
                          timeout_s=args.timeout, unit=q.length_unit(args.length),
                          record=args.record, note=args.note, facts=args.facts)
    if args.verb == 'param':
        if args.action in ('get', 'set') and not args.name:
            raise CliError(f'pma param {args.action} needs NODE NAME'
                           + (' VALUE' if args.action == 'set' else ''), USAGE)
        if args.action == 'set' and args.value is None:
            raise CliError('pma param set needs NODE NAME VALUE', USAGE)
        return commands.param(session, args.action, args.node, args.name, args.value,
                              timeout_s=args.timeout)
    if args.verb == 'calibrate':
        return calibrate.calibrate(session, params_out=args.params_out,
                                   check_pa=args.check_pressure,
                                   skip_pressure=args.skip_pressure,
                                   skip_length=args.skip_length, bag=args.bag,
                                   assume_yes=args.yes, timeout_s=args.timeout)
    raise CliError(f'unknown verb {args.verb}', USAGE)


@closed_pipe_ends_quietly
def main(argv: list[str] | None = None) -> int:
    top = parser()
    args = top.parse_args(argv)
    if args.verb == 'run':
        return run_executable(args.package, args.executable, args.args)
    if args.verb == 'up':                 # its processes start before rclpy does
        from pma_cli import up
        return up.main(args)
    if args.verb == 'export':
        from pma_cli.export import ExportError, export_csv
        out = None if str(args.csv) == '-' else args.csv
        if out is not None and not out.parent.is_dir():
            print(f'pma export: there is no directory {out.parent} to write {out.name} in',
                  file=sys.stderr)
            return USAGE                       # before the bag is read
        try:
            summary = export_csv(args.bag, out, args.topic, comments=not args.no_comments)
        except ExportError as error:
            print(f'pma export: {error}', file=sys.stderr)
            return FAILED
        if out is not None:
            print(f'{out}: {summary.rows} rows from {summary.state_topic}, {summary.predicted} '
                  'with a prediction' + ('' if summary.prediction_topic else
                                         ' (the bag has no pma/prediction)')
                  + (f'; metadata in {summary.metadata_path}' if summary.metadata_path else ''))
        if summary.truncated:
            print(f'pma export: warning: the bag is truncated ({summary.truncated}); exported '
                  'what it holds before the damage', file=sys.stderr)
        return 0

    if args.verb == 'plot':
        from pma_cli.plot import plot
        return plot(args.bag, args.output, args.topic, args.show)

    if args.verb == 'sweep':
        from pma_cli import goals
        try:
            args.goal = goals.checked_sweep_goal(args)      # before the graph is joined
        except CliError as error:
            print(f'pma sweep: {error}', file=sys.stderr)
            return error.code
    if args.verb == 'move':
        from pma_cli import goals
        try:
            args.facts = goals.recorded_facts(args, 'move', note_needs_record=True)
        except CliError as error:
            print(f'pma move: {error}', file=sys.stderr)
            return error.code

    from pma_cli.session import Session
    from pma_common.node import ros_context
    with ros_context([]) as stop:
        verbs = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
        session = Session(args.namespace, stop, verb=args.verb, up='up' in verbs.choices)
        try:
            return dispatch(args, session)
        except CliError as error:
            print(f'pma {args.verb}: {error}', file=sys.stderr)
            return error.code
        except Interrupted:
            print(f'pma {args.verb}: interrupted', file=sys.stderr)
            return INTERRUPTED
        finally:
            session.close()

