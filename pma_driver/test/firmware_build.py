"""Build the firmware image and its simulator (tools/firmware.sh) for the tests.

The tests build from the sources into their own directory, once per session, rather than
trust whatever `make firmware` left in build/: a test of the firmware tests this checkout.
The cross-package tests (tests/) use this module too, through tests/support/firmware.py.
"""

from __future__ import annotations

import atexit
import dataclasses
import functools
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / 'tools' / 'firmware.sh'
FIRMWARE_DIR = ROOT / 'pma_driver' / 'firmware'


# The deliberately broken firmware the tests must catch, a bug the host build cannot show:
# the reference as a plain `int` (16 bits on the AVR, 32 on a PC), multiplied by the ADC
# count without widening it first, so every reading wraps to about -60 kPa.
SIXTEEN_BIT_OVERFLOW = {
    'const int32_t ADC_REFERENCE_MV = 5000;': 'const int ADC_REFERENCE_MV = 5000;',
    'const int32_t scaledMv = (int32_t)adc * ADC_REFERENCE_MV - ':
        'const int32_t scaledMv = adc * ADC_REFERENCE_MV - ',
}


def script_exit_code(name: str) -> int:
    match = re.search(rf'^{name}=(\d+)$', SCRIPT.read_text(), re.M)
    assert match, f'{name} not set in {SCRIPT}'
    return int(match.group(1))


EXIT_NO_TOOLCHAIN = script_exit_code('EXIT_NO_TOOLCHAIN')
EXIT_NO_SIMULATOR = script_exit_code('EXIT_NO_SIMULATOR')


@dataclasses.dataclass(frozen=True)
class FirmwareBuild:
    build_dir: Path
    result: subprocess.CompletedProcess

    @property
    def output(self) -> str:
        return self.result.stdout + self.result.stderr

    @property
    def elf(self) -> Path:
        return self.build_dir / 'pma_firmware.elf'

    @property
    def simulator(self) -> Path:
        return self.build_dir / 'simavr' / 'pma_simavr'

    def simavr_args(self) -> tuple[str, ...]:
        """simavr_arduino's options that run this build."""
        return '--firmware', str(self.elf), '--simulator', str(self.simulator)


def run_firmware_script(build_dir: Path, firmware_dir: Path | None = None) -> FirmwareBuild:
    """tools/firmware.sh into build_dir (a copy of the sources in firmware_dir, if given)."""
    env = dict(os.environ, PMA_FIRMWARE_BUILD_DIR=str(build_dir))
    if firmware_dir is not None:
        env['PMA_FIRMWARE_DIR'] = str(firmware_dir)
    # The first run may install the toolchain and simavr with apt-get (about half a minute).
    result = subprocess.run(['bash', str(SCRIPT)], env=env, capture_output=True, text=True,
                            timeout=300, check=False)
    return FirmwareBuild(Path(build_dir), result)


def _last_line(build: FirmwareBuild) -> str:
    return (build.result.stdout.strip().splitlines() or [''])[-1]


def require_image(build: FirmwareBuild) -> FirmwareBuild:
    """The build; skips, saying why, when the AVR toolchain cannot be installed here."""
    if build.result.returncode == EXIT_NO_TOOLCHAIN:
        pytest.skip(f'AVR toolchain absent and not installable here: {_last_line(build)}')
    return build


def require_simulator(build: FirmwareBuild) -> FirmwareBuild:
    """The build with its simulator; skips, saying why, when simavr cannot be installed."""
    require_image(build)
    if build.result.returncode == EXIT_NO_SIMULATOR:
        pytest.skip('simavr absent and not installable here, so the firmware image cannot '
                    f'run: {_last_line(build)}')
    assert build.result.returncode == 0, build.output
    assert build.elf.is_file() and build.simulator.is_file(), build.output
    return build


@functools.cache
def session_build() -> FirmwareBuild:
    """This checkout's image and simulator, built once per test session (check with require_*)."""
    build_dir = Path(tempfile.mkdtemp(prefix='pma-firmware-'))
    atexit.register(shutil.rmtree, build_dir, ignore_errors=True)
    return run_firmware_script(build_dir)


def mutated_firmware(tmp_path: Path, replacements: dict[str, str]) -> Path:
    """A copy of the firmware sources with each `old` text of the sketch replaced once."""
    copy = tmp_path / 'firmware'
    shutil.copytree(FIRMWARE_DIR, copy)
    sketch = copy / 'pma_firmware' / 'pma_firmware.ino'
    text = sketch.read_text()
    for old, new in replacements.items():
        assert text.count(old) == 1, f'{old!r} is not in the sketch exactly once'
        text = text.replace(old, new)
    sketch.write_text(text)
    return copy
