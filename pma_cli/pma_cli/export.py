"""`pma export BAG --csv out.csv`: one row per PmaState with its prediction, for MATLAB or Excel.

No ROS graph: pma_bag reads the bag and rclpy's serialisation decodes each message with the
installed type support. Columns are SI with the unit in the name, as on the ROS interfaces
(gauge_pressure_pa, length_m), so the file is also a sample log `refit` reads. The bag's
metadata (its note, the sweep plan, the device and its calibration) goes into `#` comment
lines above the header, or with --no-comments into a YAML file beside the CSV.
"""

from __future__ import annotations

import csv
import datetime
import io
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

from pma_bag import BagError, BagReader
from pma_model.offline.samples import STATE_TOPIC, SamplesError, state_topic_in

PREDICTION_TYPE = 'pma_interfaces/msg/PmaPrediction'

# (column, unit, meaning): the header names them, the comment block explains them.
STATE_COLUMNS = (
    ('time_s', 's', 'header.stamp since the first row'),
    ('stamp_s', 's', 'header.stamp, ROS time (seconds since 1970-01-01 UTC)'),
    ('seq', '1', 'device sample counter (a jump of more than 1 = lost samples)'),
    ('device_time_s', 's', 'device clock at acquisition'),
    ('gauge_pressure_pa', 'Pa', 'measured gauge pressure'),
    ('gauge_setpoint_pa', 'Pa', 'setpoint the device regulated to'),
    ('length_m', 'm', 'measured length (empty: no echo)'),
    ('valve_state', '1', '0 hold, 1 fill, 2 vent'),
    ('status', '1', 'device status bits (docs/serial-protocol.md); 0 = healthy'),
    ('pressure_adc', 'count', 'raw 10-bit ADC count of the pressure sensor'),
    ('echo_us', 'us', 'raw HC-SR04 echo width (0 = no echo)'),
)
PREDICTION_COLUMNS = (
    ('predicted_length_m', 'm', "model_node's predicted length for this sample"),
    ('residual_m', 'm', 'length_m - predicted_length_m'),
    ('branch', '1', 'model branch: 1 increasing (inflating), 2 decreasing'),
    ('adaptation_offset_m', 'm', 'online drift correction: offset'),
    ('adaptation_gain', '1', 'online drift correction: gain'),
)
COLUMNS = STATE_COLUMNS + PREDICTION_COLUMNS


class ExportError(Exception):
    """The bag cannot be exported; one line for the user."""


@dataclass
class ExportSummary:
    rows: int
    predicted: int
    state_topic: str
    prediction_topic: str      # '' when the bag holds no predictions
    truncated: str
    metadata_path: Path | None


def _number(value: float) -> str:
    """Full precision, and empty for NaN (blank in Excel, NaN in MATLAB and refit)."""
    return repr(float(value)) if math.isfinite(value) else ''


def prediction_topic_for(state_topic: str, topics: dict) -> str:
    """`/left/pma/state` -> `/left/pma/prediction`, if the bag holds it as PmaPrediction."""
    name = state_topic.rsplit('/', 1)[0] + '/prediction'
    topic = topics.get(name)
    usable = topic is not None and topic.type_name == PREDICTION_TYPE and topic.message_count
    return name if usable else ''


def metadata(bag: Path, reader: BagReader, state_topic: str, prediction_topic: str,
             truncated: str) -> dict:
    """What the CSV cannot say in its columns: where it came from and what the run was."""
    time_range = reader.time_range_ns()
    return {
        'source_bag': str(bag.resolve()),
        'exported_at': datetime.datetime.now(datetime.timezone.utc).isoformat(
            timespec='seconds'),
        'state_topic': state_topic,
        'prediction_topic': prediction_topic or '(none in the bag: prediction columns empty)',
        'bag_start_s': time_range[0] / 1e9 if time_range else None,
        'truncated': truncated or None,
        'custom_data': dict(sorted(reader.custom_data.items())),
        'columns': {name: f'[{unit}] {meaning}' for name, unit, meaning in COLUMNS},
    }


def _comment_block(meta: dict) -> str:
    text = yaml.safe_dump(meta, sort_keys=False, allow_unicode=True, width=1000)
    return ''.join(f'# {line}\n' for line in text.splitlines())


def export_csv(bag: Path, out: Path | None, topic: str = STATE_TOPIC,
               comments: bool = True) -> ExportSummary:
    """Write the CSV to `out` (None: stdout); ExportError says why it cannot."""
    from rclpy.serialization import deserialize_message

    from pma_interfaces.msg import PmaPrediction, PmaState

    bag = Path(bag)
    if not bag.exists():
        raise ExportError(f'{bag}: no such bag')
    try:
        reader = BagReader.quietly(bag)
    except BagError as error:
        raise ExportError(str(error)) from None
    with reader:
        truncated = reader.damage
        try:
            state_topic = state_topic_in(reader.topics, topic)
        except SamplesError as error:
            raise ExportError(f'{bag}: {error}') from None
        prediction_topic = prediction_topic_for(state_topic, reader.topics)
        predictions = {}
        try:
            if prediction_topic:
                for message in reader.messages([prediction_topic]):
                    prediction = deserialize_message(message.data, PmaPrediction)
                    stamp = prediction.header.stamp
                    predictions[(stamp.sec, stamp.nanosec)] = prediction
            meta = metadata(bag, reader, state_topic, prediction_topic, truncated)
            buffer = io.StringIO(newline='')
            if comments:
                buffer.write(_comment_block(meta))
            writer = csv.writer(buffer, lineterminator='\n')
            writer.writerow([name for name, _, _ in COLUMNS])
            rows = matched = 0
            first = None
            for message in reader.messages([state_topic]):
                state = deserialize_message(message.data, PmaState)
                stamp = state.header.stamp
                stamp_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
                first = stamp_ns if first is None else first
                row = [_number((stamp_ns - first) / 1e9), f'{stamp.sec}.{stamp.nanosec:09d}',
                       state.seq,
                       _number(state.device_time_s), _number(state.gauge_pressure_pa),
                       _number(state.gauge_setpoint_pa), _number(state.length_m),
                       state.valve_state, state.status, state.pressure_adc, state.echo_us]
                prediction = predictions.get((stamp.sec, stamp.nanosec))
                if prediction is None:
                    row += [''] * len(PREDICTION_COLUMNS)
                else:
                    matched += 1
                    row += [_number(prediction.predicted_length_m),
                            _number(prediction.residual_m), prediction.branch,
                            _number(prediction.adaptation_offset_m),
                            _number(prediction.adaptation_gain)]
                writer.writerow(row)
                rows += 1
        except BagError as error:
            raise ExportError(str(error)) from None
    if rows == 0:
        raise ExportError(f'{bag}: {state_topic} holds no messages')
    meta_path = None
    try:
        if out is None:
            sys.stdout.write(buffer.getvalue())
        else:
            out.write_text(buffer.getvalue(), encoding='utf-8')
            if not comments:
                meta_path = out.with_name(out.name + '.metadata.yaml')
                meta_path.write_text(yaml.safe_dump(meta, sort_keys=False), encoding='utf-8')
    except BrokenPipeError:
        raise                  # `pma export BAG --csv - | head`: main ends quietly
    except OSError as error:
        raise ExportError(f'cannot write {error.filename}: {error.strerror}') from None
    return ExportSummary(rows, matched, state_topic, prediction_topic, truncated, meta_path)
