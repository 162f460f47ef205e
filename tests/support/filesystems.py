"""A real, small filesystem for disk-full tests: a tmpfs mounted for the test (needs root).

/dev/full fails every write at once; a full disk fails in the middle of a record, after some
data reached it, which is the case the recorder has to survive. Where mounting is not allowed
the test is skipped and says why, rather than faked.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest


@contextmanager
def small_filesystem(path: Path, size_bytes: int) -> Iterator[Path]:
    """Mount a tmpfs of `size_bytes` (rounded up to pages) at `path` for the block."""
    path.mkdir(parents=True, exist_ok=True)
    mount = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size_bytes},mode=0777',
                            'pma_test_small_fs', str(path)], check=False, capture_output=True,
                           text=True)
    if mount.returncode != 0:
        pytest.skip(f'cannot mount a small tmpfs for the disk-full test: '
                    f'{mount.stderr.strip() or mount.returncode} (needs root)')
    try:
        yield path
    finally:
        subprocess.run(['umount', '--lazy', str(path)], check=False)
