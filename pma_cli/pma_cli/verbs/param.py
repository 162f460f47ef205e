"""`pma param`: its flags and what it calls."""

from __future__ import annotations

from pma_cli.arguments import check_node, rcl_name
from pma_cli.session import USAGE, CliError

NAME = 'param'
HELP = "get, set or list a node's parameters (what `ros2 param` does)"


def add_arguments(p) -> None:
    p.add_argument('action', choices=('get', 'set', 'list'))
    p.add_argument('node', type=rcl_name('ROS node name', check_node),
                   help='driver_node, model_node, length_controller, recorder, ... '
                   '(relative to --namespace, or absolute)')
    p.add_argument('name', nargs='?', help='parameter name (get, set)')
    p.add_argument('value', nargs='?', help='new value (set); units where the name has one: '
                   'max_gauge_pressure_pa 450kPa')


def run(args, session) -> int:
    from pma_cli import commands  # its dependencies only when it runs
    if args.action in ('get', 'set') and not args.name:
        raise CliError(f'pma param {args.action} needs NODE NAME'
                       + (' VALUE' if args.action == 'set' else ''), USAGE)
    if args.action == 'set' and args.value is None:
        raise CliError('pma param set needs NODE NAME VALUE', USAGE)
    return commands.param(session, args.action, args.node, args.name, args.value,
                          timeout_s=args.timeout)
