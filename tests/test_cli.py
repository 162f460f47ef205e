"""Every `pma` verb against the simulated rig: real processes over DDS, no ros2 CLI.

The rig (fake_arduino, driver_node, model_node, an idle recorder, length_controller) runs in
namespace /cli, as `ros2 run` starts it; `pma` runs as a user types it, from the installed
console script, and what it claims is checked on the rig itself: the device's own setpoint in
pma/state, the controller's mode, the bag on disk read by rosbags (an independent reader).
"""

from __future__ import annotations

import csv
import itertools
import math
import os
import signal
import statistics
import subprocess
import threading
import time
from pathlib import Path

import pytest
import yaml
from rclpy.qos import qos_profile_sensor_data
from rosbags.highlevel import AnyReader
from std_msgs.msg import Float64

from pma_interfaces.msg import ControlState, PmaState
from pma_interfaces.srv import PressureForLength
from pma_sim.fake_arduino import TruthLog
from support.procs import INSTALL, ROOT, kill_own_group, popen_in_own_group
from support.ros import SpinningNode, shutdown, wait_until

pytestmark = pytest.mark.integration

PMA = INSTALL / 'pma_cli' / 'lib' / 'pma_cli' / 'pma'
NS = 'cli'


def pma(*args: str, namespace: str = NS, cwd: Path | None = None, timeout: float = 90.0):
    """Run `pma VERB ARGS --namespace NS` to its end; the CompletedProcess."""
    argv = [str(PMA), *args]
    if args[0] not in ('export', 'run') and namespace is not None:
        argv += ['--namespace', namespace]
    return subprocess.run(argv, check=False, capture_output=True, text=True, timeout=timeout,
                          cwd=cwd, stdin=subprocess.DEVNULL)


def not_waiting(stderr: str) -> str:
    """stderr without `pma`'s note that a node was not seen yet, which a busy machine's slow
    discovery can bring about before a node that runs is found."""
    return ''.join(line for line in stderr.splitlines(keepends=True)
                   if ': waiting for ' not in line)


def ok(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 0, f'exit {result.returncode}\n{result.stdout}\n{result.stderr}'
    assert 'Traceback' not in result.stderr, result.stderr
    return result.stdout


class Probe:
    """The rig as seen from the test: its states and the controller's."""

    def __init__(self):
        self.spinning = SpinningNode('cli_probe')
        self.states: list[PmaState] = []
        self.control: list[ControlState] = []
        node = self.spinning.node
        node.create_subscription(PmaState, f'/{NS}/pma/state', self.states.append,
                                 qos_profile_sensor_data)
        node.create_subscription(ControlState, f'/{NS}/pma/control_state', self.control.append,
                                 10)

    def fresh_state(self) -> PmaState:
        count = len(self.states)
        wait_until(lambda: len(self.states) > count + 1, 10, 'a fresh pma/state')
        return self.states[-1]

    def close(self):
        self.spinning.close()


@pytest.fixture(scope='module')
def rig(module_procs, tmp_path_factory):
    work = tmp_path_factory.mktemp('cli_rig')
    port = work / 'pma'
    recorder_cwd = work / 'recorder_cwd'
    recorder_cwd.mkdir()
    ns = ['-r', f'__ns:=/{NS}']
    truth = work / 'truth.csv'        # what a reference gauge and a tape would read
    fake = module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port), '--seed', '5',
                                 '--truth', str(truth))
    fake.wait_for_line('device at', 20)
    driver = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=[*ns, '-p',
                                                                          f'port:={port}'])
    model = module_procs.ros2_run('pma_model', 'model_node', ros_args=ns)
    recorder = module_procs.ros2_run('pma_bag', 'record', '--idle', ros_args=ns,
                                     cwd=recorder_cwd)
    controller = module_procs.ros2_run('pma_control', 'length_controller', ros_args=ns)
    driver.wait_for_line('active: publishing', 30)
    model.wait_for_line('model_node ready', 30)
    recorder.wait_for_line('idle', 30)
    controller.wait_for_line('length_controller ready', 30)
    probe = Probe()
    wait_until(lambda: len(probe.states) > 10 and probe.control, 20, 'the rig streaming')
    yield {'work': work, 'probe': probe, 'recorder_cwd': recorder_cwd, 'driver': driver,
           'controller': controller, 'truth': truth}
    probe.close()
    shutdown()


def test_status_reports_the_rig_and_points_at_the_right_namespace(rig):
    out = ok(pma('status', '--wait', '30s'))
    assert 'OK streaming' in out and '| active |' in out and 'fake_arduino' in out
    assert 'pressure ' in out and ' kPa' in out and 'length ' in out and ' cm' in out
    assert 'model ' in out and 'predicting' in out
    assert 'control ' in out
    elsewhere = pma('status', namespace='nowhere')
    assert elsewhere.returncode == 3, elsewhere
    assert '--namespace cli' in elsewhere.stderr, elsewhere.stderr


def test_set_is_confirmed_by_the_device_and_a_refusal_says_why(rig):
    probe = rig['probe']
    out = ok(pma('set', '150kPa', '--wait'))
    assert 'setpoint 150.0 kPa taken by the device' in out and 'reached' in out
    state = probe.fresh_state()
    assert state.gauge_setpoint_pa == 150_000.0
    assert abs(state.gauge_pressure_pa - 150_000.0) < 10_000.0
    too_high = pma('set', '6bar')
    assert too_high.returncode == 1
    assert 'refused 600.0 kPa' in too_high.stderr and 'max_gauge_pressure_pa' in too_high.stderr
    assert probe.fresh_state().gauge_setpoint_pa == 150_000.0      # nothing reached the device
    bad = pma('set', '150cm')
    assert bad.returncode == 2 and "'cm' is not a unit of pressure" in bad.stderr


def test_set_refuses_above_the_drivers_ceiling_and_other_scripts_digits_unpublished(
        procs, tmp_path):
    # A driver of its own, its ceiling lowered: `pma set` read it and refuses in the driver's
    # words, before publishing (it published 350 kPa for every subscriber to see, and took
    # `٣٠٠` for 300 Pa and `２００kPa` for 200 kPa).
    namespace = 'low_ceiling'
    port = tmp_path / 'pma'
    procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port), '--seed', '6'
                   ).wait_for_line('device at', 20)
    procs.ros2_run('pma_driver', 'driver_node', ros_args=[
        '-r', f'__ns:=/{namespace}', '-p', f'port:={port}',
        '-p', 'max_gauge_pressure_pa:=300000.0']).wait_for_line('active: publishing', 30)
    listener = SpinningNode('setpoint_listener')
    try:
        sent, _ = listener.collect(Float64, f'/{namespace}/pma/pressure_setpoint')
        above = pma('set', '350kPa', namespace=namespace)
        assert above.returncode == 1, above
        # (A note that the driver was not seen yet comes first if discovery took over 1 s.)
        assert not_waiting(above.stderr) == (
            'pma set: refused 350.0 kPa: setpoint 350000 Pa is above max_gauge_pressure_pa '
            f'300000 Pa (the parameter of /{namespace}/driver_node); nothing was sent\n')
        for text in ('٣٠٠', '２００kPa'):
            other = pma('set', text, namespace=namespace)
            assert other.returncode == 2 and 'use ASCII digits 0-9' in other.stderr, other
        ok(pma('set', '250kPa', namespace=namespace))      # what is published is heard
        wait_until(lambda: sent, 5, 'the 250 kPa setpoint')
        time.sleep(0.5)                                 # anything else would be in
        assert [message.data for message in sent] == [250_000.0]
    finally:
        listener.close()


def test_set_without_a_driver_refuses_above_the_default_ceiling_without_waiting():
    # No driver in this namespace: max_gauge_pressure_pa's default (500 kPa) applies, once
    # the driver is not found (4 s), not after --timeout (it waited it out, exit 3).
    listener = SpinningNode('setpoint_listener_no_driver')
    try:
        sent, _ = listener.collect(Float64, '/no_driver/pma/pressure_setpoint')
        started = time.monotonic()
        above = pma('set', '501kPa', '--timeout', '20s', namespace='no_driver')
        took = time.monotonic() - started
        assert above.returncode == 1, above
        waiting, note, refusal = above.stderr.splitlines()
        # Not a silent wait: after a second, what it waits for and how to start it.
        assert waiting.startswith('pma set: waiting for driver_node in /no_driver (not seen '
                                  'yet): is it running? (`pma ')
        assert ('`pma run pma_driver driver_node --ros-args -r __ns:=/no_driver -p '
                'port:=/dev/pma0`)') in waiting, waiting
        assert note.startswith('pma set: note: no answer from /no_driver/driver_node for its '
                               'max_gauge_pressure_pa within ') and \
            note.endswith('s; checking against its default, 500.0 kPa'), note
        assert refusal == ('pma set: refused 501.0 kPa: setpoint 501000 Pa is above '
                           "max_gauge_pressure_pa 500000 Pa (the parameter's default: "
                           '/no_driver/driver_node did not answer); nothing was sent')
        assert took < 12.0, took
        assert sent == []
    finally:
        listener.close()


def test_tare_wants_a_vented_muscle_and_vent_gives_one(rig):
    ok(pma('set', '100kPa'))
    refused = pma('tare')
    assert refused.returncode == 1
    assert 'not vented' in refused.stderr and 'pma tare --vent' in refused.stderr
    out = ok(pma('vent', '--wait'))
    assert 'setpoint 0 kPa taken' in out and 'vented:' in out
    assert rig['probe'].fresh_state().gauge_setpoint_pa == 0.0
    assert 'tared: ADC' in ok(pma('tare'))
    assert 'tared: ADC' in ok(pma('tare', '--vent'))


def test_vent_vents_when_a_goal_server_never_answers_the_cancel(rig, procs, tmp_path):
    """A cancel whose answer never comes (lost to a new client, or a hung node) is reported,
    and the 0 Pa setpoint is sent all the same: before, `pma vent` ended with exit 3 there
    and vented nothing. A rig of its own, in a namespace where the move server is silent."""
    ns = ['-r', '__ns:=/silent']
    port = tmp_path / 'pma'
    procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port),
                   name='silent_fake').wait_for_line('device at', 20)
    driver = procs.ros2_run('pma_driver', 'driver_node', name='silent_driver',
                            ros_args=[*ns, '-p', f'port:={port}'])
    silent = procs.python(ROOT / 'tests' / 'helpers' / 'silent_cancel_server.py',
                          '--ros-args', *ns, name='silent_cancel_server')
    silent.wait_for_line('silent_cancel_server: ready', 20)
    driver.wait_for_line('active: publishing', 30)
    ok(pma('set', '120kPa', '--wait', namespace='silent'))
    result = pma('vent', namespace='silent')
    out = ok(result)
    assert ('/silent/pma/move_to_length did not answer the cancel within 5 s; venting all '
            'the same') in result.stderr, result.stderr
    assert 'setpoint 0 kPa taken' in out
    silent.wait_for_line('cancel request 2 taken', 5)         # resent while unanswered


def test_length_answers_what_the_service_answers(rig):
    spinning = rig['probe'].spinning

    def direct() -> float:
        answer = spinning.call(PressureForLength, f'/{NS}/pressure_for_length',
                               PressureForLength.Request(length_m=0.27, branch=1),
                               idempotent=True)
        assert answer.success, answer.message
        return answer.gauge_pressure_pa

    # The model identifies online, so its inverse moves a little between calls: pma's answer
    # lies where the service's own answers just before and just after it lie.
    before = direct()
    out = ok(pma('length', '27cm', '--branch', 'inc', '--si'))
    after = direct()
    assert min(before, after) - 500.0 <= float(out) <= max(before, after) + 500.0
    human = ok(pma('length', '270mm', '--branch', 'increasing'))      # in mm, as asked
    assert human.startswith('270.0 mm on the increasing branch (inflating from rest): ') \
        and ' kPa ' in human and human.rstrip().endswith(' mm'), human
    unreachable = pma('length', '10cm')
    assert unreachable.returncode == 1 and 'reachable that way ' in unreachable.stderr
    assert ' m ' not in unreachable.stderr and 'mixed' not in unreachable.stderr
    negative = pma('length', '-3cm')   # a value for the service to refuse, not an option
    assert negative.returncode == 1 and 'length_m must be positive' in negative.stderr
    assert 'reachable' not in negative.stderr   # the service computed no range for it


def test_param_get_set_with_units_and_refusals_with_the_reason(rig):
    assert 'max_gauge_pressure_pa = 500000.0 (500.0 kPa)' in ok(
        pma('param', 'get', 'driver_node', 'max_gauge_pressure_pa'))
    out = ok(pma('param', 'set', 'driver_node', 'sweep.step_timeout_s', '12s'))
    assert 'sweep.step_timeout_s = 12.0' in out
    refused = pma('param', 'set', 'driver_node', 'calibration.tare_offset_pa', '90kPa')
    assert refused.returncode == 1
    assert 'more than 10 % of full_scale_pa' in refused.stderr
    missing = pma('param', 'set', 'model_node', 'params_file', 'no_such_refit.yaml',
                  cwd=rig['work'])
    assert missing.returncode == 1
    assert f'{rig["work"]}/no_such_refit.yaml' in missing.stderr       # made absolute here
    assert 'No such file' in missing.stderr
    typo = pma('param', 'get', 'driver_node', 'max_gauge_pressure')
    assert typo.returncode == 1 and 'did you mean max_gauge_pressure_pa' in typo.stderr
    listing = ok(pma('param', 'list', 'length_controller'))
    assert 'max_gauge_pressure_pa = ' in listing and '#' in listing
    assert 'fb_filter_time_constant_s = 0.15 (0.15 s)' in listing     # not "(0.1 s)"
    absent = pma('param', 'get', 'no_such_node', 'x', '--timeout', '8s')
    assert absent.returncode == 3 and 'no node /cli/no_such_node' in absent.stderr


def test_sweep_records_where_the_user_asked_and_exports_to_csv(rig, tmp_path):
    result = pma('sweep', '--max', '100kPa', '--step', '50kPa', '--hold', '0.5s',
                 '--record', 'runs/s1', '--note', 'cli test', cwd=tmp_path)
    out = ok(result)
    bag = tmp_path / 'runs' / 's1'
    assert 'sweep succeeded' in out and f'bag: {bag}' in out
    assert '100.0 %' in result.stderr or '80.0 %' in result.stderr     # the progress lines
    assert not (rig['recorder_cwd'] / 'runs').exists()
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    custom = meta['rosbag2_bagfile_information']['custom_data']
    assert custom['note'] == 'cli test' and 'calibration.volts_at_full' in custom
    with AnyReader([bag]) as reader:
        states = sum(1 for c, _, _ in reader.messages() if c.topic == f'/{NS}/pma/state')
    export = ok(pma('export', str(bag), '--csv', str(tmp_path / 's1.csv')))
    assert f'{states} rows from /{NS}/pma/state' in export
    lines = (tmp_path / 's1.csv').read_text().splitlines()
    assert any(line.startswith('#   note: cli test') for line in lines)
    rows = list(csv.DictReader(line for line in lines if not line.startswith('#')))
    assert len(rows) == states
    predicted = [r for r in rows if r['predicted_length_m']]
    if len(predicted) <= 0.8 * len(rows):
        # Say whether the predictions are absent from the bag or NaN, and where in the sweep.
        with AnyReader([bag]) as reader:
            stamps = {(m.header.stamp.sec, m.header.stamp.nanosec): m.predicted_length_m
                      for c, _, raw in reader.messages()
                      if c.topic == f'/{NS}/pma/prediction'
                      for m in [reader.deserialize(raw, c.msgtype)]}
        without = [(r['seq'], r['time_s'], 'NaN' if tuple(map(int, r['stamp_s'].split('.')))
                    in stamps else 'absent') for r in rows if not r['predicted_length_m']]
        pytest.fail(f'{len(without)} of {len(rows)} states without a prediction '
                    f'({len(stamps)} predictions in the bag): {without}')
    assert max(float(r['gauge_setpoint_pa']) for r in rows) == 100_000.0
    for row in predicted:
        assert math.isclose(float(row['residual_m']),
                            float(row['length_m']) - float(row['predicted_length_m']),
                            abs_tol=1e-12) if row['length_m'] else True


def test_sweep_profiles_from_flags_stream_their_setpoints_and_a_wrong_flag_is_refused(
        rig, tmp_path):
    probe = rig['probe']

    def settled_at_zero() -> int:
        """Until the probe has seen the profile's final 0 Pa (its stream lags the answer);
        the index of the next state."""
        wait_until(lambda: probe.states and probe.states[-1].gauge_setpoint_pa == 0.0, 10,
                   'a state with setpoint 0 after the profile')
        return len(probe.states)

    start = settled_at_zero()
    out = ok(pma('sweep', '--profile', 'sine', '--amplitude', '100kPa', '--offset', '150kPa',
                 '--frequency', '0.5Hz', '--cycles', '2'))
    assert 'sine 150 kPa +/- 100 kPa at 0.5 Hz, 2 period(s)' in out and 'sweep succeeded' in out
    end = settled_at_zero()
    setpoints = [state.gauge_setpoint_pa for state in probe.states[start:end]]
    assert 245_000.0 < max(setpoints) <= 250_000.0
    # ~80 setpoints streamed at 20 Hz, seen through 20 Hz states (a busy machine merges some);
    # the same path as a staircase would change a handful of times.
    changes = sum(1 for before, after in itertools.pairwise(setpoints) if after != before)
    assert changes > 20, f'{changes} setpoint changes: not a streamed sine'

    profile = tmp_path / 'profile.csv'
    profile.write_text('time_s,gauge_pressure_pa\n0,0\n1,120000\n2,0\n')
    start = settled_at_zero()
    out = ok(pma('sweep', '--profile', 'csv', '--csv', str(profile)))
    assert 'profile of 3 points over 2.0 s' in out and 'sweep succeeded' in out
    end = settled_at_zero()
    # The stream samples the line at 20 Hz: the peak itself only if a tick lands on t = 1 s.
    assert 100_000.0 < max(state.gauge_setpoint_pa for state in probe.states[start:end]) \
        <= 120_000.0

    start = settled_at_zero()
    # A goal the driver's checks refuse is refused by pma itself, with the flag, exit 2 ...
    refused = pma('sweep', '--profile', 'ramp', '--max', '300kPa')
    assert refused.returncode == 2 and 'ramp_rate_pa_s must be > 0 Pa/s' in refused.stderr \
        and '(--rate); nothing was sent' in refused.stderr, refused
    assert refused.stdout == '', refused
    # ... but for the driver's ceiling, its parameter: the driver refuses that one, exit 1.
    above = pma('sweep', '--max', '600kPa', '--step', '100kPa')
    assert above.returncode == 1 and 'above the driver ceiling' in above.stderr, above
    assert 'sweep aborted' not in above.stdout, above       # a refusal goes to stderr
    assert all(state.gauge_setpoint_pa == 0.0 for state in probe.states[start:])


def test_ctrl_c_cancels_the_sweep_and_the_driver_vents(rig):
    proc = popen_in_own_group([str(PMA), 'sweep', '--max', '300kPa', '--step', '100kPa',
                               '--hold', '3s', '--namespace', NS], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    try:
        probe = rig['probe']
        wait_until(lambda: probe.states[-1].gauge_setpoint_pa >= 100_000.0, 30,
                   'the sweep at its second step')
        os.killpg(proc.pid, signal.SIGINT)                   # what Ctrl-C sends
        time.sleep(0.02)
        proc.send_signal(signal.SIGINT)                      # impatient: a second one
        out, _ = proc.communicate(timeout=30)
    finally:
        kill_own_group(proc)
    assert proc.returncode == 130, out
    assert 'cancelling the driver goal' in out and 'sweep cancelled' in out and 'vented' in out
    assert 'Traceback' not in out
    wait_until(lambda: probe.states[-1].gauge_setpoint_pa == 0.0, 10, 'the device vented')


def test_set_sweep_and_vent_release_a_controller_that_holds_a_length(rig):
    unreachable = pma('move', '35cm')
    assert unreachable.returncode == 1 and 'move aborted: target 35.00 cm is not reachable: ' \
        'reachable ' in unreachable.stderr, unreachable
    assert unreachable.stdout == '', unreachable      # no "moving to 35.00 cm" before it
    probe = rig['probe']

    def hold() -> None:
        out = ok(pma('move', '27.5cm', '--goal-timeout', '20s'))
        assert out.startswith('moving to 27.50 cm\n') and 'move succeeded' in out, out
        wait_until(lambda: probe.control[-1].mode != ControlState.MODE_IDLE, 5, 'a target held')

    def released(out: str) -> None:
        # pma releases the controller it has discovered by then and says so; one it learns of
        # later (DDS discovery) lets go by itself when another command comes.
        assert 'released the length controller (it held 27.50 cm)' in out or \
            'released the target' in rig['controller'].output, out
        wait_until(lambda: probe.control[-1].mode == ControlState.MODE_IDLE, 5,
                   'the controller idle')

    # The held length's controller overwrote `pma set`'s setpoint at its next sample.
    hold()
    # Its diagnostics say `holding 0.2750 m`: shown in cm, as the target beside it.
    assert 'control   OK holding 27.50 cm | mode hold | target 27.50 cm' in ok(pma('status'))
    out = ok(pma('set', '100kPa', '--wait', '--timeout', '5s'))
    released(out)
    assert 'setpoint 100.0 kPa taken' in out and 'reached' in out
    assert probe.fresh_state().gauge_setpoint_pa == 100_000.0
    # ... and took the muscle back, pressurised, once a sweep had ended.
    hold()
    # A sweep the driver would refuse (no --max) is refused before anything is sent: the
    # held length stays held (it used to be released, then the goal refused).
    refused = pma('sweep', '--step', '100kPa')
    assert refused.returncode == 2 and '(--max); nothing was sent' in refused.stderr, refused
    time.sleep(1.0)
    assert probe.control[-1].mode != ControlState.MODE_IDLE
    out = ok(pma('sweep', '--max', '100kPa', '--step', '100kPa', '--hold', '0.5s'))
    released(out)
    assert 'sweep succeeded' in out
    time.sleep(1.0)                       # a holding controller commands with every sample
    assert probe.fresh_state().gauge_setpoint_pa == 0.0
    assert probe.control[-1].mode == ControlState.MODE_IDLE
    hold()
    out = ok(pma('vent', '--wait'))
    released(out)
    assert probe.fresh_state().gauge_setpoint_pa == 0.0


def test_watch_prints_one_line_per_sample_and_ctrl_c_is_interrupted(rig):
    # The default limit (20 Hz) on the rig's 20 Hz stream: every sample (it showed every other
    # one when it compared stamps 49.999999 ms apart with 50 ms).
    out = ok(pma('watch', '--count', '20', '--si'))
    lines = out.splitlines()
    assert lines[0].split()[:3] == ['time_s', 'seq', 'gauge_pressure_pa']
    seqs = [int(line.split()[1]) for line in lines[1:]]
    assert len(seqs) == 20 and seqs == sorted(seqs) and seqs[-1] - seqs[0] <= 19 + 2, seqs
    assert all(len(line.split()) == 9 for line in lines[1:])
    # For people: a sample without a prediction (the first ones, published before pma's
    # subscription was matched) shows '-' in the model column, not 'nan'; later ones join.
    human = ok(pma('watch', '--count', '60')).splitlines()
    assert human[0].split()[:2] == ['t', '[s]']
    model_cells = [line.split()[5] for line in human[1:]]
    assert len(model_cells) == 60
    assert all(cell == '-' or math.isfinite(float(cell)) for cell in model_cells), model_cells
    assert model_cells[-1] != '-', model_cells
    proc = popen_in_own_group([str(PMA), 'watch', '--namespace', NS],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killer = threading.Timer(30, proc.kill)             # should the lines never come
    killer.start()
    try:
        for _ in range(3):                               # the header and two samples
            proc.stdout.readline()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        killer.cancel()
        kill_own_group(proc)
    assert proc.returncode == 130, err
    assert 'pma watch: ' in err and 'Traceback' not in err


def test_run_is_ros2_run(rig, tmp_path):
    out = ok(pma('run', 'pma_bag', 'info', '--help'))
    assert 'usage:' in out
    missing = pma('run', 'pma_bag', 'no_such_exe')
    assert missing.returncode == 2 and 'record' in missing.stderr


def test_export_errors_are_one_line(tmp_path):
    result = pma('export', str(tmp_path / 'missing'), '--csv', str(tmp_path / 'x.csv'))
    assert result.returncode == 1 and result.stderr.strip().count('\n') == 0
    assert 'no such bag' in result.stderr


# -- calibration -----------------------------------------------------------------------------

class Typist:
    """`pma calibrate` at a terminal: reads its prompts, types what the instruments show."""

    def __init__(self, argv: list[str], cwd: Path):
        self.proc = popen_in_own_group(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, cwd=cwd)
        self.output = ''
        self._read = 0                  # what was answered: prompts after it are new
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        while chunk := os.read(self.proc.stdout.fileno(), 4096):
            with self._cond:
                self.output += chunk.decode('utf-8', errors='replace')
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def expect(self, prompt: str, timeout: float = 60.0) -> None:
        """Until `prompt` is on the screen after what was answered last."""
        with self._cond:
            found = self._cond.wait_for(
                lambda: prompt in self.output[self._read:] or not self._reader.is_alive(),
                timeout)
            at = self.output.find(prompt, self._read)
            assert found and at >= 0, f'no {prompt!r}:\n{self.output}'
            self._read = at + len(prompt)

    def type(self, answer: str) -> None:
        self.proc.stdin.write(f'{answer}\n'.encode())
        self.proc.stdin.flush()

    def finish(self, timeout: float = 60.0) -> tuple[int, str]:
        try:
            self.proc.wait(timeout)
        finally:
            kill_own_group(self.proc)
        self._reader.join(5)
        return self.proc.returncode, self.output


def truth_now(truth: Path, samples: int) -> tuple[float, float]:
    """Mean true (length_m, gauge_pressure_pa) of the rig's latest samples: tape and gauge."""
    rows = list(csv.DictReader(truth.read_text().splitlines()))[-samples:]
    return (statistics.fmean(float(r['true_length_m']) for r in rows),
            statistics.fmean(float(r['true_gauge_pressure_pa']) for r in rows))


def driver_parameter(name: str, namespace: str = NS) -> float:
    out = ok(pma('param', 'get', 'driver_node', name, '--timeout', '20s', namespace=namespace))
    return float(out.split(' = ', 1)[1].split()[0])


WRONG_SPAN = {'calibration.volts_at_full': '4.3'}       # reads 5 % high: 316 kPa at 300 kPa
WRONG_OFFSET = {'calibration.length_offset_m': '0.42'}  # every length 2 cm long
TRUE_SENSORS = {'calibration.volts_at_full': 4.5, 'calibration.length_offset_m': 0.40}


@pytest.fixture
def miscalibrated(rig):
    """The rig's driver with a wrong span and offset; set back to the true sensors after."""
    for name, value in {**WRONG_SPAN, **WRONG_OFFSET}.items():
        ok(pma('param', 'set', 'driver_node', name, value))
    yield rig
    for name, value in TRUE_SENSORS.items():
        ok(pma('param', 'set', 'driver_node', name, repr(value)))
    ok(pma('param', 'set', 'driver_node', 'calibration.tare_offset_pa', '0'))


def test_calibrate_finds_the_true_sensors_from_a_gauge_and_a_tape(miscalibrated, tmp_path,
                                                                   module_procs):
    rig = miscalibrated
    params_out, bag = tmp_path / 'rig_calibration.yaml', tmp_path / 'runs' / 'calibration'
    typist = Typist([str(PMA), 'calibrate', '--namespace', NS, '--yes', '--check-pressure',
                     '300kPa', '-o', 'rig_calibration.yaml', '--bag', 'runs/calibration'],
                    cwd=tmp_path)
    samples = 40                                   # the 2 s the routine averages, at 20 Hz
    typist.expect('Reference gauge reading')
    typist.expect(': ')
    _, gauge_pa = truth_now(rig['truth'], samples)
    assert 280_000.0 < gauge_pa < 320_000.0
    typist.type(f'{gauge_pa / 1e3:.2f}kPa')
    typist.expect('Muscle length at rest by tape')
    typist.expect(': ')
    tape_m, at_rest_pa = truth_now(rig['truth'], samples)
    assert abs(at_rest_pa) < 5_000.0
    typist.type(f'{tape_m * 100:.2f}cm')
    code, out = typist.finish()
    assert code == 0, out
    assert 'Traceback' not in out and f'applied; wrote {params_out}' in out

    # The file holds the true sensors, found back from what the instruments read.
    written = yaml.safe_load(params_out.read_text())['/**']['ros__parameters']
    assert abs(written['calibration.volts_at_full'] - 4.5) < 0.01, written   # 0.25 % of span
    assert abs(written['calibration.length_offset_m'] - 0.40) < 0.002, written
    assert 'calibration.tare_offset_pa' not in written          # per session: not in a file
    # The driver took it, and its lengths are the true ones again.
    for name in ('calibration.volts_at_full', 'calibration.length_offset_m'):
        assert driver_parameter(name) == written[name]
    probe = rig['probe']
    count = len(probe.states)
    wait_until(lambda: len(probe.states) > count + samples, 10, 'fresh states')
    truth = TruthLog.true_lengths(rig['truth'])
    errors = [s.length_m - truth[s.seq] for s in probe.states[count:]
              if s.seq in truth and math.isfinite(s.length_m)]
    assert len(errors) > samples / 2 and abs(statistics.fmean(errors)) < 0.002

    # The bag of the run says what was measured, what it was before and where the file is.
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['custom_data']
    assert float(custom['calibration.volts_at_full']) == written['calibration.volts_at_full']
    assert float(custom['previous.calibration.volts_at_full']) == 4.3
    assert float(custom['previous.calibration.length_offset_m']) == 0.42
    assert custom['calibration_params_file'] == str(params_out)
    assert any('reference gauge' in v for k, v in custom.items()
               if k.startswith('calibration_note.'))
    with AnyReader([bag]) as reader:
        assert sum(1 for c, _, _ in reader.messages() if c.topic == f'/{NS}/pma/state') > 100

    # A driver started with the file (port absent: parameters are there before the device).
    loader = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=[
        '-r', '__ns:=/cal_load', '-p', f'port:={tmp_path}/no_device', '--params-file',
        str(params_out)])
    try:
        for name in ('calibration.volts_at_full', 'calibration.length_offset_m'):
            assert driver_parameter(name, namespace='cal_load') == written[name]
    finally:
        loader.stop()


def test_ctrl_c_at_the_gauge_prompt_vents_and_changes_nothing(rig, tmp_path):
    names = ('calibration.volts_at_full', 'calibration.length_offset_m')
    before = {name: driver_parameter(name) for name in names}
    typist = Typist([str(PMA), 'calibrate', '--namespace', NS, '--yes', '--check-pressure',
                     '300kPa', '-o', 'out.yaml'], cwd=tmp_path)
    try:
        typist.expect('Reference gauge reading')
        typist.expect(': ')
        probe = rig['probe']
        assert probe.fresh_state().gauge_setpoint_pa == 300_000.0, 'inflated for the check'
        os.kill(typist.proc.pid, signal.SIGINT)            # Ctrl-C while input() waits
        code, out = typist.finish(30)
        assert code == 130, out
        assert 'interrupted: vented; no parameter changed' in out and 'Traceback' not in out
        assert probe.fresh_state().gauge_setpoint_pa == 0.0
        assert not (tmp_path / 'out.yaml').exists()
        assert {name: driver_parameter(name) for name in names} == before
    finally:
        ok(pma('param', 'set', 'driver_node', 'calibration.tare_offset_pa', '0'))


def test_calibrate_refuses_a_result_out_of_bounds_and_changes_nothing(rig, tmp_path):
    # A check pressure too low to judge the span: refused before the tare and the inflation.
    tare = driver_parameter('calibration.tare_offset_pa')
    low = pma('calibrate', '--check-pressure', '10kPa', '--yes', '-o', str(tmp_path / 'x.yaml'))
    assert low.returncode == 2 and 'refused: a check pressure of 10.0 kPa is too close to zero' \
        in low.stderr and 'check at 100 kPa or more' in low.stderr, low
    assert '1/3 pressure zero' not in low.stdout, low              # step 1 never started
    assert driver_parameter('calibration.tare_offset_pa') == tare
    before = driver_parameter('calibration.length_offset_m')
    # Typed on stdin as a user would: first a wrong unit (asked again), then 5 m at rest.
    result = subprocess.run(
        [str(PMA), 'calibrate', '--skip-pressure', '--yes', '-o', 'out.yaml', '--namespace', NS],
        check=False, input='30kPa\n5m\n', capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert result.returncode == 1, result
    assert "'kPa' is not a unit of length" in result.stdout
    assert 'refused: 500.0 cm is not a muscle at rest' in result.stderr
    assert not (tmp_path / 'out.yaml').exists()
    assert driver_parameter('calibration.length_offset_m') == before
