"""`pma sweep`: its flags and what it calls."""

from __future__ import annotations

from pathlib import Path

from pma_cli.arguments import field_count, quantities, quantity, rate
from pma_common import experiment
from pma_common.sweep import FORC_FAMILIES, PROFILES
from pma_interfaces.action import Sweep

NAME = 'sweep'
HELP = ('run a pressure profile (the Sweep action: a staircase by default) with a '
        'progress bar (a length controller that holds a length is released first); '
        'Ctrl-C cancels it and the driver vents')
EPILOG = ('profiles and their flags: staircase --max --step [--hold] [--reversals]; '
          'forc --max --step --forc-count [--forc-family] [--hold]; ramp --max --rate '
          '[--reversals] [--hold]; sine --amplitude --offset --frequency [--max]; csv --csv '
          '[--max]. All take --cycles and --rest. A flag the profile does not use is refused '
          'by the driver, with the reason.')


def add_arguments(p) -> None:
    p.add_argument('--profile', choices=PROFILES, default='staircase',
                   help='the path of the pressure (default staircase)')
    p.add_argument('--max', type=quantity('pressure', '--max'), default=0.0, dest='max_pa',
                   metavar='PRESSURE', help='top of a staircase, FORC set or ramp, e.g. 500kPa; '
                   'sine, csv: an optional bound')
    p.add_argument('--step', type=quantity('pressure', '--step'), default=0.0, dest='step_pa',
                   metavar='PRESSURE', help='staircase, forc: step height, e.g. 50kPa')
    p.add_argument('--hold', type=quantity('time'), default=None, dest='hold_s',
                   metavar='TIME', help='staircase, forc: hold at each step (default 5s); '
                   'ramp: at each turning point (default 0)')
    p.add_argument('--cycles', type=field_count(Sweep.Goal, 'cycles', 1), default=1,
                   help='repetitions of the whole profile; sine: periods (default 1)')
    p.add_argument('--rest', type=quantity('time'), default=0.0, dest='rest_s',
                   metavar='TIME', help='rest at 0 Pa between cycles (default none)')
    p.add_argument('--reversals', type=quantities('pressure', '--reversals'), default=[],
                   help='staircase, ramp: minor loops, turn at these pressures, e.g. '
                        '300kPa,150kPa')
    p.add_argument('--rate', type=rate('pressure', '--rate'), default=0.0, dest='rate_pa_s',
                   metavar='RATE', help='ramp: rise and fall rate, e.g. 50kPa/s')
    p.add_argument('--amplitude', type=quantity('pressure', '--amplitude'), default=0.0,
                   dest='amplitude_pa', metavar='PRESSURE', help='sine: amplitude, e.g. 100kPa')
    p.add_argument('--offset', type=quantity('pressure', '--offset'), default=0.0,
                   dest='offset_pa',
                   metavar='PRESSURE', help='sine: mean pressure, e.g. 200kPa')
    p.add_argument('--frequency', type=quantity('frequency'), default=0.0,
                   dest='frequency_hz', metavar='FREQUENCY', help='sine: e.g. 0.1Hz')
    p.add_argument('--csv', type=Path, dest='profile_csv', metavar='FILE',
                   help='csv: a file with columns time_s,gauge_pressure_pa (SI; a sample log '
                        'replays as a profile)')
    p.add_argument('--forc-count', type=field_count(Sweep.Goal, 'forc_count', 1), default=0,
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


def check(args) -> None:
    """The goal, refused before the graph is joined if the driver would refuse it."""
    from pma_cli import goals  # its dependencies only when it runs
    args.goal = goals.checked_sweep_goal(args)


def run(args, session) -> int:
    from pma_cli import goals  # its dependencies only when it runs
    return goals.sweep(session, args.goal, timeout_s=args.timeout)
