"""`pma tare`: its flags and what it calls."""

from __future__ import annotations

NAME = 'tare'
HELP = "zero the pressure reading at rest (the driver's ~/tare)"


def add_arguments(p) -> None:
    p.add_argument('--vent', action='store_true',
                   help='vent first and wait until the pressure is steady')


def run(args, session) -> int:
    from pma_cli import commands  # its dependencies only when it runs
    return commands.tare(session, args.vent, args.timeout)
