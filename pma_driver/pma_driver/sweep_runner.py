"""Running a Sweep goal on the device: plan, record, step, hold, and vent on every failure.

Plain Python, no ROS: the driver node turns the action's goal into a `SweepGoal`, hands it to
`SweepRunner.run` and turns the `SweepReport` into the action's result. Time (`clock`,
`sleep`) and the recorder are injected, so the unit tests run whole sweeps against the
simulated device in simulated time: timeouts, retries, cancels and vent-on-abort included.

Stepped profiles (staircase, FORC) reach and hold each setpoint; streamed ones (ramp, sine,
csv) reach their first point, then send a setpoint every 1/STREAM_RATE_HZ, each SET awaited
(one in flight): when an answer comes late, the setpoints that fell due meanwhile are skipped
and the newest goes, so the stream never builds a backlog. Every profile ends at 0 Pa.

Safety: each setpoint is checked against the ceiling at the moment it is sent (the parameter
may be lowered mid-run), under the DeviceControl lock, so a deactivation's VENT is never
overtaken. Once the first setpoint has been commanded, every end but success vents.
"""

from __future__ import annotations

import enum
import json
import logging
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

from pma_driver.control import DeviceControl
from pma_driver.link import LinkError
from pma_driver.protocol import Ack, Command, Hello
from pma_driver.sweep import (
    PROFILE_FIELDS,
    StreamPlan,
    SweepError,
    SweepGoal,
    SweepPlan,
    plan_goal,
)

SET_ATTEMPTS = 2            # SET is idempotent: sent once more when its reply got lost
_log = logging.getLogger('pma_driver.sweep_runner')


@dataclass(frozen=True)
class SweepSettings:
    tolerance_pa: float           # a step is reached within this of its setpoint
    step_timeout_s: float         # ... or after this long (logged); then the hold starts
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
    data = {'note': goal.note, 'sweep.profile': profile}
    for name in (*PROFILE_FIELDS[profile], 'rest_s'):
        data[f'sweep.{name}'] = _metadata_value(getattr(goal, name))
    data['sweep.cycles'] = str(goal.cycles)
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
    plan: SweepPlan | StreamPlan | None = None
    start_count: int = 0
    commanded: bool = False         # a step was sent: from here on, a failure vents


class SweepRunner:
    """Runs one sweep at a time on a DeviceControl."""

    def __init__(self, control: DeviceControl, *, recorder: Recorder | None = None,
                 sample_count: Callable[[], int] = lambda: 0,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 on_event: Callable[[int, str], None] = _log.log):
        self.control = control
        self.recorder = recorder
        self.sample_count = sample_count
        self.clock = clock
        self.sleep = sleep
        self.on_event = on_event

    def run(self, goal: SweepGoal, settings: SweepSettings, *,
            cancel_requested: Callable[[], bool] = lambda: False,
            feedback: Callable[[SweepProgress], None] = lambda progress: None,
            calibration: Mapping[str, float] | None = None) -> SweepReport:
        """Run the goal to its end; every failure is a report with its reason, never a raise."""
        if not self.control.claim_sweep():
            message = 'another sweep is running; this one did not start (nothing commanded)'
            self.on_event(logging.WARNING, f'sweep {Outcome.ABORTED.value}: {message}')
            return SweepReport(Outcome.ABORTED, message)
        run = _Run(goal, settings, cancel_requested, feedback, calibration or {})
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
            link = self.control.link
            metadata = recording_metadata(goal, run.plan, link.hello if link else None,
                                          run.calibration)
            try:
                bag_path = self.recorder.start(goal.bag_path, metadata)
            except RecorderError as error:
                return self._finish(run, Outcome.ABORTED, f'not started: {error}')
            self.on_event(logging.INFO, f'sweep: recording to {bag_path}')
        run.start_count = self.sample_count()
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

    def _stop_reason(self, run: _Run) -> tuple[Outcome, str] | None:
        if run.cancel_requested():
            return Outcome.CANCELED, 'canceled'
        kind, reason = self.control.not_commandable()
        if kind == 'inactive':
            return Outcome.ABORTED, 'driver deactivated'
        if reason:
            return Outcome.ABORTED, (f'{reason} during the sweep (the device also vents on '
                                     'heartbeat loss)')
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
            stop = self._reach(run, index, setpoint) or self._hold(run, index, setpoint)
            if stop:
                return stop
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
            if newest > index:           # a late answer: never send what is already stale
                skipped += newest - index
                index = newest
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
        # NaN (no reading yet) is not reached.
        while not abs(self.control.latest_gauge_pa - setpoint) <= settings.tolerance_pa:
            stop = self._stop_reason(run)
            if stop:
                return stop
            if self.clock() > deadline:
                self.on_event(logging.WARNING, (
                    f'sweep step {index}: {setpoint:.0f} Pa not reached within '
                    f'{settings.step_timeout_s:g} s (at {self.control.latest_gauge_pa:.0f} Pa); '
                    'holding'))
                return None
            self.sleep(settings.poll_period_s)
        return None

    def _hold(self, run: _Run, index: int, setpoint: float) -> tuple[Outcome, str] | None:
        settings, hold_s = run.settings, run.plan.hold_at(index)
        hold_end = self.clock() + hold_s
        next_feedback = self.clock() + settings.feedback_period_s
        while (now := self.clock()) < hold_end:
            stop = self._stop_reason(run)
            if stop:
                return stop
            if now >= next_feedback:
                self._feedback(run, index, setpoint, 1.0 - (hold_end - now) / hold_s)
                next_feedback = now + settings.feedback_period_s
            self.sleep(min(settings.poll_period_s, hold_end - now))
        return None

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
