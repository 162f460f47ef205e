"""`pma plot BAG` on bags the real rig recorded: every sweep profile (recorded by the Sweep
action through an idle recorder), a length controller's move (a recorder recording), a
split zstd bag, one still being written and one whose recorder was SIGKILLed.

Each figure is checked as a user gets it: the process's exit and output, the PNG decoded
(not blank), and what its axes show, from the PNG's text chunk that `pma plot` writes
(bag_plot.RANGES_KEY: each axes' limits and each drawn line's ranges) against the bag's
own messages, read here with pma_bag and rclpy's deserialisation.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from rclpy.serialization import deserialize_message

from pma_bag import BagReader
from pma_interfaces.msg import ControlState, PmaState
from pma_model.offline.bag_plot import RANGES_KEY
from support.procs import INSTALL
from support.ros import SpinningNode, shutdown, wait_until

pytestmark = pytest.mark.integration

PMA = INSTALL / 'pma_cli' / 'lib' / 'pma_cli' / 'pma'
NS = 'plot'
PRESSURE = 'gauge pressure [kPa] vs time [s]'
LENGTH = 'muscle length L [cm] vs time [s]'
LOOP = 'muscle length L [cm] vs gauge pressure P [kPa]'


def pma(*args: str, cwd: Path | None = None, env: dict | None = None, timeout: float = 90.0):
    argv = [str(PMA), *args]
    if args[0] != 'plot':
        argv += ['--namespace', NS]
    return subprocess.run(argv, check=False, capture_output=True, text=True, timeout=timeout,
                          cwd=cwd, stdin=subprocess.DEVNULL, env=env)


def ok(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 0, f'exit {result.returncode}\n{result.stdout}\n{result.stderr}'
    assert 'Traceback' not in result.stderr, result.stderr
    return result.stdout


@pytest.fixture(scope='module')
def rig(module_procs, tmp_path_factory):
    work = tmp_path_factory.mktemp('plot_rig')
    port = work / 'pma'
    ns = ['-r', f'__ns:=/{NS}']
    module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port), '--seed', '7'
                          ).wait_for_line('device at', 20)
    driver = module_procs.ros2_run('pma_driver', 'driver_node',
                                   ros_args=[*ns, '-p', f'port:={port}'])
    model = module_procs.ros2_run('pma_model', 'model_node', ros_args=ns)
    recorder = module_procs.ros2_run('pma_bag', 'record', '--idle', ros_args=ns, cwd=work)
    controller = module_procs.ros2_run('pma_control', 'length_controller', ros_args=ns)
    driver.wait_for_line('active: publishing', 30)
    model.wait_for_line('model_node ready', 30)
    recorder.wait_for_line('idle', 30)
    controller.wait_for_line('length_controller ready', 30)
    # The controller publishes its state per pma/state sample: it hears the driver (a goal
    # sent before that aborts at once, on no usable sample).
    probe = SpinningNode('plot_probe')
    control, _ = probe.collect(ControlState, f'/{NS}/pma/control_state')
    wait_until(lambda: len(control) > 0, 30, 'the controller hearing pma/state')
    yield {'work': work, 'procs': module_procs, 'ns': ns}
    probe.close()
    shutdown()


def recorded_states(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """(pressure [kPa], finite lengths [cm]) of every PmaState in the bag."""
    with BagReader(bag) as reader:
        (topic,) = [name for name, info in reader.topics.items()
                    if info.type_name == 'pma_interfaces/msg/PmaState']
        states = [deserialize_message(m.data, PmaState) for m in reader.messages([topic])]
    pressure = np.array([s.gauge_pressure_pa for s in states]) / 1000.0
    length = np.array([s.length_m for s in states]) * 100.0
    return pressure, length[np.isfinite(length)]


def figure_of(png: Path) -> dict:
    """What the PNG's axes show; the image checked to be a drawn figure."""
    with Image.open(png) as image:
        ranges = json.loads(image.text[RANGES_KEY])
        assert 'recorded' in image.text['Description']           # the provenance footer
        grey = np.asarray(image.convert('L'), float)
    assert grey.shape[0] > 600 and grey.shape[1] > 1000
    assert grey.std() > 20 and (grey < 100).mean() > 0.005, 'a blank figure'
    return ranges


def covers(limits, values) -> bool:
    return limits[0] <= float(np.min(values)) and limits[1] >= float(np.max(values))


def check_figure(png: Path, bag: Path, top_kpa: float | None = None) -> dict:
    """The figure shows the bag's measured pressures and lengths, in kPa and cm, on axes
    that cover them (and the sweep's top, `top_kpa`)."""
    ranges = figure_of(png)
    pressure, length = recorded_states(bag)
    shown_p, shown_l, loop = ranges[PRESSURE], ranges[LENGTH], ranges[LOOP]
    assert shown_p['drawn']['measured']['y'] == pytest.approx(
        [pressure.min(), pressure.max()], abs=1e-9)
    assert shown_l['drawn']['measured']['y'] == pytest.approx(
        [length.min(), length.max()], abs=1e-9)
    assert covers(shown_p['ylim'], pressure) and covers(shown_l['ylim'], length)
    assert covers(loop['xlim'], pressure[np.isfinite(pressure)]) and covers(loop['ylim'], length)
    if top_kpa is not None:
        assert shown_p['ylim'][1] >= top_kpa and loop['xlim'][1] >= pressure.max()
        setpoint = shown_p['drawn']['setpoint (device)']['y']
        assert top_kpa - 10.0 < setpoint[1] <= top_kpa + 1e-9, setpoint
    assert 20.0 < length.min() <= length.max() < 31.0               # cm, not m
    return ranges


PROFILES = {
    'staircase': (['--max', '200kPa', '--step', '100kPa', '--hold', '1s'], 200.0),
    'sine': (['--profile', 'sine', '--amplitude', '80kPa', '--offset', '120kPa',
              '--frequency', '0.5Hz', '--cycles', '2'], 200.0),
    'ramp': (['--profile', 'ramp', '--max', '200kPa', '--rate', '200kPa/s'], 200.0),
    'csv': (['--profile', 'csv', '--csv', 'CSV'], 150.0),
    'forc': (['--profile', 'forc', '--max', '200kPa', '--step', '100kPa', '--forc-count', '1',
              '--hold', '0.5s'], 200.0),
}


@pytest.mark.parametrize('profile', PROFILES)
def test_a_sweep_of_each_profile_recorded_by_the_sweep_plots(rig, tmp_path, profile):
    flags, top_kpa = PROFILES[profile]
    csv = tmp_path / 'profile.csv'
    csv.write_text('time_s,gauge_pressure_pa\n0,0\n1,150000\n2,0\n')
    flags = [str(csv) if flag == 'CSV' else flag for flag in flags]
    out = ok(pma('sweep', *flags, '--record', 'runs/' + profile, cwd=tmp_path))
    assert 'sweep succeeded' in out, out
    bag = tmp_path / 'runs' / profile
    result = pma('plot', str(bag))
    out = ok(result)
    png = tmp_path / 'runs' / f'{profile}.png'                  # beside the bag
    assert out.startswith(f'{png}: ') and f'of /{NS}/pma/state' in out, out
    ranges = check_figure(png, bag, top_kpa)
    assert 'model prediction (model_node)' in ranges[LENGTH]['drawn']   # model_node ran
    assert "controller's target length" not in ranges[LENGTH]['drawn']  # it had no target


def test_a_controller_move_recorded_by_a_recorder_plots_its_target(rig, tmp_path):
    bag = tmp_path / 'move'
    recorder = rig['procs'].ros2_run('pma_bag', 'record', '-o', bag,
                                     ros_args=[*rig['ns'], '-r', '__node:=recorder_move'])
    recorder.wait_for_line('recorder: recording', 30)
    try:
        assert 'move succeeded' in ok(pma('move', '27.5cm', '--goal-timeout', '20s'))
    finally:
        ok(pma('vent', '--wait'))
        recorder.signal(signal.SIGINT)
        assert recorder.popen.wait(20) == 0, recorder.output
    out_png = tmp_path / 'figures' / 'move.png'
    out_png.parent.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ('DISPLAY', 'WAYLAND_DISPLAY')}
    result = pma('plot', str(bag), '-o', str(out_png), '--show', env=env)
    out = ok(result)
    assert "with the length controller's target" in out, out
    assert '--show: no display' in result.stderr and str(out_png) in result.stderr
    ranges = check_figure(out_png, bag)
    target = ranges[LENGTH]['drawn']["controller's target length"]['y']
    assert target == pytest.approx([27.5, 27.5])
    assert covers(ranges[LENGTH]['ylim'], target)


@pytest.mark.slow       # 41 s at load 10 on the 2-core VM (a recorder, a 4 s sine, two plots)
def test_a_split_zstd_bag_plots_whole_and_while_it_is_written(rig, tmp_path):
    bag = tmp_path / 'split'
    recorder = rig['procs'].ros2_run(
        'pma_bag', 'record', '-o', bag, '--compression', 'zstd', '--max-bag-duration', '2',
        ros_args=[*rig['ns'], '-r', '__node:=recorder_split'])
    recorder.wait_for_line('recorder: recording', 30)
    try:
        ok(pma('sweep', '--profile', 'sine', '--amplitude', '80kPa', '--offset', '100kPa',
               '--frequency', '0.5Hz', '--cycles', '2'))
        # Still being written: what is there so far (at least the flushed chunks).
        live = pma('plot', str(bag), '-o', str(tmp_path / 'live.png'))
        ok(live)
        assert 'unfinished or truncated' in live.stderr, live.stderr
        ranges = figure_of(tmp_path / 'live.png')
        assert ranges[PRESSURE]['drawn']['measured']['y'][1] > 150.0
    finally:
        recorder.signal(signal.SIGINT)
        assert recorder.popen.wait(20) == 0, recorder.output
    assert len(list(bag.glob('split_*.mcap'))) >= 2
    with BagReader(bag) as reader:
        assert reader.compressions == {'zstd'} and not reader.truncated
    out = ok(pma('plot', str(bag)))
    check_figure(tmp_path / 'split.png', bag, 180.0)
    assert 'truncated' not in out


def test_a_bag_whose_recorder_was_killed_plots_what_reached_the_disk(rig, tmp_path):
    bag = tmp_path / 'killed'
    recorder = rig['procs'].ros2_run('pma_bag', 'record', '-o', bag,
                                     ros_args=[*rig['ns'], '-r', '__node:=recorder_killed'])
    recorder.wait_for_line('recorder: recording', 30)
    ok(pma('set', '120kPa', '--wait'))
    ok(pma('vent'))
    recorder.signal(signal.SIGKILL)
    recorder.popen.wait(10)
    assert not (bag / 'metadata.yaml').exists()
    result = pma('plot', str(bag))
    ok(result)
    assert 'unfinished or truncated' in result.stderr, result.stderr
    ranges = check_figure(tmp_path / 'killed.png', bag)
    assert math.isclose(ranges[PRESSURE]['drawn']['setpoint (device)']['y'][1], 120.0)


def test_a_missing_bag_or_directory_is_one_line(tmp_path):
    missing = pma('plot', str(tmp_path / 'nothing'))
    assert missing.returncode == 1 and missing.stderr.startswith('pma plot: ') \
        and 'no such bag' in missing.stderr and 'Traceback' not in missing.stderr, missing
    nowhere = pma('plot', str(tmp_path), '-o', str(tmp_path / 'no' / 'x.png'))
    assert nowhere.returncode == 2 and 'there is no directory' in nowhere.stderr, nowhere


def test_a_recorded_move_carries_the_experiment_and_its_bag_is_finished_after_ctrl_c(rig,
                                                                                    tmp_path):
    """`pma move --record` writes the move into its own bag through the idle recorder, with
    the experiment's facts and the goal in custom_data, shown in `pma_bag info` and on the
    plot; a Ctrl-C mid-move cancels the goal and still finishes the bag."""
    flags = ['--muscle', 'm7', '--load-kg', '1.5', '--supply-kpa', '600', '--operator', 'ada',
             '--note', 'after re-tare']
    out = ok(pma('move', '27.5cm', '--goal-timeout', '20s', '--record', 'runs/move', *flags,
                 cwd=tmp_path))
    bag = tmp_path / 'runs' / 'move'
    assert f'recording to {bag}' in out and 'move succeeded' in out, out
    assert f'to {bag}' in out.splitlines()[-1] and 'recorded ' in out.splitlines()[-1], out
    with BagReader(bag) as reader:
        data = reader.custom_data
        topics = {name.rsplit('/', 1)[-1] for name in reader.topics}
    assert data['experiment.muscle'] == 'm7' and data['experiment.load_kg'] == '1.5'
    assert data['experiment.supply_gauge_pressure_pa'] == '600000.0'
    assert data['experiment.operator'] == 'ada' and data['note'] == 'after re-tare'
    assert float(data['move.length_m']) == pytest.approx(0.275)
    assert float(data['move.timeout_s']) == 20.0 and float(data['move.settle_s']) == 0.0
    assert {'state', 'control_state'} <= topics, topics
    info = subprocess.run([str(INSTALL / 'pma_bag' / 'lib' / 'pma_bag' / 'info'), str(bag)],
                          capture_output=True, text=True, timeout=60, check=True).stdout
    assert 'experiment.muscle: m7' in info and 'move.length_m: 0.275' in info, info
    ok(pma('plot', str(bag)))
    with Image.open(tmp_path / 'runs' / 'move.png') as image:
        assert 'experiment.muscle=m7' in image.text['Description']

    # Interrupted: the goal is cancelled and the bag still finished (metadata.yaml written).
    stopped = tmp_path / 'runs' / 'stopped'
    move = rig['procs'].ros2_run('pma_cli', 'pma', 'move', '25.5cm', '--settle', '8s',
                                 '--record', str(stopped), '--muscle', 'm7', '--namespace', NS,
                                 name='pma_move_recorded')
    try:
        move.wait_for_line('moving to', 30)
        move.signal(signal.SIGINT)                      # what Ctrl-C sends
        assert move.popen.wait(20) == 130, move.output
    finally:
        ok(pma('vent', '--wait'))
    assert f'to {stopped}' in move.output and 'move cancelled' in move.output, move.output
    assert (stopped / 'metadata.yaml').is_file()
    with BagReader(stopped) as reader:
        assert reader.custom_data['experiment.muscle'] == 'm7'
        assert reader.message_count > 0
