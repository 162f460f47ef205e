"""pma_model.offline.bag_plot: the figure of any bag, from bags written here with pma_bag's writer
(the process tests with the real rig are in tests/test_cli_plot.py)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from PIL import Image

from pma_model import units
from pma_model.offline import bag_plot
from pma_model.offline.bag_plot import RANGES_KEY, bag_figure, plot_bag, read_bag_series

pytestmark = pytest.mark.in_process

START_S = 1_700_000_000.0


def _stamp(message, t: float) -> int:
    stamp_ns = round((START_S + t) * 1e9)
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return stamp_ns


def sine_run(n: int, rate_hz: float = 50.0):
    t = np.arange(n) / rate_hz
    setpoint = 150_000.0 + 100_000.0 * np.sin(2 * np.pi * 0.1 * t)
    pressure = setpoint + 3_000.0 * np.sin(2 * np.pi * 3.0 * t)
    length = 0.30 - 0.06 * pressure / 500_000.0
    return t, pressure, setpoint, length


def write_messages(writer, t, pressure, setpoint, length, *, control_from: float | None = None,
                   prediction: bool = True, flush_every: int = 0) -> None:
    """PmaState on /pma/state, with pma/prediction and pma/control_state as the rig
    publishes them (stamped with the state's stamp)."""
    from rclpy.serialization import serialize_message

    from pma_interfaces.msg import ControlState, PmaPrediction, PmaState

    for topic, type_name in (('/pma/state', 'PmaState'), ('/pma/prediction', 'PmaPrediction'),
                             ('/pma/control_state', 'ControlState')):
        if topic not in writer.topics:
            writer.add_topic(topic, f'pma_interfaces/msg/{type_name}')
    state, predicted, control = PmaState(), PmaPrediction(), ControlState()
    for i in range(t.size):
        stamp_ns = _stamp(state, t[i])
        state.seq, state.gauge_pressure_pa = i, float(pressure[i])
        state.gauge_setpoint_pa, state.length_m = float(setpoint[i]), float(length[i])
        writer.write('/pma/state', serialize_message(state), stamp_ns + 1_000_000)
        if prediction:
            _stamp(predicted, t[i])
            predicted.predicted_length_m = float(length[i]) + 0.001
            writer.write('/pma/prediction', serialize_message(predicted), stamp_ns + 2_000_000)
        _stamp(control, t[i])
        active = control_from is not None and t[i] >= control_from
        control.mode = ControlState.MODE_GOAL if active else ControlState.MODE_IDLE
        control.message = '' if active else 'hold ended: a test'
        control.target_length_m = 0.275 if active else float('nan')
        control.setpoint_length_m = 0.28 if active else float(length[i])
        writer.write('/pma/control_state', serialize_message(control), stamp_ns + 3_000_000)
        if flush_every and i % flush_every == flush_every - 1:
            writer.flush()


def write_bag(path, *columns, **kwargs):
    from pma_bag import BagWriter

    with BagWriter(path, custom_data={'note': 'a sine', 'run_id': 'sine-1'},
                   compression=kwargs.pop('compression', ''),
                   max_bag_duration_s=kwargs.pop('max_bag_duration_s', 0.0)) as writer:
        write_messages(writer, *columns, **kwargs)
    return path


def closing(figure):
    import matplotlib.pyplot as plt
    figure.canvas.draw()
    plt.close(figure)
    return figure


def test_the_figure_shows_pressure_setpoint_length_prediction_target_and_the_loop(tmp_path):
    t, pressure, setpoint, length = sine_run(1000)
    bag = write_bag(tmp_path / 'sine', t, pressure, setpoint, length, control_from=10.0)
    series = read_bag_series(bag)
    assert series.samples == 1000 and not series.decimated and not series.truncated
    figure = closing(bag_figure(series))
    pressure_axes, length_axes, loop_axes = figure.axes[:3]
    lines = {line.get_label(): line for line in pressure_axes.get_lines()}
    assert set(lines) == {'measured', 'setpoint (device)'}
    assert np.array_equal(lines['measured'].get_ydata(), units.pa_to_kpa(pressure))
    assert np.array_equal(lines['setpoint (device)'].get_ydata(), units.pa_to_kpa(setpoint))
    lines = {line.get_label(): line for line in length_axes.get_lines()}
    assert set(lines) == {'measured', 'model prediction (model_node)',
                          "controller's target length",
                          "controller's length setpoint (rate-limited)"}
    assert np.array_equal(lines['measured'].get_ydata(), units.m_to_cm(length))
    target = np.asarray(lines["controller's target length"].get_ydata())
    target_t = np.asarray(lines["controller's target length"].get_xdata())
    assert np.all(np.isnan(target[target_t < 9.99]))               # idle: no target, a gap
    assert target[target_t >= 10.0] == pytest.approx(27.5)
    (points,) = loop_axes.collections
    assert np.asarray(points.get_array()) == pytest.approx(t)       # coloured by time
    assert 'kPa' in pressure_axes.get_ylabel() and 'cm' in length_axes.get_ylabel()
    assert 'kPa' in loop_axes.get_xlabel() and 'cm' in loop_axes.get_ylabel()
    # The axes cover what was recorded, in kPa and cm.
    low, high = pressure_axes.get_ylim()
    assert low <= units.pa_to_kpa(pressure.min()) and high >= units.pa_to_kpa(pressure.max())
    low, high = length_axes.get_ylim()
    assert low <= units.m_to_cm(length.min()) and high >= units.m_to_cm(length.max())


def test_the_png_carries_the_footer_and_what_its_axes_show(tmp_path):
    t, pressure, setpoint, length = sine_run(500)
    bag = write_bag(tmp_path / 'sine', t, pressure, setpoint, length)
    path, series, ranges = plot_bag(bag)
    assert path == tmp_path / 'sine.png'                      # beside the bag
    assert not series.control                                 # never a target: no line
    with Image.open(path) as image:
        text = dict(image.text)
        pixels = np.asarray(image.convert('L'))
    assert 'run sine-1' in text['Description'] and 'note=a sine' in text['Description']
    assert json.loads(text[RANGES_KEY]) == ranges
    shown = ranges['gauge pressure [kPa] vs time [s]']
    measured = shown['drawn']['measured']['y']
    assert measured == pytest.approx([units.pa_to_kpa(pressure.min()),
                                      units.pa_to_kpa(pressure.max())])
    assert shown['ylim'][0] <= measured[0] and shown['ylim'][1] >= measured[1]
    assert set(ranges) == {'gauge pressure [kPa] vs time [s]',
                           'muscle length L [cm] vs time [s]',
                           'muscle length L [cm] vs gauge pressure P [kPa]'}
    assert pixels.std() > 20 and (pixels < 100).mean() > 0.01        # drawn, not blank


def test_a_large_bag_is_decimated_keeping_its_extremes():
    # 300 000 samples in 15 batches: the buckets double as the bag grows.
    buckets = bag_plot._MinMaxBuckets(2000)
    rng = np.random.default_rng(1)
    n = 300_000
    stamp = np.arange(n) / 1000.0
    pressure = 200_000.0 + 1_000.0 * rng.standard_normal(n)
    pressure[123_457] = 480_000.0                            # one spike
    length = 0.27 + 0.001 * rng.standard_normal(n)
    length[rng.choice(n, 5_000, replace=False)] = np.nan     # echo timeouts
    length[234_567] = 0.2
    setpoint = np.where(stamp < 150, 200_000.0, 0.0)
    for start in range(0, n, bag_plot.BATCH):
        part = slice(start, start + bag_plot.BATCH)
        buckets.add({'stamp': stamp[part], 'pressure': pressure[part], 'length': length[part],
                     'setpoint': setpoint[part]})
    kept = buckets.kept
    assert buckets.count == n and buckets.k == 128
    assert kept['stamp'].size <= 7 * n / buckets.k
    assert np.all(np.diff(kept['index']) > 0)
    assert kept['pressure'].max() == 480_000.0 and np.nanmin(kept['length']) == 0.2
    assert kept['pressure'].min() == pressure.min()
    assert set(kept['setpoint']) == {0.0, 200_000.0}
    # Coherent samples: each kept row is one sample, all its columns.
    rows = kept['index']
    assert np.array_equal(kept['pressure'], pressure[rows])
    assert np.array_equal(kept['length'], length[rows], equal_nan=True)


def test_a_bag_still_being_written_plots_what_it_holds_so_far(tmp_path):
    from pma_bag import BagWriter

    t, pressure, setpoint, length = sine_run(600)
    writer = BagWriter(tmp_path / 'live', compression='zstd', custom_data={'note': 'live'})
    try:
        write_messages(writer, t[:400], pressure[:400], setpoint[:400], length[:400],
                       control_from=5.0, flush_every=50)
        writer.flush()
        assert not (tmp_path / 'live' / 'metadata.yaml').exists()    # not finished
        path, series, ranges = plot_bag(tmp_path / 'live', tmp_path / 'out' / 'live.png')
        assert series.truncated and series.samples == 400
        assert series.time_s[-1] == pytest.approx(t[399])
        shown = ranges['muscle length L [cm] vs time [s]']
        assert shown['ylim'][0] <= units.m_to_cm(length[:400].min())
        assert shown['ylim'][1] >= units.m_to_cm(length[:400].max())
        with Image.open(path) as image:
            assert 'unfinished or truncated' in image.text['Title']
            assert 'note=live' in image.text['Description']
        # The writer goes on; the next look sees more.
        write_messages(writer, t[400:], pressure[400:], setpoint[400:], length[400:],
                       control_from=5.0)
        writer.flush()
        assert read_bag_series(tmp_path / 'live').samples == 600
    finally:
        writer.close()
    assert not read_bag_series(tmp_path / 'live').truncated


def test_a_split_compressed_bag_reads_as_one(tmp_path):
    t, pressure, setpoint, length = sine_run(1500)
    bag = write_bag(tmp_path / 'split', t, pressure, setpoint, length, compression='zstd',
                    max_bag_duration_s=5.0)
    assert len(list(bag.glob('*.mcap'))) >= 5
    series = read_bag_series(bag)
    assert series.samples == 1500 and series.time_s == pytest.approx(t, abs=1e-6)
    assert series.prediction['length_m'].size == 1500


def test_a_long_1khz_bag_reads_in_seconds_and_little_memory(tmp_path):
    """Five minutes at 1 kHz (300 000 states, zstd): some ten thousand points are plotted
    whatever the length, and the read holds a batch at a time (an hour at 1 kHz: docs/cli.md)."""
    import resource
    import struct

    from rclpy.serialization import serialize_message

    from pma_bag import BagWriter
    from pma_interfaces.msg import PmaState
    from pma_model.offline.samples import _field_offsets

    n = 300_000
    message = PmaState()
    message.header.frame_id = 'pma'
    offsets = {name: offset for name, (offset, _) in
               _field_offsets(message, serialize_message).items()}
    payload = bytearray(serialize_message(message))
    with BagWriter(tmp_path / 'long', compression='zstd') as writer:
        writer.add_topic('/pma/state', 'pma_interfaces/msg/PmaState')
        for i in range(n):       # a staircase of 30 s steps, written at the bytes' speed
            stamp_ns = round(START_S * 1e9) + i * 1_000_000
            setpoint = (i // 30_000 % 6) * 100_000.0
            pressure = setpoint + (i % 7) * 100.0 + (150_000.0 if i == 123_457 else 0.0)
            for name, kind, value in (('sec', '<i', stamp_ns // 10**9),
                                      ('nanosec', '<I', stamp_ns % 10**9),
                                      ('gauge_pressure_pa', '<d', pressure),
                                      ('gauge_setpoint_pa', '<d', setpoint),
                                      ('length_m', '<d', 0.3 - pressure * 1e-7)):
                struct.pack_into(kind, payload, offsets[name], value)
            writer.write('/pma/state', bytes(payload), stamp_ns + 1_000_000)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    started = time.process_time()
    series = read_bag_series(tmp_path / 'long')
    took = time.process_time() - started
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert series.samples == n and series.decimated and series.bucket == 128
    assert series.time_s.size < 15_000
    assert series.pressure_pa.max() == 400_000.0 + 500.0 + 150_000.0    # the spike survives
    assert took < 10.0, took           # ~0.7 s on the 2-core VM
    assert grew_mb < 100, grew_mb      # ~20 MB
