"""`pma move`: its flags and what it calls."""

from __future__ import annotations

from pma_cli import quantities as q
from pma_cli.arguments import quantity, target
from pma_common import experiment

NAME = 'move'
HELP = ('move to a length and hold it (the length controller\'s MoveToLength); '
        'Ctrl-C cancels')


def add_arguments(p) -> None:
    p.add_argument('length', type=target('length'), help='e.g. 26.5cm')
    p.add_argument('--tolerance', type=quantity('length', '--tolerance'), default=0.0,
                   help='settled within this (default: the action\'s 2mm)')
    p.add_argument('--settle', type=quantity('time'), default=0.0,
                   help='for this long (default: the action\'s 1s)')
    p.add_argument('--goal-timeout', type=quantity('time'), default=0.0,
                   help='abort if not settled by then (default: the action\'s 30s)')
    p.add_argument('--record', nargs='?', const='', metavar='BAG',
                   help='record the move to its own bag (a relative path is taken from here; '
                        'no path = auto-named); needs a recorder: pma run pma_bag record --idle')
    p.add_argument('--note', default='', help="operator's note for the bag's metadata")
    experiment.add_arguments(p)


def check(args) -> None:
    """The experiment's facts, refused before the graph is joined if they cannot be stored."""
    from pma_cli import goals  # its dependencies only when it runs
    args.facts = goals.recorded_facts(args, 'move', note_needs_record=True)


def run(args, session) -> int:
    from pma_cli import goals  # its dependencies only when it runs
    return goals.move(session, length_m=float(args.length), tolerance_m=args.tolerance,
                      settle_s=args.settle, goal_timeout_s=args.goal_timeout,
                      timeout_s=args.timeout, unit=q.length_unit(args.length),
                      record=args.record, note=args.note, facts=args.facts)
