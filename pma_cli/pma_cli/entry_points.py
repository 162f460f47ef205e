"""`pma` (installed in lib/pma_cli; `. tools/env.sh` puts it on PATH): stops cleanly on signals."""

from pma_common.stop import entry_point

pma = entry_point('pma_cli.main:main')
