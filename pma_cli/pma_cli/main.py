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
import sys

from pma_cli.arguments import Parser, common_parser
from pma_cli.session import INTERRUPTED, CliError, Interrupted
from pma_cli.verbs import VERBS, verb_module
from pma_common.console import closed_pipe_ends_quietly


def parser() -> argparse.ArgumentParser:
    """`pma` and every verb of the registry (pma_cli.verbs) with its flags."""
    common = common_parser()
    top = Parser(
        prog='pma', description='The PMA rig from a shell: status, setpoints, sweeps, the '
        'inverse model, parameters, calibration and CSV export. Quantities: 200kPa, 2bar, '
        '26.5cm, 5s; a plain number is SI (Pa, m, s).',
        epilog='exit codes: 0 done, 1 refused or failed, 2 bad arguments, 3 nothing answered, '
               '130 interrupted. docs/cli.md has the details and the ros2 equivalents.')
    top.joins_units = True
    verbs = top.add_subparsers(dest='verb', required=True, metavar='VERB')
    for name in VERBS:
        verb = verb_module(name)
        flags = [common] if getattr(verb, 'COMMON_FLAGS', True) else []
        p = verbs.add_parser(name, help=verb.HELP,
                             description=getattr(verb, 'DESCRIPTION', verb.HELP),
                             epilog=getattr(verb, 'EPILOG', None), parents=flags)
        verb.add_arguments(p)
    return top


@closed_pipe_ends_quietly
def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    verb = verb_module(args.verb)
    if getattr(verb, 'OFFLINE', False):
        return verb.run(args)
    if hasattr(verb, 'check'):
        try:
            verb.check(args)                      # before the graph is joined
        except CliError as error:
            print(f'pma {args.verb}: {error}', file=sys.stderr)
            return error.code

    from pma_cli.session import Session
    from pma_common.node import ros_context
    with ros_context([]) as stop:
        session = Session(args.namespace, stop, verb=args.verb, up='up' in VERBS)
        try:
            return verb.run(args, session)
        except CliError as error:
            print(f'pma {args.verb}: {error}', file=sys.stderr)
            return error.code
        except Interrupted:
            print(f'pma {args.verb}: interrupted', file=sys.stderr)
            return INTERRUPTED
        finally:
            session.close()
