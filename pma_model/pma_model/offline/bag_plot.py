"""`pma plot BAG`: one figure for any recording, no ROS graph needed.

Pressure (measured, and the device's setpoint) and length (measured, model_node's prediction
from pma/prediction and the length controller's target and rate-limited setpoint from
pma/control_state, where the bag has them) against time, and the pressure-length loop
coloured by time; kPa and cm, the refit figures' style (plots.py: its colour registry and
its footer with the run, dates, software version and the bag's metadata).

Any bag with PmaState works: staircases, sines, ramps, CSV profiles, FORC, controller runs,
split and compressed bags, and bags still being written or cut off by a crash (what is there
so far: pma_bag's reader reads up to the damage).

Decimation: the states are read in batches and decoded at numpy speed
(samples._decode_states); in every bucket of k consecutive samples only the first one and
those where pressure, setpoint or length is lowest or highest are kept (so steps, peaks and
spikes survive), k doubling as the bag grows so that at most about STATE_BUCKETS buckets
remain; of pma/prediction and pma/control_state every k-th message is kept (at most about
2 * AUX_MESSAGES), and only those are deserialised. An hour at 1 kHz thus plots some ten
thousand points, with a few MB held at any time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use('Agg')    # no display needed; plot_bag(show=True) switches for --show
import matplotlib.pyplot as plt
import numpy as np

from pma_model import units
from pma_model.offline import plots, provenance
from pma_model.offline.samples import STATE_TOPIC, SamplesError, _decode_states, state_topic_in

PREDICTION_TYPE = 'pma_interfaces/msg/PmaPrediction'
CONTROL_TYPE = 'pma_interfaces/msg/ControlState'
STATE_BUCKETS = 2000
AUX_MESSAGES = 3000
BATCH = 20_000
# The PNG text chunk with what the axes show (limits, and the plotted data's ranges).
RANGES_KEY = 'pma:plotted'


class BagPlotError(ValueError):
    """The bag cannot be plotted; one line for the user."""


class _MinMaxBuckets:
    """Samples in reading order, reduced to buckets of k consecutive samples: each bucket
    keeps its first sample and those where a signal is lowest or highest."""

    SIGNALS = ('pressure', 'setpoint', 'length')

    def __init__(self, buckets: int):
        self.buckets = buckets
        self.k = 1
        self.count = 0
        self.kept: dict[str, np.ndarray] | None = None

    def add(self, columns: dict[str, np.ndarray]) -> None:
        n = len(columns['stamp'])
        columns = dict(columns, index=np.arange(self.count, self.count + n))
        self.count += n
        reduced = self._reduce(columns, self.k)
        self.kept = reduced if self.kept is None else {
            name: np.concatenate([self.kept[name], reduced[name]]) for name in reduced}
        while self.count / self.k > 2 * self.buckets:
            self.k *= 2
            self.kept = self._reduce(self.kept, self.k)

    @classmethod
    def _reduce(cls, columns: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        if k == 1:
            return columns
        group = columns['index'] // k
        keep = [np.flatnonzero(np.r_[True, group[1:] != group[:-1]])]
        for name in cls.SIGNALS:
            values = columns[name]
            finite = np.flatnonzero(np.isfinite(values))
            if not finite.size:
                continue
            order = np.lexsort((values[finite], group[finite]))
            ordered = group[finite][order]
            starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
            ends = np.r_[starts[1:], ordered.size] - 1
            keep += [finite[order[starts]], finite[order[ends]]]
        rows = np.unique(np.concatenate(keep))
        return {name: values[rows] for name, values in columns.items()}


class _EveryKth:
    """Every k-th payload of a stream, k doubling whenever more than 2 * limit are held."""

    def __init__(self, limit: int):
        self.limit, self.k, self.count, self.kept = limit, 1, 0, []

    def add(self, payload: bytes) -> None:
        if self.count % self.k == 0:
            self.kept.append(payload)
            if len(self.kept) > 2 * self.limit:
                self.kept, self.k = self.kept[::2], self.k * 2
        self.count += 1


@dataclass
class BagSeries:
    """What a bag's figure shows, decimated, in SI; time_s from the first state's stamp."""

    source: str
    state_topic: str
    samples: int                       # states read
    time_s: np.ndarray
    pressure_pa: np.ndarray
    setpoint_pa: np.ndarray
    length_m: np.ndarray
    prediction: dict[str, np.ndarray] = field(default_factory=dict)   # time_s, length_m
    control: dict[str, np.ndarray] = field(default_factory=dict)   # time_s, target_m, setpoint_m
    bucket: int = 1                    # k of the state's min/max buckets
    truncated: str = ''

    @property
    def decimated(self) -> bool:
        return self.bucket > 1


def _sibling(state_topic: str, name: str, type_name: str, topics: dict) -> str:
    """`/left/pma/state` -> `/left/pma/<name>`, if the bag holds it with that type."""
    topic = state_topic.rsplit('/', 1)[0] + '/' + name
    info = topics.get(topic)
    return topic if info is not None and info.type_name == type_name else ''


def _stamps(messages) -> np.ndarray:
    return np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in messages])


def read_bag_series(path, topic: str = STATE_TOPIC, buckets: int = STATE_BUCKETS,
                    aux_messages: int = AUX_MESSAGES) -> BagSeries:
    """The bag's states, predictions and controller targets, decimated for plotting."""
    from rclpy.serialization import deserialize_message

    from pma_bag import BagError, BagReader
    from pma_interfaces.msg import ControlState, PmaPrediction, PmaState

    path = Path(path)
    if not path.exists():
        raise BagPlotError(f'{path}: no such bag')
    try:
        reader = BagReader.quietly(path)
    except BagError as error:
        raise BagPlotError(str(error)) from None
    with reader:
        truncated = reader.damage
        try:
            state_topic = state_topic_in(reader.topics, topic)
        except SamplesError as error:
            raise BagPlotError(f'{path}: {error}') from None
        prediction_topic = _sibling(state_topic, 'prediction', PREDICTION_TYPE, reader.topics)
        control_topic = _sibling(state_topic, 'control_state', CONTROL_TYPE, reader.topics)
        states = _MinMaxBuckets(buckets)
        aux = {prediction_topic: _EveryKth(aux_messages), control_topic: _EveryKth(aux_messages)}
        batch: list[bytes] = []

        def decode() -> None:
            stamp, pressure, length, setpoint = _decode_states(batch, PmaState)
            states.add({'stamp': stamp, 'pressure': pressure, 'length': length,
                        'setpoint': setpoint})
            batch.clear()

        try:
            for message in reader.messages({state_topic, prediction_topic, control_topic} - {''}):
                if message.topic == state_topic:
                    batch.append(message.data)
                    if len(batch) >= BATCH:
                        decode()
                else:
                    aux[message.topic].add(message.data)
        except BagError as error:
            raise BagPlotError(f'{path}: {error}') from None
        if batch:
            decode()
    if states.kept is None:
        raise BagPlotError(f'{path}: {state_topic} holds no messages (yet)')
    kept = states.kept
    order = np.argsort(kept['stamp'], kind='stable')
    start = kept['stamp'][order[0]]
    series = BagSeries(str(path), state_topic, states.count, kept['stamp'][order] - start,
                       kept['pressure'][order], kept['setpoint'][order], kept['length'][order],
                       bucket=states.k, truncated=truncated)
    if prediction_topic and aux[prediction_topic].kept:
        decoded = [deserialize_message(p, PmaPrediction) for p in aux[prediction_topic].kept]
        series.prediction = {'time_s': _stamps(decoded) - start,
                             'length_m': np.array([m.predicted_length_m for m in decoded])}
    if control_topic and aux[control_topic].kept:
        decoded = [deserialize_message(p, ControlState) for p in aux[control_topic].kept]
        target = np.array([m.target_length_m for m in decoded])
        if np.any(np.isfinite(target)):          # a controller that never had a target: none
            series.control = {
                'time_s': _stamps(decoded) - start, 'target_m': target,
                # the rate-limited setpoint only while there is a target (idle: NaN, a gap)
                'setpoint_m': np.where(np.isfinite(target),
                                       [m.setpoint_length_m for m in decoded], np.nan)}
    return series


def bag_figure(series: BagSeries, title: str = ''):
    """Pressure and length against time (left), the loop coloured by time (right)."""
    figure = plt.figure(figsize=(13, 7))
    grid = figure.add_gridspec(2, 2, width_ratios=[1.6, 1])
    pressure = figure.add_subplot(grid[0, 0])
    length = figure.add_subplot(grid[1, 0], sharex=pressure)
    loop = figure.add_subplot(grid[:, 1])
    t = series.time_s
    p_kpa, l_cm = units.pa_to_kpa(series.pressure_pa), units.m_to_cm(series.length_m)
    pressure.plot(t, p_kpa, **plots.series_style('measured'))
    if np.any(np.isfinite(series.setpoint_pa)):       # dashed, over the measured line
        pressure.plot(t, units.pa_to_kpa(series.setpoint_pa), drawstyle='steps-post',
                      **plots.series_style('setpoint'))
    pressure.set_ylabel('gauge pressure [kPa]')
    pressure.tick_params(labelbottom=False)
    length.plot(t, l_cm, **plots.series_style('measured'))
    if series.prediction:
        length.plot(series.prediction['time_s'], units.m_to_cm(series.prediction['length_m']),
                    **plots.series_style('prediction'))
    if series.control:
        length.plot(series.control['time_s'], units.m_to_cm(series.control['target_m']),
                    **plots.series_style('target'))
        length.plot(series.control['time_s'], units.m_to_cm(series.control['setpoint_m']),
                    **plots.series_style('length setpoint'))
    length.set(xlabel='time [s]', ylabel=plots.LENGTH_LABEL)
    finite = np.isfinite(l_cm) & np.isfinite(p_kpa)
    # The path in faint grey, to follow it between the points; the points coloured by time.
    loop.plot(p_kpa[finite], l_cm[finite], color='0.82', lw=0.6, zorder=1, label='path')
    points = loop.scatter(p_kpa[finite], l_cm[finite], c=t[finite],
                          s=10 if np.count_nonzero(finite) < 3000 else 3, cmap='viridis',
                          linewidths=0, zorder=2, rasterized=True)
    # The colour bar inside the loop's top right corner, which a muscle's loop leaves empty
    # (long at low pressure, short at high).
    scale = loop.inset_axes([0.5, 0.9, 0.45, 0.025])
    figure.colorbar(points, cax=scale, orientation='horizontal', label='time [s]')
    scale.xaxis.set_label_position('top')
    scale.tick_params(labelsize=8)
    loop.set(xlabel=plots.PRESSURE_LABEL, ylabel=plots.LENGTH_LABEL)
    loop.set_title('pressure-length loop, coloured by time', fontsize=10)
    duration = t[-1] if t.size else 0.0
    what = f'{series.samples} samples over {duration:.1f} s'
    if series.decimated:
        what += (f'; plotted: {t.size} (min/max of every {series.bucket} samples)')
    if series.truncated:
        what += '; the bag is unfinished or truncated: what it holds so far'
    pressure.set_title(title or f'{Path(series.source).name}: {what}', fontsize=10)
    for ax in (pressure, length, loop):
        ax.grid(alpha=0.3)
    for ax in (pressure, length):
        ax.legend(fontsize=8, loc='best', framealpha=0.9)
    return figure


def _span(values) -> list[float] | None:
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    return [float(values.min()), float(values.max())] if values.size else None


def plotted_ranges(figure) -> dict:
    """What the figure's axes show, by axis labels ('gauge pressure [kPa] vs time [s]'): their
    limits, and the x and y ranges of each line and point set drawn (NaN left out), by its
    label; for a test, or a program reading the PNG."""
    shown = {}
    for ax in figure.axes:
        xlabel, ylabel = ax.get_xlabel() or 'time [s]', ax.get_ylabel()
        if not ylabel:
            continue
        drawn = {line.get_label(): (line.get_xdata(), line.get_ydata())
                 for line in ax.get_lines()}
        for index, collection in enumerate(ax.collections):
            offsets = np.asarray(collection.get_offsets(), float).reshape(-1, 2)
            drawn[f'points {index}'] = (offsets[:, 0], offsets[:, 1])
        shown[f'{ylabel} vs {xlabel}'] = {
            'xlim': [float(v) for v in ax.get_xlim()], 'ylim': [float(v) for v in ax.get_ylim()],
            'drawn': {label: {'x': _span(x), 'y': _span(y)} for label, (x, y) in drawn.items()}}
    return shown


def default_output(bag) -> Path:
    """BAG.png beside the bag: runs/day1 -> runs/day1.png, runs/x.mcap -> runs/x.png."""
    bag = Path(bag)
    return bag.with_suffix('.png') if bag.is_file() else bag.parent / f'{bag.name}.png'


def plot_bag(bag, out=None, *, topic: str = STATE_TOPIC, run_id: str | None = None):
    """Read `bag`, write its figure to `out` (default: default_output); (path, series, ranges)."""
    series = read_bag_series(bag, topic)
    figure = bag_figure(series)
    ranges = plotted_ranges(figure)
    path = Path(out) if out is not None else default_output(bag)
    run = provenance.input_run(bag, run_id)
    plots.save(figure, path, run, extra_metadata={RANGES_KEY: json.dumps(ranges)})
    return path, series, ranges
