"""The memory rules on minor loops, measured against the simulated rig (docs/model.md, §3).

The truth is the rig's Preisach muscle (pma_driver.sim), a family the model does not
contain; each model is fitted to the major loop only (the shipped defaults, from Table 1)
and must predict the minor loops. Two runs: the Sweep action's staircase with reversals,
through the simulated device (valves, 10-bit sensor with its noise), and a dense path with
26 nested reversals on the muscle alone. Errors are in % of the stroke.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from pma_driver import protocol
from pma_driver.calibration import PressureCalibration
from pma_driver.sim.device import DeviceConfig, SimDevice
from pma_driver.sim.muscle import PreisachMuscle
from pma_driver.sweep import plan_sweep
from pma_model.params import default_params

MEMORIES = ('switch', 'madelung', 'play')
FORMS = ('sigmoid', 'hill')
# 0 -> 350 -> 150 -> 300 -> 200 -> 500 -> 100 -> 250 -> 0 kPa: loops on both branches
REVERSALS_PA = (350e3, 150e3, 300e3, 200e3, 500e3, 100e3, 250e3)
NESTED_TURNS_KPA = (0, 350, 150, 300, 200, 250, 0, 500, 100, 400, 250, 500, 0, 200, 50, 450,
                    300, 350, 0, 250, 150, 220, 180, 500, 380, 460, 420, 0)


def staircase_through_the_device(hold_ms: int = 1000, step_pa: float = 50e3):
    """(measured gauge pressure, true length) per 50 Hz sample of a staircase sweep."""
    device = SimDevice(DeviceConfig(rate_hz=50, seed=5))
    decoder = protocol.FrameDecoder()
    sensor = PressureCalibration()
    plan = plan_sweep(500e3, step_pa, hold_ms / 1000, 1, list(REVERSALS_PA), ceiling_pa=500e3)
    pressures, lengths = [], []

    def run(ms: int) -> None:
        for t in range(ms):
            if t % 200 == 0:
                device.receive(protocol.encode_command(protocol.Command.HEARTBEAT))
            device.advance(1)
            for frame in decoder.feed(b''.join(device.take_output())):
                if isinstance(frame, protocol.Sample):
                    pressures.append(sensor.adc_to_pa(frame.adc))
                    lengths.append(device.rig.length_m)

    for setpoint in plan.setpoints_pa:
        device.receive(protocol.encode_command(protocol.Command.SET, round(setpoint)))
        run(400)          # the valves move the pressure to the step
        run(hold_ms)
    return np.array(pressures), np.array(lengths)


def nested_path_on_the_muscle(step_pa: float = 1e3):
    turns = np.array(NESTED_TURNS_KPA) * 1e3
    path = np.concatenate([[turns[0]]] + [
        np.linspace(a, b, max(1, round(abs(b - a) / step_pa)) + 1)[1:]
        for a, b in itertools.pairwise(turns)])
    muscle = PreisachMuscle()
    return path, np.array([muscle.update(p) for p in path])


def errors_pct(pressures, truth):
    """{(form, memory): (rmse %, max %, largest step between samples [mm])}."""
    stroke = truth.max() - truth.min()
    table = {}
    for form, memory in itertools.product(FORMS, MEMORIES):
        model = replace(default_params(), branch_form=form, memory=memory).build_model()
        predicted = model.predict(pressures)
        error = 100 * (predicted - truth) / stroke
        table[form, memory] = (float(np.sqrt(np.mean(error ** 2))),
                               float(np.max(np.abs(error))),
                               float(1000 * np.max(np.abs(np.diff(predicted)))))
    return table


def report(title, table):
    lines = [f'\n{title}: RMSE / max error in % of stroke, largest jump between samples',
             *(f'  {form:8s} {memory:9s} {rmse:5.2f} / {worst:5.2f} %   {jump:5.2f} mm'
               for (form, memory), (rmse, worst, jump) in table.items())]
    print('\n'.join(lines))


@pytest.fixture(scope='module')
def staircase_table():
    table = errors_pct(*staircase_through_the_device())
    report('Sweep staircase with reversals, through the simulated device', table)
    return table


@pytest.fixture(scope='module')
def nested_table():
    table = errors_pct(*nested_path_on_the_muscle())
    report('26 nested reversals at 1 kPa steps, on the muscle', table)
    return table


@pytest.mark.parametrize('form', FORMS)
def test_memory_rules_remove_the_jump_at_reversals(nested_table, form):
    # switch jumps by the loop width (about 5 mm) when the detector flips; the others are
    # continuous: one 1 kPa step moves them by at most the branches' slope (~0.25 mm).
    assert nested_table[form, 'switch'][2] > 4.0
    assert nested_table[form, 'madelung'][2] < 0.3
    assert nested_table[form, 'play'][2] < 0.3


@pytest.mark.parametrize('form', FORMS)
def test_play_is_never_worse_than_the_papers_switch(staircase_table, nested_table, form):
    # The default memory: the worst error never above switch's, the RMSE no more than a
    # rounding above it (on 50 kPa staircases both have converged by the hold).
    for table in (staircase_table, nested_table):
        switch, play = table[form, 'switch'], table[form, 'play']
        assert play[1] <= switch[1] + 1e-9 and play[0] < switch[0] + 0.1, (form, switch, play)
    assert nested_table[form, 'play'][1] < 0.75 * nested_table[form, 'switch'][1]


DOCUMENTED = {   # docs/model.md §3: (rmse %, max %) on the staircase and on the nested path
    ('sigmoid', 'switch'): ((2.99, 6.89), (3.25, 9.82)),
    ('sigmoid', 'madelung'): ((3.17, 6.97), (3.43, 9.54)),
    ('sigmoid', 'play'): ((3.04, 6.89), (3.14, 6.82)),
    ('hill', 'switch'): ((1.71, 6.09), (2.05, 8.49)),
    ('hill', 'madelung'): ((2.09, 4.45), (2.18, 6.99)),
    ('hill', 'play'): ((1.74, 4.18), (1.80, 4.01)),
}


def test_figures_stay_where_the_docs_put_them(staircase_table, nested_table):
    # Within +/-0.3 percentage points, so a change that moves them fails here and gets
    # docs/model.md updated with it.
    for key, (staircase, nested) in DOCUMENTED.items():
        for table, (rmse, worst) in ((staircase_table, staircase), (nested_table, nested)):
            assert table[key][0] == pytest.approx(rmse, abs=0.3), key
            assert table[key][1] == pytest.approx(worst, abs=0.3), key
