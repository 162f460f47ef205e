"""Samples from real files: a synthetic sweep bag, CSV logs, the branch table; holds and labels."""

import math

import numpy as np
import pytest

from pma_model import units
from pma_model.branches import SigmoidBranch
from pma_model.detector import BRANCH_INCREASING, detect_branches
from pma_model.offline.samples import (
    Samples,
    SamplesError,
    hold_runs,
    load_branch_data,
    read_bag,
    read_branch_table,
    read_sample_log,
    split_branches,
)

TRUE_INCREASING = SigmoidBranch(0.3006, 0.19, 1.13e-5, 6.214)
TRUE_DECREASING = SigmoidBranch(0.3006, 0.188, 1.30e-5, 6.214)
TABLE = units.kpa_to_pa(np.arange(0, 501, 50))


def staircase(rate_hz=20.0, hold_s=2.0, noise_m=2e-4, nan_every=0, seed=1):
    """(t, pressure, setpoint, length) of a 0 -> 500 -> 0 kPa staircase through a known loop."""
    rng = np.random.default_rng(seed)
    levels = np.concatenate([TABLE, TABLE[-2::-1]])
    per_hold = int(hold_s * rate_hz)
    setpoint = np.repeat(levels, per_hold)
    t = np.arange(setpoint.size) / rate_hz
    pressure = np.empty_like(setpoint)
    value = 0.0
    for i, target in enumerate(setpoint):  # first-order regulation, tau = 0.15 s
        value += (target - value) * (1 - math.exp(-1 / (rate_hz * 0.15)))
        pressure[i] = value
    rising = detect_branches(pressure, 20_000.0) == BRANCH_INCREASING
    length = np.where(rising, TRUE_INCREASING.length(pressure), TRUE_DECREASING.length(pressure))
    length = length + rng.normal(0, noise_m, length.size)
    if nan_every:
        length[::nan_every] = np.nan
    return t, pressure, setpoint, length


def write_state_bag(path, t, pressure, setpoint, length, *, start_s=1_700_000_000.0,
                    topics=('/pma/state',), custom_data=None):
    """A rosbag2 MCAP bag of PmaState on /pma/state (or these topics), stamped start_s + t,
    with the experiment's custom_data (as the Sweep action writes it)."""
    from rclpy.serialization import serialize_message

    from pma_bag import BagWriter
    from pma_interfaces.msg import PmaState

    with BagWriter(path, custom_data=custom_data) as writer:
        for topic in topics:
            writer.add_topic(topic, 'pma_interfaces/msg/PmaState')
        message = PmaState()
        message.header.frame_id = 'pma'
        for i in range(t.size):
            stamp_ns = round((start_s + t[i]) * 1e9)
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
            message.seq = i
            message.gauge_pressure_pa = float(pressure[i])
            message.gauge_setpoint_pa = float(setpoint[i])
            message.length_m = float(length[i])
            for topic in topics:
                writer.write(topic, serialize_message(message), stamp_ns + 2_000_000)
    return path


def write_sample_log(path, t, pressure, length, setpoint=None):
    columns = ['time_s', 'gauge_pressure_pa', 'length_m']
    rows = [t, pressure, length]
    if setpoint is not None:
        columns.append('gauge_setpoint_pa')
        rows.append(setpoint)
    with open(path, 'w') as stream:
        stream.write(','.join(columns) + '\n')
        for values in zip(*rows, strict=True):
            stream.write(','.join(repr(float(v)) for v in values) + '\n')
    return path


def test_bag_samples_by_header_stamp_with_nan_dropped(tmp_path):
    t, pressure, setpoint, length = staircase(nan_every=7)
    bag = write_state_bag(tmp_path / 'sweep', t, pressure, setpoint, length)
    samples = read_bag(bag, progress=False)
    expected_nan = int(np.isnan(length).sum())
    assert samples.dropped_nan == expected_nan > 0
    assert samples.pressure_pa.size == t.size - expected_nan
    keep = ~np.isnan(length)
    assert samples.time_s == pytest.approx(t[keep], abs=1e-6)  # header.stamp, not log time
    assert samples.length_m == pytest.approx(length[keep])
    assert samples.setpoint_pa == pytest.approx(setpoint[keep])
    bare = read_bag(bag / 'sweep_0.mcap', progress=False)
    assert bare.pressure_pa.size == samples.pressure_pa.size


def test_namespaced_bags_are_found_and_two_muscles_need_a_choice(tmp_path):
    t, pressure, setpoint, length = staircase()
    one = write_state_bag(tmp_path / 'one', t, pressure, setpoint, length,
                          topics=('/rig1/pma/state',))
    assert read_bag(one, progress=False).pressure_pa.size == t.size
    two = write_state_bag(tmp_path / 'two', t, pressure, setpoint, length,
                          topics=('/left/pma/state', '/right/pma/state'))
    with pytest.raises(SamplesError, match=r'several pma/state topics.*--topic'):
        read_bag(two, progress=False)
    assert read_bag(two, '/right/pma/state', progress=False).pressure_pa.size == t.size
    with pytest.raises(SamplesError, match='no /pma/state topic'):
        read_bag(two, '/pma/state', progress=False)


def test_steady_state_reduction_recovers_the_table(tmp_path):
    t, pressure, setpoint, length = staircase(noise_m=0.0)
    data = split_branches(Samples(t, pressure, length, setpoint), 20_000.0, steady_state=True)
    assert data.steady_state
    assert data.inc_pressure_pa == pytest.approx(TABLE, abs=20.0)  # 0..500 incl. the top hold
    assert data.dec_pressure_pa == pytest.approx(TABLE[-2::-1], abs=20.0)
    assert data.inc_length_m == pytest.approx(TRUE_INCREASING.length(TABLE), abs=1e-5)
    assert data.dec_length_m == pytest.approx(TRUE_DECREASING.length(TABLE[-2::-1]), abs=1e-5)
    assert data.rest_length_m == pytest.approx(TRUE_INCREASING.length(0.0))


def test_auto_steady_state_keeps_raw_samples_of_a_ramp():
    t = np.linspace(0, 10, 1001)
    pressure = 5e5 * np.where(t < 5, t / 5, (10 - t) / 5)
    length = TRUE_INCREASING.length(pressure)
    data = split_branches(Samples(t, pressure, length), 20_000.0)
    assert not data.steady_state
    assert data.inc_pressure_pa.size + data.dec_pressure_pa.size == t.size
    # The detector's deadband: the reversal is confirmed 20 kPa after the peak.
    assert data.dec_pressure_pa.max() == pytest.approx(5e5 - 2e4, abs=1e3)


def test_sample_log_with_and_without_setpoint(tmp_path):
    t, pressure, setpoint, length = staircase()
    with_setpoint = read_sample_log(write_sample_log(tmp_path / 'a.csv', t, pressure, length,
                                                     setpoint))
    assert with_setpoint.setpoint_pa == pytest.approx(setpoint)
    without = load_branch_data(write_sample_log(tmp_path / 'b.csv', t, pressure, length))
    assert without.steady_state  # holds of near-constant pressure found
    assert without.inc_pressure_pa.size == 11


def test_branch_table_in_si(tmp_path):
    data = load_branch_data(__import__('pma_model').__path__[0] + '/data/paper_table1.csv')
    assert data.inc_pressure_pa[-1] == 500_000.0
    assert data.dec_length_m[1] == pytest.approx(0.3005666667)
    assert data.rest_length_m == pytest.approx(0.3006)
    table = tmp_path / 't.csv'
    table.write_text('pressure_kpa,length_increasing_cm,length_decreasing_cm\n0,30,\n50,29.9,29.5\n')
    partial = read_branch_table(table)
    assert partial.inc_pressure_pa.size == 2 and partial.dec_pressure_pa.size == 1


def test_hold_runs_on_long_ramps_is_fast():
    values = np.arange(1_000_000, dtype=float) * 1000.0  # every sample its own run
    assert hold_runs(values) == []
    steps = np.repeat(np.arange(100) * 10_000.0, 1000)
    assert len(hold_runs(steps)) == 100


@pytest.mark.parametrize(('content', 'message'), [
    ('time_s,gauge_pressure_pa\n0,1\n', 'missing column'),
    ('time_s,gauge_pressure_pa,length_m\n0,abc,0.3\n', 'not a number'),
    ('', 'empty'),
])
def test_bad_csv_is_a_clear_error(tmp_path, content, message):
    path = tmp_path / 'bad.csv'
    path.write_text(content)
    with pytest.raises(SamplesError, match=message):
        load_branch_data(path)


def test_missing_file_and_empty_bag_are_clear_errors(tmp_path):
    with pytest.raises(SamplesError, match='no such file'):
        load_branch_data(tmp_path / 'nope.mcap')
    t, pressure, setpoint, _ = staircase()
    bag = write_state_bag(tmp_path / 'nan', t, pressure, setpoint, np.full(t.size, np.nan))
    with pytest.raises(SamplesError, match='no usable samples'):
        load_branch_data(bag, progress=False)
