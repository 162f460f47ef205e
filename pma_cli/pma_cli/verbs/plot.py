"""`pma plot BAG`: a figure of any bag, read from the files (no ROS graph)."""

from __future__ import annotations

from pathlib import Path

from pma_cli.arguments import output_file
from pma_common import names

NAME = 'plot'
HELP = ('a figure of any bag: pressure and length against time (setpoint, the '
        "model's prediction, the controller's target) and the loop; no ROS graph")
OFFLINE = True


def add_arguments(p) -> None:
    p.add_argument('bag', type=Path, help='bag directory or .mcap (one still being written too)')
    p.add_argument('-o', '--output', type=output_file, metavar='FILE.png',
                   help='PNG to write (default: BAG.png beside the bag)')
    p.add_argument('--topic', default=names.STATE, help='PmaState topic (default pma/state, in '
                   'any namespace)')
    p.add_argument('--show', action='store_true',
                   help='also open it in a window (needs a display)')


def run(args) -> int:
    from pma_cli.plot import plot  # matplotlib only when it runs
    return plot(args.bag, args.output, args.topic, args.show)
