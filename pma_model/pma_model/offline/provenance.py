"""Where a result comes from: which run, recorded when, made when and by which software, and
the bag's custom_data (the experiment's metadata). Every refit JSON and every figure carries
it, so a PNG found on a colleague's disk still says what it shows."""

from __future__ import annotations

import datetime
import functools
import importlib.metadata
import subprocess
from collections.abc import Mapping
from pathlib import Path


@functools.cache
def software_version() -> str:
    """pma_model's package version, and the git commit when it runs from a checkout
    ('0.1.0+g1d847c0', '+...-dirty' with uncommitted changes): which code made a figure."""
    try:
        version = importlib.metadata.version('pma_model')
    except importlib.metadata.PackageNotFoundError:
        version = 'unknown'
    try:
        described = subprocess.run(
            ['git', 'describe', '--always', '--dirty', '--abbrev=10', '--exclude=*'],
            cwd=Path(__file__).resolve().parent, capture_output=True, text=True, timeout=5,
            check=False)
    except (OSError, subprocess.SubprocessError):
        return version
    commit = described.stdout.strip()
    return f'{version}+g{commit}' if described.returncode == 0 and commit else version


def utc_text(when: datetime.datetime) -> str:
    return when.astimezone(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M:%S UTC')


def run_info(*, run_id: str, source: str, recorded_ns: int | None = None,
             custom_data: Mapping[str, str] | None = None,
             made: datetime.datetime | None = None) -> dict:
    """What every figure's footer and the JSON's "run" say."""
    recorded = None if recorded_ns is None else utc_text(
        datetime.datetime.fromtimestamp(recorded_ns / 1e9, datetime.timezone.utc))
    return {'run_id': run_id, 'source': source, 'recorded': recorded,
            'date': utc_text(made or datetime.datetime.now(datetime.timezone.utc)),
            'software_version': software_version(), 'custom_data': dict(custom_data or {})}


def bag_metadata(path) -> tuple[dict[str, str] | None, int | None]:
    """(custom_data, first message time [ns]) of a bag; (None, None) for a CSV or a bag that
    cannot be read (the caller reports that when it reads the messages)."""
    path = Path(path)
    if not (path.is_dir() or path.suffix == '.mcap'):
        return None, None
    import warnings

    from pma_bag import BagError, BagReader

    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')      # a truncated bag: the reader of the data warns
            with BagReader(path) as reader:
                time_range = reader.time_range_ns()
                return reader.custom_data, time_range[0] if time_range else None
    except BagError:
        return None, None


def default_run_id(path, custom_data: Mapping[str, str] | None) -> str:
    """The bag's own run_id, else the input's name (a bag directory's, a file's stem)."""
    if custom_data and custom_data.get('run_id'):
        return custom_data['run_id']
    path = Path(path)
    return path.name if path.is_dir() else path.stem


def input_run(path, run_id: str | None = None,
              made: datetime.datetime | None = None) -> dict:
    """run_info of an input file or bag (run_id: given, else default_run_id). `made`: the
    run's one date, when several inputs' figures must say the same."""
    custom_data, recorded_ns = bag_metadata(path)
    return run_info(run_id=run_id or default_run_id(path, custom_data), source=str(path),
                    recorded_ns=recorded_ns, custom_data=custom_data, made=made)
