"""pma export: a real bag (pma_bag's writer, rclpy's serialisation) back out as CSV, row by row."""

import csv
import math

import pytest
import yaml
from rclpy.serialization import serialize_message

from pma_bag import BagWriter
from pma_cli.export import COLUMNS, ExportError, export_csv
from pma_interfaces.msg import PmaPrediction, PmaState
from pma_model.offline.samples import read_sample_log

T0_NS = 1_790_000_000_123_456_789


def state(k: int) -> PmaState:
    msg = PmaState(seq=1000 + k, device_time_s=12.0 + 0.05 * k,
                   gauge_pressure_pa=1000.0 * k + 0.125, length_m=0.3 - 0.001 * k,
                   gauge_setpoint_pa=50_000.0, valve_state=PmaState.VALVE_FILL, status=0,
                   pressure_adc=100 + k, echo_us=600 + k)
    stamp_ns = T0_NS + k * 50_000_000
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = 'pma_link'
    if k == 3:
        msg.length_m, msg.echo_us, msg.status = math.nan, 0, PmaState.STATUS_ECHO_TIMEOUT
    return msg


def prediction(s: PmaState) -> PmaPrediction:
    msg = PmaPrediction(gauge_pressure_pa=s.gauge_pressure_pa, measured_length_m=s.length_m,
                        predicted_length_m=s.length_m + 0.0005,
                        residual_m=-0.0005 if math.isfinite(s.length_m) else math.nan,
                        branch=PmaPrediction.BRANCH_INCREASING, adaptation_offset_m=0.0,
                        adaptation_gain=1.0)
    msg.header = s.header
    return msg


def write_bag(path, count=10, predict=lambda k: k % 4 != 1, namespaces=('/left',)):
    writer = BagWriter(path, custom_data={'note': 'muscle 2, new sleeve',
                                          'calibration.volts_at_full': '4.49'})
    for ns in namespaces:
        writer.add_topic(f'{ns}/pma/state', 'pma_interfaces/msg/PmaState')
        writer.add_topic(f'{ns}/pma/prediction', 'pma_interfaces/msg/PmaPrediction')
    for k in range(count):
        s = state(k)
        for ns in namespaces:
            writer.write(f'{ns}/pma/state', serialize_message(s), T0_NS + k * 50_000_000 + 10)
            if predict(k):
                writer.write(f'{ns}/pma/prediction', serialize_message(prediction(s)),
                             T0_NS + k * 50_000_000 + 20)
    writer.close()
    return path


def rows_of(path):
    with open(path, newline='') as stream:
        lines = [line for line in stream if not line.startswith('#')]
    return list(csv.DictReader(lines))


def test_one_row_per_state_with_its_prediction(tmp_path):
    bag = write_bag(tmp_path / 'bag')
    out = tmp_path / 'out.csv'
    summary = export_csv(bag, out)
    assert (summary.rows, summary.predicted) == (10, 7)
    assert summary.state_topic == '/left/pma/state'
    assert summary.prediction_topic == '/left/pma/prediction'
    rows = rows_of(out)
    assert list(rows[0]) == [name for name, _, _ in COLUMNS]
    for k, row in enumerate(rows):
        s = state(k)
        assert float(row['time_s']) == pytest.approx(0.05 * k, abs=1e-9)
        sec, nanosec = divmod(T0_NS + k * 50_000_000, 1_000_000_000)
        assert row['stamp_s'] == f'{sec}.{nanosec:09d}'           # exact, no float rounding
        assert int(row['seq']) == s.seq and int(row['pressure_adc']) == s.pressure_adc
        assert float(row['gauge_pressure_pa']) == s.gauge_pressure_pa    # full precision
        if k == 3:
            assert row['length_m'] == '' and row['echo_us'] == '0' and row['status'] == '4'
        else:
            assert float(row['length_m']) == s.length_m
        if k % 4 == 1:
            assert row['predicted_length_m'] == row['branch'] == ''
        elif k == 3:                         # predicted, but NaN: empty, the branch is there
            assert row['predicted_length_m'] == row['residual_m'] == '' and row['branch'] == '1'
        else:
            assert float(row['predicted_length_m']) == prediction(s).predicted_length_m
            assert row['branch'] == '1' and float(row['adaptation_gain']) == 1.0


def test_the_metadata_rides_along_and_refit_reads_the_file(tmp_path):
    bag = write_bag(tmp_path / 'bag')
    out = tmp_path / 'out.csv'
    export_csv(bag, out)
    comments = ''.join(line[2:] for line in out.read_text().splitlines(keepends=True)
                       if line.startswith('# '))
    meta = yaml.safe_load(comments)
    assert meta['custom_data'] == {'calibration.volts_at_full': '4.49',
                                   'note': 'muscle 2, new sleeve'}
    assert meta['source_bag'] == str(bag.resolve())
    assert meta['columns']['gauge_pressure_pa'].startswith('[Pa]')
    samples = read_sample_log(out)               # the same file is a sample log for refit
    assert samples.pressure_pa.size == 9 and samples.dropped_nan == 1


def test_no_comments_puts_the_metadata_beside_the_file(tmp_path):
    bag = write_bag(tmp_path / 'bag')
    out = tmp_path / 'plain.csv'
    summary = export_csv(bag, out, comments=False)
    assert out.read_text().startswith('time_s,stamp_s,seq,')
    assert summary.metadata_path == tmp_path / 'plain.csv.metadata.yaml'
    meta = yaml.safe_load(summary.metadata_path.read_text())
    assert meta['custom_data']['note'] == 'muscle 2, new sleeve'


def test_a_bag_without_predictions_leaves_those_columns_empty(tmp_path):
    bag = write_bag(tmp_path / 'bag', predict=lambda k: False)
    out = tmp_path / 'out.csv'
    summary = export_csv(bag, out)
    assert summary.predicted == 0 and summary.prediction_topic == ''
    assert all(row['predicted_length_m'] == '' for row in rows_of(out))


def test_errors_say_what_to_do(tmp_path):
    with pytest.raises(ExportError, match='no such bag'):
        export_csv(tmp_path / 'missing', tmp_path / 'x.csv')
    two = write_bag(tmp_path / 'two', namespaces=('/left', '/right'))
    with pytest.raises(ExportError, match='--topic'):
        export_csv(two, tmp_path / 'x.csv')
    summary = export_csv(two, tmp_path / 'right.csv', topic='/right/pma/state')
    assert summary.rows == 10 and summary.prediction_topic == '/right/pma/prediction'
    not_a_bag = tmp_path / 'notes.mcap'
    not_a_bag.write_text('hello')
    with pytest.raises(ExportError):
        export_csv(not_a_bag, tmp_path / 'x.csv')
