"""`pma`'s verbs, one module each, in the order `pma --help` lists them.

A verb module has NAME, HELP, `add_arguments(parser)` and `run(args, session)` (the session:
a hidden node in the command's namespace), or `run(args)` with OFFLINE = True for a verb that
needs no ROS graph (or starts its own). Optional: `check(args)`, run before the graph is
joined (a goal refused at once), EPILOG, DESCRIPTION, COMMON_FLAGS = False (no --namespace
or --timeout). Adding a verb: one module here and its name in VERBS (docs/development.md).
"""

from __future__ import annotations

import importlib
from types import ModuleType

VERBS = ('status', 'watch', 'set', 'vent', 'tare', 'sweep', 'length', 'move', 'param',
         'calibrate', 'export', 'plot', 'up', 'run')


def verb_module(name: str) -> ModuleType:
    return importlib.import_module(f'{__name__}.{name}')
