"""`pma calibrate`: its flags and what it calls."""

from __future__ import annotations

from pathlib import Path

from pma_cli.arguments import output_file, quantity

NAME = 'calibrate'
HELP = ('guided calibration: pressure zero and span against a reference '
        'gauge, length offset from a tape measurement; writes a driver params file')


def add_arguments(p) -> None:
    p.add_argument('-o', '--params-out', type=output_file,
                   default=Path('pma_calibration.yaml'),
                   help='params file to write (default pma_calibration.yaml)')
    p.add_argument('--check-pressure', type=quantity('pressure', '--check-pressure'),
                   default=None,
                   help='span check pressure (default 60 %% of max_gauge_pressure_pa)')
    p.add_argument('--skip-pressure', action='store_true', help='no tare, no span check')
    p.add_argument('--skip-length', action='store_true', help='no length offset')
    p.add_argument('--bag', type=Path, help='also record the calibration run to this bag, '
                   'with the result in its metadata')
    p.add_argument('-y', '--yes', action='store_true', help='do not ask for confirmations '
                   '(the gauge and tape readings are still asked)')


def run(args, session) -> int:
    from pma_cli import calibrate  # its dependencies only when it runs
    return calibrate.calibrate(session, params_out=args.params_out,
                               check_pa=args.check_pressure,
                               skip_pressure=args.skip_pressure,
                               skip_length=args.skip_length, bag=args.bag,
                               assume_yes=args.yes, timeout_s=args.timeout)
