"""Refit of a one-hour 100 Hz bag (360,000 PmaState samples), against reading the same bag.

Target: the whole refit (read, decode, split, steady-state, five models, hold-out) under 15 s
on one core. The baseline is iterating the bag's raw messages with BagReader in the same run,
so the ratio is comparable between machines; decoding is timed on its own as well.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import sys
import tempfile
import time
from pathlib import Path

# "On one core": pinned before numpy starts its BLAS threads, which inherit the affinity.
ONE_CORE = min(os.sched_getaffinity(0))
os.sched_setaffinity(0, {ONE_CORE})
for _name in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_name] = '1'

import numpy as np  # noqa: E402

RATE_HZ = 100.0
DURATION_S = 3600.0
HOLD_S = 10.0
TARGET_S = 15.0


def write_bag(path: Path) -> int:
    from rclpy.serialization import serialize_message

    from pma_bag import BagWriter
    from pma_interfaces.msg import PmaState
    from pma_model.params import default_params

    increasing, decreasing = default_params().branches()
    rng = np.random.default_rng(0)
    levels = np.arange(0, 500_001, 50_000.0)
    cycle = np.concatenate([levels, levels[-2:0:-1]])
    count = int(DURATION_S * RATE_HZ)
    per_hold = int(HOLD_S * RATE_HZ)
    setpoint = np.resize(np.repeat(cycle, per_hold), count)
    alpha = 1 - math.exp(-1 / (RATE_HZ * 0.3))
    pressure = np.empty(count)
    value = 0.0
    for i in range(count):
        value += (setpoint[i] - value) * alpha
        pressure[i] = value
    rising = np.r_[True, np.diff(setpoint) >= 0]
    last = True
    for i in range(count):  # the branch of the last setpoint change
        if setpoint[i] != setpoint[i - 1] if i else False:
            last = setpoint[i] > setpoint[i - 1]
        rising[i] = last
    length = np.where(rising, increasing.length(pressure), decreasing.length(pressure))
    length += rng.normal(0, 2e-4, count)
    length[rng.random(count) < 0.001] = np.nan
    noisy_pressure = pressure + rng.normal(0, 300.0, count)
    message = PmaState()
    message.header.frame_id = 'pma'
    start_ns = 1_700_000_000 * 10**9
    with BagWriter(path) as writer:
        writer.add_topic('/pma/state', 'pma_interfaces/msg/PmaState')
        for i in range(count):
            stamp = start_ns + i * 10_000_000
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10**9)
            message.seq = i
            message.gauge_pressure_pa = float(noisy_pressure[i])
            message.gauge_setpoint_pa = float(setpoint[i])
            message.length_m = float(length[i])
            writer.write('/pma/state', serialize_message(message), stamp + 1_000_000)
    return count


def time_it(function):
    started = time.perf_counter()
    result = function()
    return time.perf_counter() - started, result


def main() -> int:
    from pma_bag import BagReader
    from pma_model.offline import refit
    from pma_model.offline.samples import read_bag

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / 'hour'
        write_s, count = time_it(lambda: write_bag(bag))

        def read_raw():
            with BagReader(bag) as reader:
                return sum(1 for _ in reader.messages(['/pma/state']))

        read_s, seen = time_it(read_raw)
        assert seen == count
        decode_s, samples = time_it(lambda: read_bag(bag, progress=False))
        quiet = io.StringIO()
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(io.StringIO()):
            refit_s, code = time_it(lambda: refit.main([str(bag), '--json',
                                                        str(Path(tmp) / 'r.json')]))
        if code != 0:
            print(quiet.getvalue())
            return 1
    print(f'bag: {count} PmaState samples ({DURATION_S / 3600:.0f} h at {RATE_HZ:.0f} Hz), '
          f'written in {write_s:.1f} s (not part of the refit)')
    print(f'{"step":<42}{"s":>8}{"x raw read":>12}')
    for label, seconds in (('baseline: BagReader raw iteration', read_s),
                           ('read + rclpy decode + NaN drop (samples)', decode_s),
                           ('full refit (5 models, hold-out, JSON)', refit_s)):
        print(f'{label:<42}{seconds:8.2f}{seconds / read_s:12.1f}')
    print(f'samples kept: {samples.pressure_pa.size} (dropped NaN lengths: '
          f'{samples.dropped_nan})')
    verdict = 'PASS' if refit_s < TARGET_S else 'FAIL'
    print(f'target: full refit < {TARGET_S:.0f} s on one core (CPU {ONE_CORE}): {verdict} '
          f'({refit_s:.1f} s)')
    return 0 if refit_s < TARGET_S else 1


if __name__ == '__main__':
    sys.exit(main())
