"""refit checks what it fits, on sweeps recorded by the simulated rig (issue 46).

fake_arduino, driver_node and an idle recorder as processes; the muscle set to 200 kPa (a
setpoint on pma/pressure_setpoint, as `pma set 200kPa --wait` sends it), then a staircase
Sweep goal with `start_pressurised` (0 -> 500 -> 0 kPa, 100 kPa steps, 1 s holds,
recorded by the action): its first 0 kPa level is reached from 200 kPa, so it lands on the
decreasing branch and the paper's L0 is the length at 100 kPa. `refit --strict` on that
bag prints the warnings, keeps them in the JSON (`data_checks`), exits 3 and writes no
params file. The same sweep from rest passes --strict with no data warning. Each refit runs
while the next sweep does.
"""

from __future__ import annotations

import json

import pytest
from rclpy.action import ActionClient
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import Float64

from pma_common import names
from pma_interfaces.action import Sweep
from pma_interfaces.msg import PmaState
from support.ros import SpinningNode, shutdown, wait_for_action_server, wait_until

# Two sweeps and two refits: about 50 s (at load 7 on two cores), so its module goes to a
# worker first.
pytestmark = [pytest.mark.integration, pytest.mark.slow]

EXIT_STRICT = 3     # refit --strict with data warnings (docs/refit.md)


def set_pressure(probe, publisher, states, pressure_pa: float) -> None:
    """What `pma set P --wait` does, without starting a process: the setpoint, then the
    measured pressure within 10 kPa of it."""
    def there() -> bool:
        publisher.publish(Float64(data=pressure_pa))
        return bool(states) and abs(states[-1].gauge_pressure_pa - pressure_pa) < 10e3
    wait_until(there, 20, f'the muscle at {pressure_pa / 1e3:.0f} kPa')


def sweep(probe, bag, *, start_pressurised: bool) -> None:
    client = ActionClient(probe.node, Sweep, names.SWEEP)
    wait_for_action_server(client)
    goal = Sweep.Goal(max_gauge_pressure_pa=500e3, step_pa=100e3, hold_s=1.0, cycles=1,
                      record=True, bag_path=str(bag), start_pressurised=start_pressurised)
    handle = probe.send_goal(client, goal, timeout=20)
    assert handle.accepted
    result = probe.in_executor(handle.get_result_async)
    wait_until(result.done, 90, 'the sweep result')
    client.destroy()
    assert result.result().result.success, result.result().result.message


@pytest.fixture(scope='module')
def refits(module_procs, tmp_path_factory):
    work = tmp_path_factory.mktemp('refit_checks')
    port = work / 'ttyPMA'
    fake = module_procs.ros2_run('pma_sim', 'fake_arduino', '--link', port, '--seed', '4')
    fake.wait_for_line('fake_arduino: device at', 20)
    recorder = module_procs.ros2_run('pma_bag', 'record', '--idle')
    driver = module_procs.ros2_run('pma_driver', 'driver_node', ros_args=['-p',
                                                                          f'port:={port}'])
    recorder.wait_for_line('recorder: idle', 30)
    driver.wait_for_line('active: publishing', 30)
    probe = SpinningNode('refit_checks_probe')
    states, _ = probe.collect(PmaState, names.STATE, qos_profile_sensor_data)
    setpoint = probe.node.create_publisher(Float64, names.PRESSURE_SETPOINT, 10)
    runs = {}
    try:
        for name, pressurised in (('pressurised', True), ('from_rest', False)):
            out = work / name
            set_pressure(probe, setpoint, states, 200e3 if pressurised else 0.0)
            sweep(probe, out / 'bag', start_pressurised=pressurised)
            args = [out / 'bag', '--no-holdout', '--strict', '--json', out / 'refit.json',
                    '--params-out', out / 'params.yaml']
            args += ['--plots', out / 'plots'] if pressurised else []
            runs[name] = (out, module_procs.ros2_run('pma_model', 'refit', *args,
                                                     name=f'refit_{name}'))
        done = {}
        for name, (out, proc) in runs.items():
            code = proc.popen.wait(120)
            proc.stop()
            done[name] = (out, code, proc.output)
    finally:
        probe.close()
        shutdown()
    return done


def test_a_sweep_started_pressurised_is_refused_by_strict(refits):
    out, code, output = refits['pressurised']
    assert code == EXIT_STRICT, output
    assert not (out / 'params.yaml').exists(), output
    assert '--strict: ' in output and f'{out / "params.yaml"} not written' in output
    report = json.loads((out / 'refit.json').read_text())
    checks = report['data_checks']
    found = {warning['check'] for warning in checks['warnings']}
    assert {'rest_level_missing', 'wrong_branch', 'rest_length'} <= found, checks['warnings']
    wrong = next(w for w in checks['warnings'] if w['check'] == 'wrong_branch')
    assert '(0 kPa): reached from above' in wrong['message']
    for warning in checks['warnings']:      # every one is in the console too
        assert f"! {warning['check']}: {warning['message']}" in output
    zero = next(level for level in checks['levels'] if level['target_kpa'] == 0)
    assert (zero['approach'], zero['fit_branch']) == ('from above', 'decreasing')
    assert (out / 'plots' / 'loop.png').exists()


def test_the_same_sweep_from_rest_has_no_such_warning(refits):
    """Nothing about the start, the branches or L0. A level the driver found not settled
    (the simulated rig on a loaded machine) would be a warning of its own, and --strict's."""
    out, code, output = refits['from_rest']
    report = json.loads((out / 'refit.json').read_text())
    found = [w['check'] for w in report['data_checks']['warnings']]
    assert set(found) <= {'not_settled'}, report['data_checks']['warnings']
    assert (report['data']['n_increasing'], report['data']['n_decreasing']) == (6, 5)
    if found:
        assert code == EXIT_STRICT, output
        return
    assert code == 0, output
    assert 'data checks: no warnings' in output
    text = (out / 'params.yaml').read_text()
    assert not text.startswith('# WARNING') and 'Written by refit' in text
