"""`pma set`: its flags and what it calls."""

from __future__ import annotations

from pma_cli.arguments import quantity, target

NAME = 'set'
HELP = ('command a gauge pressure (pma/pressure_setpoint) and confirm the device '
        'took it; a length controller that holds a length is released first')


def add_arguments(p) -> None:
    p.add_argument('pressure', type=target('pressure'), help='e.g. 200kPa, 2bar, 200000')
    p.add_argument('--wait', action='store_true', help='also wait until the pressure is there '
                   '(up to 30s, or --timeout if longer)')
    p.add_argument('--tolerance', type=quantity('pressure', '--tolerance', minimum=0.0,
                                                 strict=True),
                   default=10_000.0,
                   help='for --wait (default 10kPa)')


def run(args, session) -> int:
    from pma_cli import commands  # its dependencies only when it runs
    return commands.set_pressure(session, args.pressure, args.wait, args.tolerance,
                                 args.timeout)
