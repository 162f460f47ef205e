"""SweepRunner against the simulated device, in simulated time (no ROS, no threads).

The device is the real SimDevice (firmware rules, valves, sensor noise) behind an in-memory
link (sim_link.py); the clock is the device's, so a timeout is exact and a minute-long
sweep runs in well under a second.
"""

from __future__ import annotations

import itertools
import json
import logging
import math

import pytest
from sim_link import SimClock, SimLink

from pma_common.calibration import PressureCalibration
from pma_common.protocol import Command
from pma_common.sweep import STREAM_RATE_HZ, plan_goal
from pma_driver.command_gate import DeviceControl
from pma_driver.sweep_runner import (
    PHASE_REST,
    PHASE_RUNNING,
    Branch,
    Outcome,
    RecorderError,
    RecordingSummary,
    RecordKind,
    SweepGoal,
    SweepProgress,
    SweepRecord,
    SweepRunner,
    SweepSettings,
)
from pma_sim.device import DeviceConfig, SimDevice
from pma_sim.pneumatics import PneumaticParams

pytestmark = pytest.mark.in_process

SENSOR = PressureCalibration()
SETTINGS = SweepSettings(tolerance_pa=10_000.0, step_timeout_s=5.0)
CALIBRATION = {'calibration.volts_at_zero': 0.5, 'calibration.volts_at_full': 4.5}


class ListRecorder:
    """Keeps what the runner asked of it, with the device time and the commands sent so far."""

    def __init__(self, rig: Rig, fail_start: str = '', fail_stop: str = '',
                 fail_check: str = ''):
        self.rig = rig
        self.fail_start = fail_start
        self.fail_stop = fail_stop
        self.fail_check = fail_check
        self.calls: list[tuple[str, int, int, object]] = []
        self.records_by: dict[str, int] = {}     # call: how many records had come by then

    def _note(self, call: str, detail) -> None:
        self.calls.append((call, self.rig.device.t_ms, len(self.rig.link.sent), detail))
        self.records_by[call] = len(self.rig.records)

    def check(self):
        if self.fail_check:
            raise RecorderError(self.fail_check)

    def start(self, bag_path, custom_data):
        self._note('start', (bag_path, dict(custom_data)))
        if self.fail_start:
            raise RecorderError(self.fail_start)
        return f'/bags/{bag_path or "auto"}'

    def stop(self):
        self._note('stop', None)
        if self.fail_stop:
            raise RecorderError(self.fail_stop)
        return RecordingSummary(f'/bags/{self.calls[0][3][0] or "auto"}', 1234, 0)


class Rig:
    def __init__(self, **config):
        self.device = SimDevice(DeviceConfig(rate_hz=50, seed=3, **config))
        self.events: list[tuple[int, str]] = []
        self.samples = 0
        self.control = DeviceControl(500_000.0, on_event=self._event)
        self.link = SimLink(self.device, on_sample=self._on_sample)
        self.control.link = self.link
        self.control.active = True
        self.clock = SimClock(self.link)
        self.feedback: list[SweepProgress] = []
        self.on_feedback = None     # a test's hook into the run
        self.cancel_at_s = None
        self.recorder = None
        self.trace: list[tuple[float, float, int]] = []   # (device s, measured Pa, device SET)
        self.records: list[SweepRecord] = []

    def _event(self, level: int, message: str) -> None:
        self.events.append((level, message))

    def _on_sample(self, sample) -> None:
        self.samples += 1
        gauge_pa = SENSOR.adc_to_pa(sample.adc)
        self.control.note_sample(sample, gauge_pa)
        self.trace.append((sample.t_ms / 1000.0, gauge_pa, sample.setpoint_pa))

    def _on_feedback(self, progress: SweepProgress) -> None:
        self.feedback.append(progress)
        if self.on_feedback is not None:
            self.on_feedback(progress)

    def run(self, settings: SweepSettings = SETTINGS, **goal):
        """A staircase 0 -> 200 -> 0 kPa unless told otherwise; other profiles from scratch."""
        if goal.get('profile', 'staircase') == 'staircase':
            goal = {'max_gauge_pressure_pa': 200_000.0, 'step_pa': 100_000.0, 'hold_s': 1.0,
                    **goal}
        goal = {'cycles': 1, **goal}
        runner = SweepRunner(self.control, recorder=self.recorder,
                             sample_count=lambda: self.samples, clock=self.clock,
                             sleep=self.clock.sleep, on_event=self._event,
                             now_ns=lambda: round(self.clock() * 1e9))
        self.runner = runner
        return runner.run(
            SweepGoal(**goal), settings, feedback=self._on_feedback, calibration=CALIBRATION,
            cancel_requested=lambda: self.cancel_at_s is not None
            and self.clock() >= self.cancel_at_s, record=self.records.append)

    def sets(self) -> list[int]:
        return [args[0] for args in self.link.commands('SET')]

    def levels(self) -> list[SweepRecord]:
        return [r for r in self.records if r.kind is RecordKind.LEVEL]

    def timed_sets(self) -> list[tuple[float, int]]:
        """(device s, Pa) of every SET."""
        return [(ms / 1000.0, args[0]) for ms, name, args in self.link.sent if name == 'SET']

    def settle(self, seconds: float = 5.0) -> None:
        self.clock.sleep(seconds)

    def warnings(self) -> list[str]:
        return [m for level, m in self.events if level >= logging.WARNING]


@pytest.fixture
def rig():
    return Rig()


def test_a_sweep_steps_through_its_plan_and_holds_each_step(rig):
    report = rig.run()
    assert report.outcome is Outcome.SUCCEEDED and report.success, report.message
    assert report.message.startswith('5 steps done')
    assert rig.sets() == [0, 0, 100_000, 200_000, 100_000, 0]     # the first: to rest
    assert not rig.link.commands('VENT') and not rig.warnings()
    assert {f.step_index for f in rig.feedback} == set(range(5))
    progress = [f.progress for f in rig.feedback]
    assert progress == sorted(progress) and progress[-1] == 1.0
    # At rest already: the wait is one rest_time_s. Then each hold starts once the step is
    # reached: 5 holds of 1 s, plus the filling and venting.
    assert 6.0 < rig.clock() < 6.0 + 4.0
    # 50 Hz throughout, counted from the first step on (after the 1 s wait for rest), as
    # the sweep's bag holds them.
    assert report.sample_count == pytest.approx(50 * (rig.clock() - 1.0), abs=2)


def test_every_hold_is_at_its_setpoint(rig):
    held: dict[int, list[float]] = {}
    rig.on_feedback = lambda f: held.setdefault(f.step_index, []).append(
        rig.control.latest_gauge_pa - f.gauge_setpoint_pa)
    rig.run(hold_s=2.0)
    errors = [e for step in held.values() for e in step[1:]]     # [0]: the step was just sent
    assert errors and max(abs(e) for e in errors) < SETTINGS.tolerance_pa


def test_a_lost_set_reply_is_sent_once_more_and_the_sweep_goes_on(rig):
    rig.on_feedback = lambda f: f.step_index == 1 and f.progress < 0.3 and setattr(
        rig.link, 'lost_replies', 1)
    report = rig.run()
    assert report.success, report.message
    assert rig.sets() == [0, 0, 100_000, 200_000, 200_000, 100_000, 0]


def test_two_lost_replies_abort_and_vent(rig):
    def lose_the_next_two(f: SweepProgress) -> None:
        if f.step_index == 1 and rig.link.lost_replies == 0 and 200_000 not in rig.sets():
            rig.link.lost_replies = 2
    rig.on_feedback = lose_the_next_two
    report = rig.run()
    assert report.outcome is Outcome.ABORTED and report.vented
    assert report.message == ('SET 200000 Pa failed: no reply to SET within 0.5 s; vented')
    assert rig.sets() == [0, 0, 100_000, 200_000, 200_000]
    assert len(rig.link.commands('VENT')) == 1
    rig.settle()
    assert rig.device.setpoint_pa == 0 and rig.device.rig.pressure_pa < 5_000


def test_a_refused_step_aborts_and_vents(rig):
    # Another host lowers the device's ceiling mid-run: the next step is NAKed.
    rig.on_feedback = lambda f: f.step_index == 1 and rig.link.send(Command.MAX, 150_000)
    report = rig.run()
    assert report.outcome is Outcome.ABORTED and report.vented
    assert report.message == 'device refused SET 200000 Pa: NAK RANGE; vented'
    rig.settle()
    assert rig.device.setpoint_pa == 0 and rig.device.rig.pressure_pa < 5_000


def test_cancel_vents(rig):
    rig.cancel_at_s = 2.5
    report = rig.run(max_gauge_pressure_pa=400_000.0, hold_s=5.0)
    assert report.outcome is Outcome.CANCELED and report.message == 'canceled; vented'
    assert rig.clock() == pytest.approx(2.5, abs=0.05)
    assert rig.link.commands('VENT')
    rig.settle()
    assert rig.device.setpoint_pa == 0 and rig.device.rig.pressure_pa < 5_000


def test_a_deactivation_vents_and_no_set_follows_it(rig):
    rig.clock.on_tick = lambda t: t >= 2.5 and rig.control.active and rig.control.deactivate()
    report = rig.run(max_gauge_pressure_pa=400_000.0)
    assert report.outcome is Outcome.ABORTED
    assert report.message.startswith('driver deactivated; vented')
    first_vent = next(i for i, (_, name, _) in enumerate(rig.link.sent) if name == 'VENT')
    assert all(name != 'SET' for _, name, _ in rig.link.sent[first_vent:])
    rig.settle()
    assert rig.device.setpoint_pa == 0


def test_a_ceiling_lowered_mid_sweep_is_never_exceeded(rig):
    def lower(f: SweepProgress) -> None:
        if f.step_index == 1:
            rig.control.max_gauge_pressure_pa = 150_000.0
    rig.on_feedback = lower
    report = rig.run(max_gauge_pressure_pa=400_000.0)
    assert report.outcome is Outcome.ABORTED and report.vented
    assert 'step 200000 Pa is above max_gauge_pressure_pa 150000 Pa' in report.message
    assert max(rig.sets()) == 100_000


def test_a_step_the_supply_cannot_reach_times_out_and_the_hold_starts_anyway():
    rig = Rig(pneumatics=PneumaticParams(supply_pa=250_000.0))
    settings = SweepSettings(tolerance_pa=10_000.0, step_timeout_s=2.0)
    starts: dict[int, float] = {}
    rig.on_feedback = lambda f: starts.setdefault(f.step_index, rig.clock())
    report = rig.run(settings, max_gauge_pressure_pa=400_000.0, step_pa=200_000.0)
    assert report.success, report.message
    warning, level = rig.warnings()
    assert warning.startswith('sweep step 2: 400000 Pa not reached within 2 s (at 2')
    assert level.startswith('sweep level 2 (400 kPa): not settled: not reached within '
                            'sweep.step_timeout_s 2 s; 2')
    assert [r.settled for r in rig.levels()] == [True, True, False, True, True]
    # Step 3 starts after the timeout (2 s), the 1 s hold and one poll.
    assert starts[3] - starts[2] == pytest.approx(3.0, abs=0.05)


@pytest.mark.parametrize(('goal', 'words'), [
    ({'step_pa': 0.01}, 'goal refused: the plan has 40000001 steps'),
    ({'max_gauge_pressure_pa': 600_000.0}, 'goal refused: max_gauge_pressure_pa 600000 Pa is '
                                           'above the driver ceiling 500000 Pa'),
    ({'cycles': 0}, 'goal refused: cycles must be >= 1'),
])
def test_a_bad_goal_aborts_at_once_with_the_reason_and_commands_nothing(rig, goal, words):
    rig.link.send(Command.SET, 50_000)          # a manual setpoint: a refused goal leaves it
    sent = len(rig.link.sent)
    report = rig.run(**goal)
    assert report.outcome is Outcome.ABORTED and not report.vented
    assert report.message.startswith(words), report.message
    assert rig.link.sent[sent:] == [] and rig.clock() == 0.0
    assert rig.device.setpoint_pa == 50_000


def test_an_inactive_driver_commands_nothing(rig):
    rig.control.active = False
    report = rig.run()
    assert report.outcome is Outcome.ABORTED
    assert report.message == 'not started: driver not active'
    assert rig.link.sent == []


def test_a_second_sweep_while_one_runs_is_aborted_at_once(rig):
    second = []

    def start_another(f: SweepProgress) -> None:
        if f.step_index == 1 and not second:
            sent = len(rig.link.sent)
            second.append(rig.runner.run(SweepGoal(100_000.0, 50_000.0, 0.0, 1), SETTINGS))
            second.append(rig.link.sent[sent:])
    rig.on_feedback = start_another
    report = rig.run()
    assert report.success
    assert second[0].outcome is Outcome.ABORTED and 'another sweep is running' in \
        second[0].message
    assert second[1] == []                        # the running sweep was not disturbed
    assert not rig.control.sweep_running          # released at the end


def test_setpoints_are_refused_while_a_sweep_runs(rig):
    refusals = []
    rig.on_feedback = lambda f: refusals.append(rig.control.command_setpoint(300_000.0))
    rig.run()
    assert refusals and set(refusals) == {('sweep', 'a sweep is running')}
    assert 300_000 not in rig.sets()
    assert rig.control.command_setpoint(300_000.0) == ('', '')


# -- the start from rest, and the records -----------------------------------------------------


def pressurised(**config) -> Rig:
    """A rig left at 200 kPa, as `pma set 200kPa --wait` leaves it (user guide, step 5)."""
    rig = Rig(**config)
    rig.link.send(Command.SET, 200_000)
    rig.settle(3.0)
    assert rig.device.rig.pressure_pa > 190_000
    return rig


def mean_pressure(rig: Rig, start_s: float, end_s: float) -> float:
    values = [p for t, p, _ in rig.trace if start_s <= t < end_s]
    return sum(values) / len(values)


def test_a_sweep_vents_and_waits_for_rest_before_its_first_level():
    rig = pressurised()
    report = rig.run()
    assert report.success, report.message
    assert rig.sets() == [200_000, 0, 0, 100_000, 200_000, 100_000, 0]
    (_, vent_s), (_, first_level_s) = [(v, t) for t, v in rig.timed_sets()][1:3]
    # The first level (0 Pa) began only once the pressure had been below 5 kPa and flat for
    # 1 s: venting 200 kPa takes ~1.8 s to 5 kPa on the simulated exhaust (tau 0.5 s).
    assert first_level_s - vent_s > 2.0
    assert mean_pressure(rig, first_level_s - 1.0, first_level_s) < 5_000.0
    assert abs(mean_pressure(rig, first_level_s - 1.0, first_level_s - 0.5)
               - mean_pressure(rig, first_level_s - 0.5, first_level_s)) < 1_000.0
    phases = [f.phase for f in rig.feedback]
    assert phases[0] == PHASE_REST and phases[-1] == PHASE_RUNNING
    assert phases == sorted(phases, key=[PHASE_REST, PHASE_RUNNING].index)
    assert all(f.gauge_setpoint_pa == 0.0 for f in rig.feedback if f.phase == PHASE_REST)
    start, *levels, end = rig.records
    assert start.kind is RecordKind.START and start.started_at_rest
    assert start.start_gauge_pressure_pa < 5_000.0 and start.message.startswith('at rest: ')
    assert start.stamp_ns == pytest.approx(first_level_s * 1e9, abs=0.05e9)
    assert [r.branch for r in levels] == [Branch.REST, Branch.RISING, Branch.RISING,
                                          Branch.FALLING, Branch.FALLING]
    assert end.kind is RecordKind.END and end.message == 'succeeded: 5 steps done'


def test_the_old_order_is_what_the_records_show_with_start_pressurised():
    # start_pressurised: from the pressure it finds (the user guide's tester, before issue
    # 46): the first "0 kPa" level comes from 200 kPa and is on the decreasing branch.
    rig = pressurised()
    report = rig.run(start_pressurised=True)
    assert report.success, report.message
    assert rig.sets() == [200_000, 0, 100_000, 200_000, 100_000, 0]
    assert all(f.phase == PHASE_RUNNING for f in rig.feedback)
    start = rig.records[0]
    assert start.kind is RecordKind.START and not start.started_at_rest
    assert start.start_gauge_pressure_pa == pytest.approx(200_000, abs=10_000)
    assert 'started pressurised at 20' in start.message
    assert any('started pressurised' in m for _, m in rig.events)
    assert [r.branch for r in rig.levels()] == [Branch.FALLING, Branch.RISING, Branch.RISING,
                                                Branch.FALLING, Branch.FALLING]
    assert rig.recorder is None


def test_not_at_rest_in_time_aborts_with_the_reason_and_vents():
    # An exhaust that hardly lets air out (blocked): the muscle stays pressurised.
    rig = pressurised(pneumatics=PneumaticParams(vent_time_constant_s=1000.0))
    rig.recorder = ListRecorder(rig)
    settings = SweepSettings(tolerance_pa=10_000.0, step_timeout_s=5.0, rest_timeout_s=4.0)
    started_s = rig.clock()
    report = rig.run(settings, record=True)
    assert report.outcome is Outcome.ABORTED and report.vented
    assert report.message.startswith('not at rest within sweep.rest_timeout_s 4 s of venting '
                                     '(19'), report.message
    assert 'a blocked exhaust' in report.message and report.message.endswith('; vented')
    assert rig.clock() - started_s == pytest.approx(4.0, abs=0.1)
    assert rig.sets() == [200_000, 0] and rig.link.commands('VENT')
    assert rig.recorder.calls == []               # no bag: it would have begun at rest
    assert [(r.kind, r.message) for r in rig.records] == [
        (RecordKind.END, 'aborted: ' + report.message)]


def test_every_level_is_recorded_with_what_it_reached(rig):
    report = rig.run(hold_s=2.0)
    assert report.success, report.message
    levels = rig.levels()
    assert [r.level_index for r in levels] == list(range(5))
    assert {r.level_count for r in levels} == {5}
    assert [r.target_gauge_pressure_pa for r in levels] == [0, 100e3, 200e3, 100e3, 0]
    assert all(r.settled and r.message == '' for r in levels), levels
    for r in levels:
        assert abs(r.reached_gauge_pressure_pa - r.target_gauge_pressure_pa) < 5_000.0
        assert (r.hold_end_ns - r.hold_start_ns) / 1e9 == pytest.approx(2.0, abs=0.05)
        assert r.stamp_ns == r.hold_end_ns and r.profile == 'staircase'
    assert [r.kind for r in rig.records] == [RecordKind.START, *[RecordKind.LEVEL] * 5,
                                             RecordKind.END]


def test_a_hold_too_short_for_the_pressure_to_settle_is_recorded_as_not_settled():
    # A slow inlet (tau 10 s): each rising step times out after 0.5 s and its 0.5 s hold ends
    # with the pressure still climbing, far below the target; the last 0 Pa too (venting
    # 100 kPa to 10 kPa takes 1.2 s), while 200 -> 100 kPa is reached in 0.3 s.
    rig = Rig(pneumatics=PneumaticParams(fill_time_constant_s=10.0))
    settings = SweepSettings(tolerance_pa=10_000.0, step_timeout_s=0.5)
    report = rig.run(settings, hold_s=0.5)
    assert report.success, report.message
    levels = rig.levels()
    assert [r.settled for r in levels] == [True, False, False, True, False]
    for r in (*levels[1:3], levels[4]):
        assert abs(r.reached_gauge_pressure_pa - r.target_gauge_pressure_pa) > 10_000.0
        assert r.message.startswith('not settled: not reached within sweep.step_timeout_s '
                                    '0.5 s; '), r.message
        assert 'kPa from the target (sweep.tolerance_pa 10 kPa)' in r.message


def test_a_cancel_and_an_abort_end_with_an_end_record():
    rig = Rig()
    rig.recorder = ListRecorder(rig)
    rig.cancel_at_s = 3.5
    report = rig.run(record=True)
    assert report.outcome is Outcome.CANCELED
    end = rig.records[-1]
    assert end.kind is RecordKind.END and end.message == 'canceled: canceled; vented'
    # The END is in the bag: it came before the recorder was asked to stop.
    assert rig.recorder.records_by['stop'] == len(rig.records)
    assert rig.recorder.records_by['start'] == 0     # and START after the bag began
    assert rig.records[0].kind is RecordKind.START

    rig = Rig()
    rig.clock.on_tick = lambda t: t >= 3.5 and rig.control.active and rig.control.deactivate()
    report = rig.run()
    assert report.outcome is Outcome.ABORTED
    assert rig.records[-1].message == 'aborted: driver deactivated; vented'
    assert [r.kind for r in rig.records].count(RecordKind.END) == 1


def test_a_goal_that_commands_nothing_records_nothing(rig):
    report = rig.run(cycles=0)
    assert report.outcome is Outcome.ABORTED and rig.records == []


def test_a_streamed_profile_has_a_start_and_an_end_but_no_levels(rig):
    report = rig.run(**SINE)
    assert report.success, report.message
    assert [r.kind for r in rig.records] == [RecordKind.START, RecordKind.END]
    assert rig.records[0].profile == 'sine' and rig.records[0].started_at_rest


# -- recording -----------------------------------------------------------------------------


def test_a_recording_sweep_starts_the_bag_before_the_first_step_and_stops_it_after_the_last(
        rig):
    rig.recorder = ListRecorder(rig)
    report = rig.run(record=True, bag_path='major', note='new muscle, 20 degC',
                     reversal_pressures_pa=[])
    assert report.success, report.message
    assert report.bag_path == '/bags/major'
    assert report.message == '5 steps done; bag /bags/major: 1234 messages, 0 lost'
    (start, _, sent_before, (bag, data)), (stop, stopped_ms, sent_by_stop, _) = \
        rig.recorder.calls
    assert (start, stop, bag) == ('start', 'stop', 'major')
    # The bag starts at rest: after the vent (SET 0) and before the first level's SET.
    assert [args for _, name, args in rig.link.sent[:sent_before] if name == 'SET'] == [(0,)]
    assert sent_by_stop == len(rig.link.sent)
    assert stopped_ms == rig.device.t_ms
    assert data['note'] == 'new muscle, 20 degC'
    assert json.loads(data['sweep.setpoints_pa']) == [0, 100_000, 200_000, 100_000, 0]
    assert (data['sweep.step_pa'], data['sweep.hold_s'], data['sweep.cycles']) == (
        '100000.0', '1.0', '1')
    assert (data['device.firmware'], data['device.firmware_version'],
            data['device.protocol_version']) == ('fake_arduino', '0.1.0', '1')
    assert data['calibration.volts_at_zero'] == '0.5'


def test_without_a_recorder_the_goal_aborts_at_once_and_commands_nothing(rig):
    rig.recorder = ListRecorder(rig, fail_check='no recorder at /recorder/start: start one')
    report = rig.run(record=True)
    assert report.outcome is Outcome.ABORTED and not report.vented
    assert report.message == 'not started: no recorder at /recorder/start: start one'
    assert rig.link.sent == [] and rig.recorder.calls == [] and rig.records == []


def test_a_recorder_that_refuses_the_bag_after_the_wait_for_rest_leaves_the_muscle_vented():
    # The bag starts at rest, so the recorder's refusal (its path holds a bag) comes after
    # the vent: the goal aborts, says so, and the END record has it.
    rig = Rig()
    rig.link.send(Command.SET, 200_000)
    rig.settle(3.0)
    rig.recorder = ListRecorder(rig, fail_start='the recorder refused to start: b exists')
    report = rig.run(record=True, bag_path='b')
    assert report.outcome is Outcome.ABORTED and report.vented
    assert report.message == 'not started: the recorder refused to start: b exists; vented'
    assert rig.sets() == [200_000, 0] and rig.device.setpoint_pa == 0
    assert [r.kind for r in rig.records] == [RecordKind.END]
    assert rig.records[0].message == 'aborted: ' + report.message


def test_an_aborted_recording_sweep_vents_before_the_bag_is_closed(rig):
    rig.recorder = ListRecorder(rig)
    rig.cancel_at_s = 2.0
    report = rig.run(record=True)
    assert report.outcome is Outcome.CANCELED
    assert report.message == 'canceled; vented; bag /bags/auto: 1234 messages, 0 lost'
    _, _, sent_by_stop, _ = rig.recorder.calls[1]
    assert rig.link.sent[sent_by_stop - 1][1] == 'VENT'


def test_a_bag_that_could_not_be_finished_fails_the_goal(rig):
    rig.recorder = ListRecorder(rig, fail_stop='no answer from /recorder/stop within 5 s')
    report = rig.run(record=True, bag_path='b')
    assert report.outcome is Outcome.ABORTED
    assert report.message == ('5 steps done; the bag /bags/b may be incomplete: no answer from '
                              '/recorder/stop within 5 s')


def test_a_failing_recorder_is_an_abort_with_the_error_never_a_raise(rig):
    class BrokenRecorder(ListRecorder):
        def start(self, bag_path, custom_data):
            raise ValueError('not enough values to unpack')
    rig.recorder = BrokenRecorder(rig)
    report = rig.run(record=True)
    assert report.outcome is Outcome.ABORTED
    assert report.message == "internal error: ValueError('not enough values to unpack'); vented"
    assert rig.link.commands('SET') == [(0,)] and not rig.control.sweep_running


# -- the other profiles ----------------------------------------------------------------------

RAMP = {'profile': 'ramp', 'max_gauge_pressure_pa': 400_000.0, 'ramp_rate_pa_s': 50_000.0}
SINE = {'profile': 'sine', 'sine_amplitude_pa': 150_000.0, 'sine_offset_pa': 200_000.0,
        'sine_frequency_hz': 0.2, 'cycles': 2}


def plan_of(**goal):
    return plan_goal(SweepGoal(**{'cycles': 1, **goal}), ceiling_pa=500_000.0)


def streamed_start(rig: Rig) -> float:
    """Device time at which the profile's clock started (its first point reached)."""
    return round(rig.timed_sets()[2][0] - 1 / STREAM_RATE_HZ, 3)   # [0]: the vent to rest


def test_a_ramp_is_streamed_at_20_hz_and_the_pressure_follows_it(rig):
    report = rig.run(**RAMP)
    assert report.success, report.message
    assert report.message == 'ramp done: 321 setpoints over 16 s'
    timed = rig.timed_sets()[1:]                  # [0]: the vent to rest
    values = [v for _, v in timed]
    assert len(values) == 321 and values[0] == 0 and values[-1] == 0
    top = values.index(400_000)
    assert values[:top] == sorted(values[:top]) and values[top:] == sorted(values[top:])[::-1]
    assert max(abs(b - a) for a, b in itertools.pairwise(values)) <= 50_000 / 20 + 1
    # One SET every 50 ms of device time (to the ms), from when the first point was reached.
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(timed[1:])]
    assert all(abs(gap - 0.05) <= 0.0011 for gap in gaps)
    assert timed[-1][0] - timed[1][0] == pytest.approx(16.0 - 0.05, abs=0.0011)
    start = streamed_start(rig)
    tracking = [abs(p - plan_of(**RAMP).pressure_at(t - start)) for t, p, _ in rig.trace
                if start + 1.0 <= t <= start + 16.0]
    assert max(tracking) < 15_000            # the regulation band plus one setpoint's lag
    assert not rig.link.commands('VENT') and not rig.warnings()
    progress = [f.progress for f in rig.feedback]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert {f.step_count for f in rig.feedback} == {321}


def test_a_sine_starts_at_its_trough_peaks_on_time_and_ends_vented(rig):
    report = rig.run(**SINE)
    assert report.success, report.message
    assert report.message == 'sine done: 201 setpoints over 10 s'
    values = rig.sets()
    assert values[:2] == [0, 50_000] and max(values) == 350_000 and values[-2:] == [50_000, 0]
    start = streamed_start(rig)
    plan = plan_of(**SINE)
    errors = [p - plan.pressure_at(t - start) for t, p, _ in rig.trace
              if start + 0.5 <= t <= start + plan.duration_s]
    rms = math.sqrt(sum(e * e for e in errors) / len(errors))
    assert rms < 12_000, rms
    peaks = [t - start for t, p, _ in rig.trace if p > 340_000]
    assert peaks and all(min(abs(t - 2.5), abs(t - 7.5)) < 0.6 for t in peaks)
    rig.settle()
    assert rig.device.setpoint_pa == 0 and rig.device.rig.pressure_pa < 5_000


def test_a_csv_profile_rests_at_0_pa_between_cycles(rig):
    goal = {'profile': 'csv', 'profile_time_s': [0.0, 2.0, 4.0, 6.0],
            'profile_pressure_pa': [0.0, 300_000.0, 300_000.0, 100_000.0], 'cycles': 2,
            'rest_s': 3.0}
    report = rig.run(**goal)
    assert report.success, report.message
    start = streamed_start(rig)
    resting = [t - start for t, _, setpoint in rig.trace if setpoint == 0
               and start + 1 < t < start + 14]
    assert resting[0] == pytest.approx(6.0, abs=0.1)
    assert resting[-1] == pytest.approx(9.0, abs=0.1)
    assert len(resting) == pytest.approx(3.0 * 50, abs=4)
    held = [p for t, p, _ in rig.trace if start + 3.0 <= t - 0 <= start + 4.0]
    assert all(abs(p - 300_000) < 10_000 for p in held)


def test_a_forc_set_runs_its_plan_step_by_step(rig):
    goal = {'profile': 'forc', 'max_gauge_pressure_pa': 200_000.0, 'step_pa': 100_000.0,
            'hold_s': 0.5, 'forc_count': 2, 'forc_family': 'both'}
    report = rig.run(**goal)
    assert report.success, report.message
    plan = plan_of(**goal)
    assert rig.sets() == [0, *(round(p) for p in plan.setpoints_pa)]
    assert report.message.startswith(f'{plan.step_count} steps done')


def test_a_late_answer_skips_the_stale_setpoints_and_sends_the_newest(rig):
    def lose_one(f: SweepProgress) -> None:
        if f.progress > 0.3 and not getattr(rig, 'lost', False):
            rig.lost = rig.link.lost_replies = 1
    rig.on_feedback = lose_one
    report = rig.run(**RAMP)
    assert report.success, report.message
    # The lost reply costs the link's 0.5 s timeout; then the newest point goes, not the
    # stale one again, nor the nine that fell due meanwhile.
    assert report.message == ('ramp done: 312 setpoints over 16 s (9 skipped: the device '
                              'answered late)')
    [warning] = rig.warnings()
    assert warning.endswith('failed: no reply to SET within 0.5 s; the stream goes on')
    start = streamed_start(rig)
    plan = plan_of(**RAMP)
    timed = rig.timed_sets()[1:]
    assert max(b[0] - a[0] for a, b in itertools.pairwise(timed)) == pytest.approx(0.5)
    # Every SET is the profile's value at the time it was sent.
    for t, value in timed[1:-1]:
        assert abs(value - plan.pressure_at(t - start)) <= 50_000 / 20 + 1, (t, value)


def test_a_late_answer_never_skips_the_peak_of_the_loop(rig):
    """The reply lost at 390 kPa on the way up costs 0.5 s, over the ramp's peak at 8 s:
    the peak goes (late), then the newest point; the reversal pressure is the loop's."""
    send = rig.link.send

    def lose_at_390_kpa(command, *args, **kwargs):
        if args == (390_000,) and not getattr(rig, 'lost', False):
            rig.lost = rig.link.lost_replies = 1
        return send(command, *args, **kwargs)
    rig.link.send = lose_at_390_kpa
    report = rig.run(**RAMP)
    assert report.success, report.message
    values = rig.sets()
    top = values.index(400_000)             # sent, where the old stream skipped it
    assert values[top - 1] == 390_000 and values[top + 1] < 400_000 - 50_000 / 20, values
    assert values.count(400_000) == 1 and 'skipped: the device answered late' in report.message


def test_a_plan_names_where_its_profile_turns():
    ramp = plan_of(**RAMP)                               # 0 -> 400 kPa at 50 kPa/s -> 0
    assert ramp.first_turn(0, ramp.setpoint_count) == 160 and ramp.first_turn(161, 320) is None
    held = plan_of(**RAMP, hold_s=1.0)                   # 400 kPa held from 8 s to 9 s
    assert held.first_turn(150, 200) == 160 and held.first_turn(161, 200) is None
    sine = plan_of(**SINE)                               # peaks at 2.5 and 7.5 s
    assert [sine.first_turn(k, k + 60) for k in (1, 51, 101)] == [50, 100, 150]


def test_two_lost_replies_in_a_row_abort_a_stream_and_vent(rig):
    rig.on_feedback = lambda f: f.progress > 0.3 and not rig.link.commands('VENT') and \
        setattr(rig.link, 'lost_replies', 2)
    report = rig.run(**RAMP)
    assert report.outcome is Outcome.ABORTED and report.vented
    assert report.message.endswith('failed: no reply to SET within 0.5 s (2 in a row); vented')


def test_cancelling_a_stream_vents(rig):
    rig.cancel_at_s = 3.0
    report = rig.run(**SINE)
    assert report.outcome is Outcome.CANCELED and report.message == 'canceled; vented'
    assert rig.clock() == pytest.approx(3.0, abs=0.05)
    rig.settle()
    assert rig.device.setpoint_pa == 0 and rig.device.rig.pressure_pa < 5_000


def test_a_ceiling_lowered_mid_stream_is_never_exceeded(rig):
    def lower(f: SweepProgress) -> None:
        if f.progress > 0.1:
            rig.control.max_gauge_pressure_pa = 150_000.0
    rig.on_feedback = lower
    report = rig.run(**RAMP)
    assert report.outcome is Outcome.ABORTED and report.vented
    assert 'setpoint 152500 Pa is above max_gauge_pressure_pa 150000 Pa (lowered' in \
        report.message
    assert max(rig.sets()) == 150_000


def test_a_deactivation_mid_stream_vents_and_no_set_follows_it(rig):
    rig.clock.on_tick = lambda t: t >= 2.5 and rig.control.active and rig.control.deactivate()
    report = rig.run(**SINE)
    assert report.outcome is Outcome.ABORTED
    assert report.message.startswith('driver deactivated; vented')
    first_vent = next(i for i, (_, name, _) in enumerate(rig.link.sent) if name == 'VENT')
    assert all(name != 'SET' for _, name, _ in rig.link.sent[first_vent:])


@pytest.mark.parametrize(('goal', 'words'), [
    ({**SINE, 'sine_offset_pa': 400_000.0}, 'goal refused: the sine peaks at 550000 Pa'),
    ({**RAMP, 'ramp_rate_pa_s': 5e6}, 'goal refused: ramp_rate_pa_s 5000000 Pa/s is faster'),
    ({'profile': 'csv', 'profile_time_s': [0.0, 1.0], 'profile_pressure_pa': [0.0, math.nan]},
     'goal refused: profile_pressure_pa[1] must be a finite number'),
    ({'profile': 'forc', 'max_gauge_pressure_pa': 200e3, 'step_pa': 50e3},
     'goal refused: forc_count must be >= 1'),
    ({'sine_amplitude_pa': 100e3}, "goal refused: sine_amplitude_pa is set, but profile "
                                   "'staircase' does not use it"),
])
def test_a_bad_profile_goal_aborts_at_once_and_commands_nothing(rig, goal, words):
    report = rig.run(**goal)
    assert report.outcome is Outcome.ABORTED and not report.vented
    assert report.message.startswith(words), report.message
    assert rig.link.sent == [] and rig.clock() == 0.0


def test_a_recorded_sine_keeps_its_profile_in_the_bag(rig):
    rig.recorder = ListRecorder(rig)
    report = rig.run(**SINE, record=True, note='sine')
    assert report.success, report.message
    data = rig.recorder.calls[0][3][1]
    assert {k: v for k, v in data.items() if k.startswith('sweep.')} == {
        'sweep.profile': 'sine', 'sweep.max_gauge_pressure_pa': '0.0',
        'sweep.sine_amplitude_pa': '150000.0', 'sweep.sine_offset_pa': '200000.0',
        'sweep.sine_frequency_hz': '0.2', 'sweep.cycles': '2', 'sweep.rest_s': '0.0',
        'sweep.start_pressurised': 'false',
        'sweep.duration_s': '10.0', 'sweep.stream_rate_hz': '20.0',
        'sweep.setpoint_count': '201'}


def test_a_recorded_forc_set_keeps_its_turning_points(rig):
    rig.recorder = ListRecorder(rig)
    report = rig.run(profile='forc', max_gauge_pressure_pa=200e3, step_pa=100e3, forc_count=2,
                     record=True)
    assert report.success, report.message
    data = rig.recorder.calls[0][3][1]
    assert (data['sweep.profile'], data['sweep.forc_count'], data['sweep.forc_family']) == (
        'forc', '2', 'ascending')
    assert json.loads(data['sweep.turning_points_pa']) == [0, 200_000, 100_000, 200_000, 0,
                                                           200_000, 0]
    assert 'sweep.reversal_pressures_pa' not in data


def test_a_lost_commander_aborts_the_sweep_and_vents(rig):
    """`pma sweep` on another host holds a lease; the network drops at 2.5 s (no renewal
    since), so the driver finds it lost at 3.5 s and the sweep ends there, vented."""
    rig.control.clock = rig.clock
    rig.control.leases.timeout_s = 1.0
    rig.control.note_lease('sweep-lease', 'pma sweep (pid 7 on workstation)', True)

    def tick(t: float) -> None:
        if t < 2.5:
            rig.control.note_lease('sweep-lease', 'pma sweep (pid 7 on workstation)', True)
        rig.control.check_leases()

    rig.clock.on_tick = tick
    report = rig.run(max_gauge_pressure_pa=400_000.0, hold_s=5.0)
    assert report.outcome is Outcome.ABORTED
    assert report.message.startswith('commander pma sweep (pid 7 on workstation) lost: no '
                                     'renewal of its lease for 1 s')
    assert rig.clock() == pytest.approx(3.5, abs=0.1)
    first_vent = next(i for i, (_, name, _) in enumerate(rig.link.sent) if name == 'VENT')
    assert all(name != 'SET' for _, name, _ in rig.link.sent[first_vent:])
    rig.settle()
    assert rig.device.setpoint_pa == 0
