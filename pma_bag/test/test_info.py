"""`info`'s sweep count comes from the driver's SweepRecords, never from the pressure trace.

The user guide's tester got "sweeps found: 2" for one sweep that started from 200 kPa: the
old count read the setpoint (up from 0 and back), which a sweep starting pressurised and a
manual setpoint both fool. Bags written here with BagWriter, read by `info` as a user runs it.
"""

from __future__ import annotations

import time

import pytest
from rclpy.serialization import serialize_message

from pma_bag import BagWriter
from pma_bag.info import main
from pma_interfaces.msg import PmaState, SweepRecord

pytestmark = pytest.mark.in_process

STATE = 'pma_interfaces/msg/PmaState'
RECORD = 'pma_interfaces/msg/SweepRecord'
FOREVER = {'sec': 9223372036, 'nsec': 854775807}
RELIABLE = {'history': 'keep_last', 'depth': 10, 'reliability': 'reliable',
            'durability': 'volatile', 'deadline': FOREVER, 'lifespan': FOREVER,
            'liveliness': 'automatic', 'liveliness_lease_duration': FOREVER,
            'avoid_ros_namespace_conventions': False}


def state(seq: int, setpoint_pa: float) -> bytes:
    msg = PmaState(seq=seq, gauge_pressure_pa=setpoint_pa, gauge_setpoint_pa=setpoint_pa,
                   length_m=0.3)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + seq // 20, (seq % 20) * 50_000_000
    return serialize_message(msg)


def record(sweep_id: str, kind: int, **fields) -> bytes:
    return serialize_message(SweepRecord(sweep_id=sweep_id, kind=kind, profile='staircase',
                                         **fields))


def write_bag(path, setpoints, records=None):
    t0 = time.time_ns()
    with BagWriter(path) as writer:
        writer.add_topic('/pma/state', STATE, [RELIABLE])
        if records is not None:
            writer.add_topic('/pma/sweep_record', RECORD, [RELIABLE])
        for seq, setpoint in enumerate(setpoints):
            writer.write('/pma/state', state(seq, setpoint), t0 + seq * 50_000_000)
        for index, data in enumerate(records or ()):
            writer.write('/pma/sweep_record', data, t0 + index)
    return path


def info(path, capsys) -> str:
    assert main([str(path)]) == 0
    return capsys.readouterr().out


# A sweep that starts at 200 kPa (a manual setpoint before it): up from 0 twice in the trace.
TRACE = [200e3] * 10 + [0.0] * 10 + [100e3] * 10 + [200e3] * 10 + [100e3] * 10 + [0.0] * 10


def test_one_sweep_is_one_sweep_and_its_levels_are_counted(tmp_path, capsys):
    levels = [(0.0, 0, True), (100e3, 1, True), (200e3, 1, True), (100e3, -1, False),
              (0.0, -1, True)]
    records = [record('a' * 32, SweepRecord.KIND_START, started_at_rest=True)]
    records += [record('a' * 32, SweepRecord.KIND_LEVEL, level_index=i, level_count=5,
                       target_gauge_pressure_pa=target, branch=branch, settled=settled)
                for i, (target, branch, settled) in enumerate(levels)]
    records.append(record('a' * 32, SweepRecord.KIND_END, message='succeeded: 5 steps done'))
    out = info(write_bag(tmp_path / 'one', TRACE, records), capsys)
    assert '  sweeps:         1 (1 succeeded; from /pma/sweep_record)' in out
    assert '  levels:         5 (1 at rest, 2 rising, 2 falling), 1 not settled' in out
    assert 'sweeps found' not in out


def test_how_sweeps_ended_is_counted(tmp_path, capsys):
    records = [record('a' * 32, SweepRecord.KIND_START, started_at_rest=True),
               record('a' * 32, SweepRecord.KIND_END, message='canceled: canceled; vented'),
               record('b' * 32, SweepRecord.KIND_START, started_at_rest=False),
               record('c' * 32, SweepRecord.KIND_END, message='aborted: not at rest; vented')]
    out = info(write_bag(tmp_path / 'three', TRACE, records), capsys)
    assert ('  sweeps:         3 (1 aborted, 1 canceled, 1 without an END in the bag (cut '
            'short?), 1 ended before its first level, 1 started pressurised '
            '(start_pressurised); from /pma/sweep_record)') in out
    assert 'levels:' not in out


def test_a_bag_without_records_says_so_whatever_its_trace(tmp_path, capsys):
    out = info(write_bag(tmp_path / 'none', TRACE), capsys)
    assert '  sweeps:         none recorded (no pma/sweep_record topic in the bag)' in out
    out = info(write_bag(tmp_path / 'empty', TRACE, records=[]), capsys)
    assert '  sweeps:         none recorded (/pma/sweep_record)' in out
