"""The user guide in its own order on the simulated rig (issue 46): real processes, real DDS.

Step 5 leaves the muscle at 200 kPa (`pma set 200kPa --wait`); step 7's quick staircase then
used to start from there: its "0 kPa" level, held 1 s, did not deflate the muscle and landed
on the falling branch, so the fit got 5 rising and 6 falling levels, refit pinned L0 at the
length seen at 100 kPa (29.15 cm, not 30.06 cm) and `pma_bag info` counted 2 sweeps. Now the
sweep vents and waits for rest before its first level, its bag begins at rest and holds the
driver's records of it, and `info` counts sweeps from those records.

fake_arduino + driver_node + model_node + an idle recorder as `ros2 run` starts them; `pma`
and the refit as a user types them; the bag read back with rosbags (an independent reader).
"""

from __future__ import annotations

import json
import subprocess
from collections import Counter

import pytest
import yaml
from rosbags.highlevel import AnyReader

from pma_common import experiment
from pma_sim.registry import muscle_family
from support.procs import INSTALL

pytestmark = [pytest.mark.integration, pytest.mark.slow]

PMA = INSTALL / 'pma_cli' / 'lib' / 'pma_cli' / 'pma'
REFIT = INSTALL / 'pma_model' / 'lib' / 'pma_model' / 'refit'
INFO = INSTALL / 'pma_bag' / 'lib' / 'pma_bag' / 'info'
# The length sensor's noise (HC-SR04: 1.5 mm a reading, 3 mm resolution), averaged over a
# hold's last half: the fitted L0 is the rest length to within a few mm.
L0_TOLERANCE_M = 0.003


def run(*argv, cwd, timeout: float = 90.0) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in argv], cwd=cwd, capture_output=True, text=True,
                            timeout=timeout, check=False, stdin=subprocess.DEVNULL)
    assert result.returncode == 0, f'{argv}: exit {result.returncode}\n{result.stdout}\n' \
                                   f'{result.stderr}'
    assert 'Traceback' not in result.stderr, result.stderr
    return result


def test_steps_5_7_and_9_in_order_give_the_rest_length_and_one_sweep(module_procs, tmp_path):
    port = tmp_path / 'pma0'
    recorder_cwd = tmp_path / 'recorder'
    recorder_cwd.mkdir()
    module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', port, '--seed', '7'
                          ).wait_for_line('device at', 20)
    driver = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=['-p', f'port:={port}'])
    model = module_procs.ros2_run('pma_model', 'model_node')
    recorder = module_procs.ros2_run('pma_bag', 'record', '--idle', cwd=recorder_cwd)
    driver.wait_for_line('active: publishing', 30)
    model.wait_for_line('model_node ready', 30)
    recorder.wait_for_line('idle', 30)

    # Step 5: is data flowing? The muscle is left at 200 kPa.
    out = run(PMA, 'set', '200kPa', '--wait', cwd=tmp_path).stdout
    assert 'reached' in out, out
    # Step 7: the quick staircase, recorded (the guide's exact command, bag under tmp_path).
    sweep = run(PMA, 'sweep', '--max', '500kPa', '--step', '100kPa', '--hold', '1s',
                '--record', 'runs/sweep1', '--muscle', 'm1', '--load-kg', '0', '--supply-kpa',
                '600', '--operator', 'me', cwd=tmp_path, timeout=120)
    assert 'sweep succeeded' in sweep.stdout, sweep.stdout + sweep.stderr
    assert 'venting to rest: ' in sweep.stderr, sweep.stderr
    bag = tmp_path / 'runs' / 'sweep1'

    # The bag's own account of the sweep, read by rosbags.
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == '/pma/sweep_record']
        assert connections, [c.topic for c in reader.connections]
        records = [reader.deserialize(data, conn.msgtype)
                   for conn, _, data in reader.messages(connections=connections)]
        first_state = next(reader.deserialize(data, conn.msgtype) for conn, _, data in
                           reader.messages(connections=[c for c in reader.connections
                                                        if c.topic == '/pma/state']))
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['custom_data']          # the methods section's facts
    assert {key: custom.get(key) for key in experiment.KEYS} == {
        'experiment.muscle': 'm1', 'experiment.load_kg': '0.0',
        'experiment.supply_gauge_pressure_pa': '600000.0', 'experiment.operator': 'me'}
    kinds = [r.kind for r in records]
    assert kinds == [0] + [1] * 11 + [2], kinds            # START, 11 LEVELs, END
    start, *levels, end = records
    assert len({r.sweep_id for r in records}) == 1
    assert start.started_at_rest and start.start_gauge_pressure_pa < 5_000.0
    assert end.message.startswith('succeeded: 11 steps done'), end.message
    branches = Counter(r.branch for r in levels)
    # 6 on the rising branch (the first 0 kPa from rest, then 100..500 kPa) and 5 falling.
    assert (branches[0], branches[1], branches[-1]) == (1, 5, 5), branches
    assert levels[0].branch == 0 and levels[0].target_gauge_pressure_pa == 0.0
    assert all(r.settled for r in levels), [r.message for r in levels if not r.settled]
    # The bag began at rest, not at step 5's 200 kPa.
    assert first_state.gauge_setpoint_pa == 0.0 and first_state.gauge_pressure_pa < 10_000.0

    # Step 9: refit (its L0 is the length at the lowest rising level: the rest length).
    report_path = tmp_path / 'refit.json'
    refit = run(REFIT, bag, '--json', report_path, '--no-holdout', cwd=tmp_path, timeout=120)
    assert '  muscle m1, load 0 kg, supply 600 kPa, operator me' in refit.stdout, refit.stdout
    report = json.loads(report_path.read_text())
    l0_m = report['data']['rest_length_cm'] / 100.0
    rest_m = muscle_family().rest_length_m
    assert abs(l0_m - rest_m) <= L0_TOLERANCE_M, (l0_m, rest_m)

    info = run(INFO, bag, cwd=tmp_path).stdout
    assert '  sweeps:         1 (1 succeeded; from /pma/sweep_record)' in info, info
    assert '  levels:         11 (1 at rest, 5 rising, 5 falling), all settled' in info, info
    assert 'experiment.muscle: m1' in info and 'experiment.operator: me' in info, info
