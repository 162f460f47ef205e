"""pma_driver's firmware build helper (pma_driver/test/firmware_build.py) for tests here.

One module for both, so a session builds the image and its simulator once.
"""

import sys

from support.procs import ROOT

_PACKAGE_TESTS = str(ROOT / 'pma_driver' / 'test')
if _PACKAGE_TESTS not in sys.path:
    sys.path.append(_PACKAGE_TESTS)

from firmware_build import (  # noqa: E402
    SIXTEEN_BIT_OVERFLOW,
    FirmwareBuild,
    mutated_firmware,
    require_simulator,
    run_firmware_script,
    session_build,
)

__all__ = ['SIXTEEN_BIT_OVERFLOW', 'FirmwareBuild', 'mutated_firmware', 'require_simulator',
           'run_firmware_script', 'session_build']
