"""`pma export BAG --csv OUT`: a bag as CSV, read from the files (no ROS graph)."""

from __future__ import annotations

import sys
from pathlib import Path

from pma_cli.arguments import output_file
from pma_cli.session import FAILED, USAGE
from pma_common import names

NAME = 'export'
HELP = 'a bag as CSV: one row per pma/state with its prediction, SI columns'
OFFLINE = True


def add_arguments(p) -> None:
    p.add_argument('bag', type=Path, help='bag directory or .mcap')
    p.add_argument('--csv', type=output_file, required=True,
                   metavar='OUT', help="CSV file to write, in a directory that exists ('-' = "
                   'standard output)')
    p.add_argument('--topic', default=names.STATE, help='PmaState topic (default pma/state, in '
                   'any namespace)')
    p.add_argument('--no-comments', action='store_true',
                   help='no # metadata lines above the header: the metadata goes to '
                        'OUT.metadata.yaml instead')


def run(args) -> int:
    from pma_cli.export import ExportError, export_csv
    out = None if str(args.csv) == '-' else args.csv
    if out is not None and not out.parent.is_dir():
        print(f'pma export: there is no directory {out.parent} to write {out.name} in',
              file=sys.stderr)
        return USAGE                       # before the bag is read
    try:
        summary = export_csv(args.bag, out, args.topic, comments=not args.no_comments)
    except ExportError as error:
        print(f'pma export: {error}', file=sys.stderr)
        return FAILED
    if out is not None:
        print(f'{out}: {summary.rows} rows from {summary.state_topic}, {summary.predicted} '
              'with a prediction' + ('' if summary.prediction_topic else
                                     ' (the bag has no pma/prediction)')
              + (f'; metadata in {summary.metadata_path}' if summary.metadata_path else ''))
    if summary.truncated:
        print(f'pma export: warning: the bag is truncated ({summary.truncated}); exported '
              'what it holds before the damage', file=sys.stderr)
    return 0
