"""Running a Sweep goal on the device: plan, record, step, hold, and vent on every failure.

Plain Python, no ROS: the driver node turns the action's goal into a `SweepGoal`, hands it to
`SweepRunner.run` and turns the `SweepReport` into the action's result. Time (`clock`,
`sleep`) and the recorder are injected, so the unit tests run whole sweeps against the
simulated device in simulated time: timeouts, retries, cancels and vent-on-abort included.

Stepped profiles (staircase, FORC) reach and hold each setpoint; streamed ones (ramp, sine,
csv) reach their first point, then send a setpoint every 1/STREAM_RATE_HZ, each SET awaited
(one in flight): when an answer comes late, the setpoints that fell due meanwhile are skipped
and the newest goes, so the stream never builds a backlog; but one where the profile turns
(its peak, a trough, a hold's start) is sent, late, before the stream skips on, since the
loop's reversal pressures are what a hysteresis sweep measures. Every profile ends at 0 Pa.

A sweep starts from rest: before its first level it vents (setpoint 0) and waits until the
pressure is at rest (`rest_check`: the mean of the readings over the last `rest_time_s` below
`rest_pa`, and the mean of that window's second half within REST_FLAT_PA of its first half's),
or aborts after `rest_timeout_s`; a goal with `start_pressurised` starts from the pressure it
finds. A recording sweep's bag is started after that wait, so the bag begins at rest.

What the sweep did goes to an injected `record` callback as `SweepRecord`s (plain data; the
node publishes them on pma/sweep_record): START when the first level begins, LEVEL when a
stepped profile's hold ends (target, reached = mean over the hold's last half, branch,
settled), END with the outcome, before the bag is stopped.

Safety: each setpoint is checked against the ceiling at the moment it is sent (the parameter
may be lowered mid-run), under the DeviceControl lock, so a deactivation's VENT is never
overtaken. Once the first setpoint has been commanded, every end but success vents.
"""

from __future__ import annotations

import enum
import json
import logging
import math
import statistics
import time
import traceback
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from pma_common.protocol import Ack, Command, Hello
from pma_common.sweep import (
    PROFILE_FIELDS,
    StreamPlan,
    SweepError,
    SweepGoal,
    SweepPlan,
    plan_goal,
)
from pma_driver.command_gate import DeviceControl
from pma_driver.link import LinkError

SET_ATTEMPTS = 2            # SET is idempotent: sent once more when its reply got lost
# At rest, the pressure no longer falls: the means of the rest window's two halves differ by
# less than this [Pa]. Means, not single readings: the sensor's noise (2.5 kPa a reading on
# the simulated rig, 0.5 % of full scale) would otherwise keep a flat pressure from passing.
REST_FLAT_PA = 1_000.0
REST_MIN_READINGS = 2       # in each half of the rest window
PHASE_REST = 'venting to rest'
PHASE_RUNNING = 'running'
_log = logging.getLogger('pma_driver.sweep_runner')


@dataclass(frozen=True)
class SweepSettings:
    tolerance_pa: float           # a step is reached within this of its setpoint
    step_timeout_s: float         # ... or after this long (logged); then the hold starts
    rest_pa: float = 5_000.0      # at rest: the window's mean below this [Pa] ...
    rest_time_s: float = 1.0      # ... and flat (REST_FLAT_PA) over a window this long [s]
    rest_timeout_s: float = 30.0  # not at rest this long after venting: the goal aborts
    feedback_period_s: float = 0.5
    poll_period_s: float = 0.02   # how often the pressure and the stop conditions are looked at


@dataclass(frozen=True)
class SweepProgress:
    """One feedback message."""

    step_index: int
    step_count: int
    gauge_setpoint_pa: float
    progress: float
    sample_count: int
    phase: str = PHASE_RUNNING


class RecordKind(enum.IntEnum):
    """pma_interfaces/msg/SweepRecord's KIND_* values."""

    START = 0
    LEVEL = 1
    END = 2


class Branch(enum.IntEnum):
    """pma_interfaces/msg/SweepRecord's BRANCH_* values."""

    REST = 0
    RISING = 1
    FALLING = -1


@dataclass(frozen=True)
class SweepRecord:
    """One pma_interfaces/msg/SweepRecord without ROS (the .msg documents each field);
    times are the runner's `now_ns` clock (the node's ROS clock) [ns]."""

    kind: RecordKind
    profile: str
    stamp_ns: int
    started_at_rest: bool = False
    start_gauge_pressure_pa: float = math.nan
    level_index: int = 0
    level_count: int = 0
    target_gauge_pressure_pa: float = math.nan
    reached_gauge_pressure_pa: float = math.nan
    branch: Branch = Branch.REST
    settled: bool = False
    hold_start_ns: int = 0
    hold_end_ns: int = 0
    message: str = ''


@dataclass(frozen=True)
class RestCheck:
    """The rest criterion over one window of readings."""

    at_rest: bool
    mean_pa: float          # of every reading in the window (NaN: too few readings)
    change_pa: float        # second half's mean minus the first half's
    readings: int


def rest_check(window: Sequence[tuple[float, float]], now: float, rest_pa: float,
               rest_time_s: float) -> RestCheck:
    """Is the pressure at rest, judged on the (time, Pa) readings of the last `rest_time_s`?

    At rest: the mean of the window below `rest_pa`, and its second half's mean within
    REST_FLAT_PA of its first half's (no longer falling), with REST_MIN_READINGS or more in
    each half. The caller must have watched for `rest_time_s` at least.
    """
    start, middle = now - rest_time_s, now - rest_time_s / 2
    first = [p for t, p in window if start <= t < middle]
    second = [p for t, p in window if t >= middle]
    if len(first) < REST_MIN_READINGS or len(second) < REST_MIN_READINGS:
        return RestCheck(False, math.nan, math.nan, len(first) + len(second))
    mean = statistics.fmean(first + second)
    change = statistics.fmean(second) - statistics.fmean(first)
    return RestCheck(mean < rest_pa and abs(change) < REST_FLAT_PA, mean, change,
                     len(first) + len(second))


class Outcome(enum.Enum):
    SUCCEEDED = 'succeeded'
    ABORTED = 'aborted'
    CANCELED = 'canceled'


@dataclass(frozen=True)
class SweepReport:
    outcome: Outcome
    message: str
    bag_path: str = ''
    sample_count: int = 0
    vented: bool = False

    @property
    def success(self) -> bool:
        return self.outcome is Outcome.SUCCEEDED


class RecorderError(RuntimeError):
    """The recorder is missing, refused, or did not answer; the message says what to do."""


@dataclass(frozen=True)
class RecordingSummary:
    bag_path: str
    message_count: int
    lost_message_count: int


class Recorder(Protocol):
    """A running recorder: one bag per sweep (the driver uses pma_bag's record node)."""

    def start(self, bag_path: str, custom_data: Mapping[str, str]) -> str:
        """Start a bag ('' = auto-named); return its absolute path. Raises RecorderError."""

    def stop(self) -> RecordingSummary:
        """Finish the bag. Raises RecorderError."""

    def check(self) -> None:
        """Raise RecorderError when no recorder answers (asked before anything is commanded:
        the bag itself starts after the wait for rest)."""


def _metadata_value(value) -> str:
    """Text as is, numbers as Python float reprs, lists as JSON."""
    if isinstance(value, str):
        return value
    if isinstance(value, int | float):
        return repr(float(value))
    return json.dumps([float(v) for v in value])


def recording_metadata(goal: SweepGoal, plan: SweepPlan | StreamPlan, hello: Hello | None,
                       calibration: Mapping[str, float]) -> dict[str, str]:
    """The bag's custom_data: what was asked, of which device, read with which calibration."""
    profile = goal.profile_name
    data = {**goal.custom_data, 'note': goal.note, 'sweep.profile': profile}
    for name in (*PROFILE_FIELDS[profile], 'rest_s'):
        data[f'sweep.{name}'] = _metadata_value(getattr(goal, name))
    data['sweep.cycles'] = str(goal.cycles)
    data['sweep.start_pressurised'] = 'true' if goal.start_pressurised else 'false'
    if profile == 'forc':
        data['sweep.forc_count'] = str(goal.forc_count)
        data['sweep.forc_family'] = goal.forc_family or 'ascending'
    if isinstance(plan, SweepPlan):
        data['sweep.turning_points_pa'] = json.dumps([round(t) for t in plan.turning_points_pa])
        data['sweep.step_count'] = str(plan.step_count)
        data['sweep.setpoints_pa'] = json.dumps([round(s) for s in plan.setpoints_pa])
    else:
        data['sweep.duration_s'] = repr(plan.duration_s)
        data['sweep.stream_rate_hz'] = repr(plan.rate_hz)
        data['sweep.setpoint_count'] = str(plan.setpoint_count)
    if hello is not None:
        data.update({
            'device.firmware': hello.firmware,
            'device.firmware_version': hello.fw_version,
            'device.protocol_version': str(hello.proto),
            'device.limit_pa': str(hello.limit_pa),
        })
    data.update({name: repr(float(value)) for name, value in calibration.items()})
    return data


@dataclass
class _Run:
    goal: SweepGoal
    settings: SweepSettings
    cancel_requested: Callable[[], bool]
    feedback: Callable[[SweepProgress], None]
    calibration: Mapping[str, float]
    record: Callable[[SweepRecord], None] = lambda record: None
    plan: SweepPlan | StreamPlan | None = None
    start_count: int = 0
    commanded: bool = False         # a step was sent: from here on, a failure vents
    started_at_rest: bool = False
    start_pa: float = math.nan      # the pressure when the first level began
    last_reading: object = None     # the DeviceControl reading seen last (by identity)
    reach_timed_out: bool = False   # the step just reached was not, within step_timeout_s
    previous_level: tuple[float, Branch] | None = None   # the last level's target and branch
    commanders_lost: int = 0        # DeviceControl.commanders_lost when the run began


class SweepRunner:
    """Runs one sweep at a time on a DeviceControl."""

    def __init__(self, control: DeviceControl, *, recorder: Recorder | None = None,
                 sample_count: Callable[[], int] = lambda: 0,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 on_event: Callable[[int, str], None] = _log.log,
                 now_ns: Callable[[], int] = time.time_ns):
        self.control = control
        self.recorder = recorder
        self.sample_count = sample_count
        self.clock = clock
        self.sleep = sleep
        self.on_event = on_event
        self.now_ns = now_ns            # the records' stamps (the node's ROS clock)

    def run(self, goal: SweepGoal, settings: SweepSettings, *,
            cancel_requested: Callable[[], bool] = lambda: False,
            feedback: Callable[[SweepProgress], None] = lambda progress: None,
            calibration: Mapping[str, float] | None = None,
            record: Callable[[SweepRecord], None] = lambda record: None) -> SweepReport:
        """Run the goal to its end; every failure is a report with its reason, never a raise.

        `record` gets the sweep's START, LEVEL and END records as they happen (none for a
        goal that commanded nothing)."""
        if not self.control.claim_sweep():
            message = 'another sweep is running; this one did not start (nothing commanded)'
            self.on_event(logging.WARNING, f'sweep {Outcome.ABORTED.value}: {message}')
            return SweepReport(Outcome.ABORTED, message)
        run = _Run(goal, settings, cancel_requested, feedback, calibration or {}, record,
                   commanders_lost=self.control.commanders_lost)
        try:
            return self._run(run)
        except Exception as error:   # a bug (or a recorder's) must still vent and say so
            self.on_event(logging.ERROR, f'sweep failed: {traceback.format_exc()}')
            return self._finish(run, Outcome.ABORTED, f'internal error: {error!r}')
        finally:
            self.control.release_sweep()

    # -- the run -------------------------------------------------------------------------

    def _run(self, run: _Run) -> SweepReport:
        goal = run.goal
        try:
            run.plan = plan_goal(goal, ceiling_pa=self.control.ceiling_pa())
        except SweepError as error:
            return self._finish(run, Outcome.ABORTED, f'goal refused: {error}')
        _, reason = self.control.not_commandable()
        if reason:
            return self._finish(run, Outcome.ABORTED, f'not started: {reason}')
        bag_path = ''
        if goal.record:
            if self.recorder is None:
                return self._finish(run, Outcome.ABORTED, 'not started: no recorder configured')
            try:
                self.recorder.check()   # before the vent: a missing recorder commands nothing
            except RecorderError as error:
                return self._finish(run, Outcome.ABORTED, f'not started: {error}')
        run.start_count = self.sample_count()
        if goal.start_pressurised:
            run.start_pa = self.control.latest_gauge_pa
            start_note = (f'started pressurised at {run.start_pa / 1e3:.1f} kPa, as the goal '
                          'asked (start_pressurised): no vent and no wait for rest, so the first '
                          'level may land on the decreasing branch')
            self.on_event(logging.INFO, f'sweep: {start_note}')
        else:
            try:
                stop, start_note = self._wait_for_rest(run)
            except Exception as error:   # a bug here must still vent
                self.on_event(logging.ERROR, f'sweep failed: {traceback.format_exc()}')
                stop = Outcome.ABORTED, f'internal error: {error!r}'
            if stop:
                return self._finish(run, *stop)
            run.started_at_rest = True
        if goal.record:
            link = self.control.link
            metadata = recording_metadata(goal, run.plan, link.hello if link else None,
                                          run.calibration)
            try:
                bag_path = self.recorder.start(goal.bag_path, metadata)
            except RecorderError as error:
                return self._finish(run, Outcome.ABORTED, f'not started: {error}')
            self.on_event(logging.INFO, f'sweep: recording to {bag_path}')
        # After the bag started (and the recorder's readers were matched): START is in it.
        # The run's samples are counted from here, as its bag holds them.
        run.start_count = self.sample_count()
        self._emit(run, SweepRecord(
            RecordKind.START, run.plan.profile, self.now_ns(), started_at_rest=run.started_at_rest,
            start_gauge_pressure_pa=run.start_pa, message=start_note))
        try:
            if isinstance(run.plan, StreamPlan):
                outcome, message = self._stream(run)
            else:
                outcome, message = self._follow(run)
        except Exception as error:   # a bug here must still vent and finish the bag
            self.on_event(logging.ERROR, f'sweep failed: {traceback.format_exc()}')
            outcome, message = Outcome.ABORTED, f'internal error: {error!r}'
        return self._finish(run, outcome, message, bag_path)

    def _finish(self, run: _Run, outcome: Outcome, message: str,
                bag_path: str = '') -> SweepReport:
        vented = False
        if outcome is not Outcome.SUCCEEDED and run.commanded:
            # Whatever stopped the run (cancel, NAK, lost reply, stall, deactivation), the
            # muscle must not stay at the last step's pressure.
            vented = self.control.vent(f'sweep {outcome.value}')
            message += '; vented' if vented else '; could not send VENT (the device vents ' \
                'by itself when the heartbeats stop)'
        if run.commanded or bag_path:
            # Before the bag is stopped, so that it holds the END.
            self._emit(run, SweepRecord(RecordKind.END, run.plan.profile if run.plan else
                                        run.goal.profile_name, self.now_ns(),
                                        message=f'{outcome.value}: {message}'))
        if bag_path:
            try:
                summary = self.recorder.stop()
            except RecorderError as error:
                message += f'; the bag {bag_path} may be incomplete: {error}'
                if outcome is Outcome.SUCCEEDED:
                    outcome = Outcome.ABORTED   # the goal asked for a bag
            else:
                message += (f'; bag {summary.bag_path}: {summary.message_count} messages, '
                            f'{summary.lost_message_count} lost')
        count = self.sample_count() - run.start_count if run.commanded else 0
        level = logging.INFO if outcome is Outcome.SUCCEEDED else logging.WARNING
        self.on_event(level, f'sweep {outcome.value}: {message} ({count} samples)')
        return SweepReport(outcome, message, bag_path, count, vented)

    def _emit(self, run: _Run, record: SweepRecord) -> None:
        """Hand a record on; a failing callback (a node shutting down) never ends the run."""
        try:
            run.record(record)
        except Exception as error:
            self.on_event(logging.WARNING, f'sweep: {record.kind.name} record not published: '
                          f'{error!r}')

    def _new_reading(self, run: _Run) -> float | None:
        """The pressure of a sample not seen before by this run [Pa], or None."""
        reading = self.control.latest_reading
        if reading is None or reading is run.last_reading:
            return None
        run.last_reading = reading
        return reading[1] if math.isfinite(reading[1]) else None

    def _wait_for_rest(self, run: _Run) -> tuple[tuple[Outcome, str] | None, str]:
        """Vent (setpoint 0) and wait until the pressure is at rest (rest_check).

        (how the run ends, '') when it must end here; (None, what the START record says).
        """
        settings = run.settings
        stop = self._step(run, 0.0, 'setpoint')
        if stop:
            return stop, ''
        self.on_event(logging.INFO, (
            f'sweep: venting to rest (below {settings.rest_pa / 1e3:g} kPa and within '
            f'{REST_FLAT_PA / 1e3:g} kPa over {settings.rest_time_s:g} s) before the first level'))
        start = self.clock()
        window: deque[tuple[float, float]] = deque()
        next_feedback = start
        check = RestCheck(False, math.nan, math.nan, 0)
        while True:
            stop = self._stop_reason(run)
            if stop:
                return stop, ''
            now = self.clock()
            pressure = self._new_reading(run)
            if pressure is not None:
                window.append((now, pressure))
            while window and window[0][0] < now - settings.rest_time_s:
                window.popleft()
            if now - start >= settings.rest_time_s:
                check = rest_check(window, now, settings.rest_pa, settings.rest_time_s)
                if check.at_rest:
                    run.start_pa = check.mean_pa
                    note = (f'at rest: {check.mean_pa / 1e3:.1f} kPa (mean over '
                            f'{settings.rest_time_s:g} s, changing {check.change_pa / 1e3:+.1f} '
                            f'kPa), {now - start:.1f} s after venting')
                    self.on_event(logging.INFO, f'sweep: {note}')
                    return None, note
            if now >= next_feedback:
                plan = run.plan
                count = plan.step_count if isinstance(plan, SweepPlan) else plan.setpoint_count
                run.feedback(SweepProgress(
                    step_index=0, step_count=count, gauge_setpoint_pa=0.0, progress=0.0,
                    sample_count=self.sample_count() - run.start_count, phase=PHASE_REST))
                next_feedback = now + settings.feedback_period_s
            if now - start > settings.rest_timeout_s:
                if math.isnan(check.mean_pa):
                    found = f'{check.readings} pressure readings in the last ' \
                            f'{settings.rest_time_s:g} s, too few to judge'
                else:
                    found = (f'{check.mean_pa / 1e3:.1f} kPa, changing '
                             f'{check.change_pa / 1e3:+.1f} kPa over {settings.rest_time_s:g} s')
                return (Outcome.ABORTED, (
                    f'not at rest within sweep.rest_timeout_s {settings.rest_timeout_s:g} s of '
                    f'venting ({found}; at rest is below sweep.rest_pa '
                    f'{settings.rest_pa / 1e3:g} kPa and within {REST_FLAT_PA / 1e3:g} kPa over '
                    f'sweep.rest_time_s): a blocked exhaust, a leak into the muscle, or a sensor '
                    'not tared (`pma tare --vent`)')), ''
            self.sleep(settings.poll_period_s)

    def _stop_reason(self, run: _Run) -> tuple[Outcome, str] | None:
        if run.cancel_requested():
            return Outcome.CANCELED, 'canceled'
        kind, reason = self.control.not_commandable()
        if kind == 'inactive':
            return Outcome.ABORTED, 'driver deactivated'
        if reason:
            return Outcome.ABORTED, (f'{reason} during the sweep (the device also vents on '
                                     'heartbeat loss)')
        if self.control.commanders_lost > run.commanders_lost:
            return Outcome.ABORTED, self.control.last_commander_lost
        return None

    def _command(self, run: _Run, setpoint: float, what: str,
                 attempts: int = SET_ATTEMPTS) -> tuple[tuple[Outcome, str] | None, str]:
        """SET one setpoint, if nothing stops the run and it is within the ceiling now.

        (how the run ends, '') when it must end here; (None, error) when no reply came;
        (None, '') when the device took it.
        """
        with self.control.lock:
            stop = self._stop_reason(run)
            if stop:
                return stop, ''
            limit = self.control.ceiling_pa()
            if setpoint > limit:
                return (Outcome.ABORTED, (f'{what} {setpoint:.0f} Pa is above '
                                          f'max_gauge_pressure_pa {limit} Pa (lowered '
                                          'during the sweep)')), ''
            run.commanded = True
            reply, error = self._set(round(setpoint), attempts)
        if reply is None:
            return None, f'SET {setpoint:.0f} Pa failed: {error}'
        if not isinstance(reply, Ack):
            return (Outcome.ABORTED, f'device refused SET {setpoint:.0f} Pa: NAK '
                                     f'{reply.reason}'), ''
        return None, ''

    def _step(self, run: _Run, setpoint: float, what: str) -> tuple[Outcome, str] | None:
        """SET, sent once more if its reply got lost; how the run ends, if it must."""
        stop, lost = self._command(run, setpoint, what)
        return stop or ((Outcome.ABORTED, lost) if lost else None)

    def _follow(self, run: _Run) -> tuple[Outcome, str]:
        plan = run.plan
        self.on_event(logging.INFO, f'sweep: {plan.profile}, {plan.step_count} steps up to '
                      f'{plan.peak_pa:.0f} Pa, hold {plan.hold_s:g} s')
        for index, setpoint in enumerate(plan.setpoints_pa):
            stop = self._step(run, setpoint, 'step')
            if stop:
                return stop
            self._feedback(run, index, setpoint, 0.0)
            stop = self._reach(run, index, setpoint)
            if stop:
                return stop
            hold_start_ns = self.now_ns()
            readings: list[tuple[float, float]] = []
            stop = self._hold(run, index, setpoint, readings)
            if stop:
                return stop
            self._level_record(run, index, setpoint, readings, hold_start_ns)
        self._feedback(run, plan.step_count - 1, plan.setpoints_pa[-1], 1.0)
        return Outcome.SUCCEEDED, f'{plan.step_count} steps done'

    def _stream(self, run: _Run) -> tuple[Outcome, str]:
        plan, settings = run.plan, run.settings
        count = plan.setpoint_count
        self.on_event(logging.INFO, (
            f'sweep: {plan.profile}, {plan.duration_s:g} s up to {plan.peak_pa:.0f} Pa, '
            f'{count} setpoints at {plan.rate_hz:g} Hz'))
        setpoint = plan.pressure_at(0.0)
        stop = self._step(run, setpoint, 'setpoint')
        if stop:
            return stop
        self._stream_feedback(run, 0, setpoint, 0.0)
        stop = self._reach(run, 0, setpoint)       # the profile's clock starts there
        if stop:
            return stop
        start = self.clock()
        next_feedback = start + settings.feedback_period_s
        skipped = lost_in_a_row = 0
        index = 1
        while index < count:
            due = start + plan.time_of(index)
            while (now := self.clock()) < due:
                stop = self._stop_reason(run)
                if stop:
                    return stop
                self.sleep(min(settings.poll_period_s, due - now))
            newest = plan.index_at(now - start)
            if newest > index:           # a late answer: never send what is already stale,
                turn = plan.first_turn(index, newest)   # but a turn of the loop, late, first
                target = newest if turn is None else turn
                skipped += target - index
                index = target
            t = plan.time_of(index)
            setpoint = plan.pressure_at(t)
            # A lost reply is not sent again: the next setpoint, newer, goes instead.
            stop, lost = self._command(run, setpoint, 'setpoint', attempts=1)
            if stop:
                return stop
            lost_in_a_row = lost_in_a_row + 1 if lost else 0
            if lost_in_a_row >= SET_ATTEMPTS:
                return Outcome.ABORTED, f'{lost} ({lost_in_a_row} in a row)'
            if lost:
                self.on_event(logging.WARNING, f'sweep: {lost}; the stream goes on')
            if self.clock() >= next_feedback:
                self._stream_feedback(run, index, setpoint, t)
                next_feedback = self.clock() + settings.feedback_period_s
            index += 1
        if setpoint != 0.0:                 # every profile ends at rest
            stop = self._step(run, 0.0, 'setpoint') or self._reach(run, count - 1, 0.0)
            if stop:
                return stop
        self._stream_feedback(run, count - 1, 0.0, plan.duration_s)
        late = f' ({skipped} skipped: the device answered late)' if skipped else ''
        return Outcome.SUCCEEDED, (f'{plan.profile} done: {count - skipped} setpoints over '
                                   f'{plan.duration_s:g} s{late}')

    def _set(self, gauge_pa: int, attempts: int = SET_ATTEMPTS):
        """SET, again while the reply gets lost: (reply, '') or (None, error text)."""
        error = ''
        for _ in range(attempts):
            try:
                return self.control.send_and_wait(Command.SET, gauge_pa), ''
            except LinkError as failure:
                error = str(failure)
        return None, error

    def _reach(self, run: _Run, index: int, setpoint: float) -> tuple[Outcome, str] | None:
        """Wait until the measured pressure is within tolerance, or the step times out."""
        settings = run.settings
        deadline = self.clock() + settings.step_timeout_s
        run.reach_timed_out = False
        # NaN (no reading yet) is not reached.
        while not abs(self.control.latest_gauge_pa - setpoint) <= settings.tolerance_pa:
            stop = self._stop_reason(run)
            if stop:
                return stop
            if self.clock() > deadline:
                run.reach_timed_out = True
                self.on_event(logging.WARNING, (
                    f'sweep step {index}: {setpoint:.0f} Pa not reached within '
                    f'{settings.step_timeout_s:g} s (at {self.control.latest_gauge_pa:.0f} Pa); '
                    'holding'))
                return None
            self.sleep(settings.poll_period_s)
        return None

    def _hold(self, run: _Run, index: int, setpoint: float,
              readings: list[tuple[float, float]] | None = None) -> tuple[Outcome, str] | None:
        """Hold the step; `readings` gets (clock, Pa) of each new sample during the hold."""
        settings, hold_s = run.settings, run.plan.hold_at(index)
        hold_end = self.clock() + hold_s
        next_feedback = self.clock() + settings.feedback_period_s
        self._new_reading(run)          # only samples taken from here on count
        while (now := self.clock()) < hold_end:
            stop = self._stop_reason(run)
            if stop:
                return stop
            pressure = self._new_reading(run)
            if pressure is not None and readings is not None:
                readings.append((now, pressure))
            if now >= next_feedback:
                self._feedback(run, index, setpoint, 1.0 - (hold_end - now) / hold_s)
                next_feedback = now + settings.feedback_period_s
            self.sleep(min(settings.poll_period_s, hold_end - now))
        return None

    def _level_record(self, run: _Run, index: int, target: float,
                      readings: list[tuple[float, float]], hold_start_ns: int) -> None:
        """LEVEL: what the hold that just ended reached, on which branch, and if it settled."""
        settings, plan = run.settings, run.plan
        hold_s = plan.hold_at(index)
        last_half = [p for t, p in readings if t >= self.clock() - hold_s / 2]
        pressure = self._new_reading(run)
        if pressure is not None:
            last_half.append(pressure)
        if not last_half:      # a hold of 0 s: the latest reading
            last_half = [self.control.latest_gauge_pa]
        reached = statistics.fmean(last_half)
        tolerance = settings.tolerance_pa
        outside = sum(not abs(p - target) <= tolerance for p in last_half)
        notes = []
        if run.reach_timed_out:
            notes.append(f'not reached within sweep.step_timeout_s {settings.step_timeout_s:g} s')
        if not abs(reached - target) <= tolerance:
            notes.append(f'{reached / 1e3:.1f} kPa reached, {(reached - target) / 1e3:+.1f} kPa '
                         f'from the target (sweep.tolerance_pa {tolerance / 1e3:g} kPa)')
        elif outside:
            notes.append(f"{outside} of {len(last_half)} readings of the hold's last half off "
                         f'the target by more than sweep.tolerance_pa {tolerance / 1e3:g} kPa')
        previous = run.previous_level
        if previous is None:
            if target == 0.0 and (run.started_at_rest or run.start_pa < settings.rest_pa):
                branch = Branch.REST
            else:
                branch = Branch.RISING if target > run.start_pa else Branch.FALLING
        elif target == previous[0]:
            branch = previous[1]
        else:
            branch = Branch.RISING if target > previous[0] else Branch.FALLING
        run.previous_level = (target, branch)
        message = f'not settled: {"; ".join(notes)}' if notes else ''
        if notes:
            self.on_event(logging.WARNING,
                          f'sweep level {index} ({target / 1e3:g} kPa): {message}')
        self._emit(run, SweepRecord(
            RecordKind.LEVEL, plan.profile, self.now_ns(), started_at_rest=run.started_at_rest,
            start_gauge_pressure_pa=run.start_pa, level_index=index, level_count=plan.step_count,
            target_gauge_pressure_pa=target, reached_gauge_pressure_pa=reached, branch=branch,
            settled=not notes, hold_start_ns=hold_start_ns, hold_end_ns=self.now_ns(),
            message=message))

    def _feedback(self, run: _Run, index: int, setpoint: float, hold_fraction: float) -> None:
        plan = run.plan
        run.feedback(SweepProgress(
            step_index=index, step_count=plan.step_count, gauge_setpoint_pa=setpoint,
            progress=plan.progress(index, hold_fraction),
            sample_count=self.sample_count() - run.start_count))

    def _stream_feedback(self, run: _Run, index: int, setpoint: float, t_s: float) -> None:
        plan = run.plan
        run.feedback(SweepProgress(
            step_index=index, step_count=plan.setpoint_count, gauge_setpoint_pa=setpoint,
            progress=plan.progress(t_s), sample_count=self.sample_count() - run.start_count))
