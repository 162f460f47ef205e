"""`pma length`: its flags and what it calls."""

from __future__ import annotations

from pma_cli import quantities as q
from pma_cli.arguments import target

NAME = 'length'
HELP = 'which pressure gives this length? (the inverse model service)'


def add_arguments(p) -> None:
    p.add_argument('length', type=target('length'), help='e.g. 26.5cm, 0.265')
    p.add_argument('--branch', choices=('auto', 'inc', 'dec', 'increasing', 'decreasing'),
                   default='auto', help='inc/dec: that major branch; auto (default): from the '
                   'current state along the path the muscle will follow')
    p.add_argument('--si', action='store_true', help='print only the pressure in Pa')


def run(args, session) -> int:
    from pma_cli import commands  # its dependencies only when it runs
    return commands.pressure_for_length(session, float(args.length), args.branch, args.si,
                                        args.timeout, unit=q.length_unit(args.length))
