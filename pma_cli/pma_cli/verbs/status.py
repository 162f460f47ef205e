"""`pma status`: its flags and what it calls."""

from __future__ import annotations

from pma_cli.arguments import quantity

# `pma status` listens at most this long for every node's diagnostics (usually ~4 s:
# observe.MIN_LISTEN_S).
LISTEN_S = 8.0

NAME = 'status'
HELP = ('link, rate, pressure, length, model and controller, from /diagnostics '
        'and the topics; exit 0 when the driver streams without an error')


def add_arguments(p) -> None:
    p.add_argument('--wait', type=quantity('time', minimum=0.0), nargs='?', const=30.0,
                   default=0.0,
                   metavar='TIME', help='first wait until the driver streams (default 30s)')


def run(args, session) -> int:
    from pma_cli import observe  # its dependencies only when it runs
    return observe.status(session, args.wait, listen_s=LISTEN_S)
