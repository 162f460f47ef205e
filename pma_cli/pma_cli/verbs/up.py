"""`pma up`: one muscle's nodes, what bringup.launch.py starts (pma_cli.up runs them)."""

from __future__ import annotations

from pathlib import Path

from pma_bringup.node_set import LIVE_HOST, LIVE_PORT
from pma_cli.arguments import quantity
from pma_common import experiment

NAME = 'up'
HELP = ("start one muscle's nodes (what bringup.launch.py starts), each logging "
        'into runs/<timestamp>/logs, wait until the driver streams, and keep them '
        'running; Ctrl-C stops them all (the driver vents)')
OFFLINE = True            # it starts the nodes before rclpy is initialised
READY_TIMEOUT_S = 30.0


def add_arguments(p) -> None:
    p.add_argument('--port', default='', help='serial port of the rig, e.g. /dev/pma0 (default '
                   '/dev/ttyACM0); with --simulated the path of the simulated device (default '
                   '/tmp/pma_<namespace>, /tmp/pma_muscle)')
    p.add_argument('--simulated', action='store_true',
                   help='also start fake_arduino, a simulated rig on a pty at --port')
    p.add_argument('--seed', default='0', help='--simulated: seed of the sensor noise')
    p.add_argument('--no-driver', action='store_true', help='no driver_node (nor fake_arduino): '
                   'the rig computer runs it (docs/lab-network.md)')
    p.add_argument('--no-model', action='store_true', help='no model_node')
    p.add_argument('--no-control', action='store_true', help='no length controller')
    p.add_argument('--record', nargs='?', const='', default=None, metavar='DIR',
                   help='also run the recorder into this bag (no DIR: '
                        'pma_bag_[<namespace>_]<date-time> here)')
    p.add_argument('--live', action='store_true', help='also run foxglove_live, the live view '
                   f'(ws://{LIVE_HOST}:{LIVE_PORT}; docs/live-view.md)')
    p.add_argument('--live-host', default=LIVE_HOST, help='address the live view listens on '
                   f'(default {LIVE_HOST}: this machine only; 0.0.0.0: the lab network too)')
    p.add_argument('--live-port', type=int, default=LIVE_PORT,
                   help=f'TCP port of the live view (default {LIVE_PORT})')
    for option, node in (('driver', 'driver_node'), ('model', 'model_node'),
                         ('control', 'length_controller'), ('recorder', 'the recorder')):
        p.add_argument(f'--{option}-params', type=Path, metavar='FILE',
                       help=f'{node} parameters file (default: its package\'s config/)')
    p.add_argument('--refit-params', type=Path, metavar='FILE',
                   help='a refit --params-out file for model_node (hot-reloaded)')
    experiment.add_arguments(p)
    p.add_argument('--note', default='', help='with --record: a free note for every bag')
    p.add_argument('--runs-dir', type=Path, default=Path('runs'),
                   help='where the run directory with the logs goes (default ./runs)')
    p.add_argument('--wait', type=quantity('time', minimum=0.0, strict=True),
                   default=READY_TIMEOUT_S, metavar='TIME',
                   help=f'how long the rig may take to come up (default {READY_TIMEOUT_S:g}s)')


def run(args) -> int:
    from pma_cli import up
    return up.main(args)
