"""`pma vent`: its flags and what it calls."""

from __future__ import annotations

NAME = 'vent'
HELP = 'cancel any sweep or move and command 0 Pa'


def add_arguments(p) -> None:
    p.add_argument('--wait', action='store_true', help='wait until the pressure is near 0')


def run(args, session) -> int:
    from pma_cli import commands  # its dependencies only when it runs
    return commands.vent(session, args.wait, args.timeout)
