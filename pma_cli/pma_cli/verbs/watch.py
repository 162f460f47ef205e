"""`pma watch`: its flags and what it calls."""

from __future__ import annotations

from pma_cli import quantities as q
from pma_cli.arguments import argument, quantity

NAME = 'watch'
HELP = ('one line per sample: pressure, setpoint, length, the model\'s prediction '
        '(Ctrl-C ends it)')


def add_arguments(p) -> None:
    p.add_argument('--count', type=argument(q.parse_count, 'count'), default=0,
                   help='stop after this many lines (default 0: until Ctrl-C)')
    p.add_argument('--max-rate', type=quantity('frequency', minimum=0.0), default=20.0,
                   metavar='HZ', help='at most about this many lines a second; a stream at '
                   'that rate shows every sample (default 20; 0 = no limit)')
    p.add_argument('--si', action='store_true', help='columns in Pa and m instead of kPa and cm')


def run(args, session) -> int:
    from pma_cli import observe  # its dependencies only when it runs
    return observe.Watch(session, args.si, args.max_rate).run(args.count, args.timeout)
