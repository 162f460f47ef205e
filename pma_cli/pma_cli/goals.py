"""`pma sweep` and `pma move`: an action goal with live feedback; Ctrl-C cancels it.

A stop signal while the goal runs cancels the goal and waits for its result (the driver vents
when a sweep is cancelled; a cancelled move leaves the pressure where it is), so the command
ends only when the rig has ended the run too.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable

from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient

from pma_cli import quantities as q
from pma_cli.commands import CONTROL_TOPIC, holds_target, release_holding_controller
from pma_cli.session import (
    FAILED,
    INTERRUPTED,
    NO_ANSWER,
    OK,
    USAGE,
    CliError,
    Interrupted,
    Session,
)
from pma_driver.sweep import (
    STREAMED_PROFILES,
    SweepError,
    SweepGoal,
    plan_goal,
    read_profile_csv,
)
from pma_interfaces.action import MoveToLength, Sweep
from pma_interfaces.msg import ControlState, PmaState

CANCEL_WAIT_S = 15.0
DEFAULT_STEP_HOLD_S = 5.0    # pma sweep's hold at each step of a staircase or FORC set
# STATUS_UNKNOWN: the server holds no goal of that ID (pma_common.action: a rejection taken
# for the duplicate of an accepted goal).
STATUS_WORDS = {GoalStatus.STATUS_SUCCEEDED: 'succeeded', GoalStatus.STATUS_ABORTED: 'aborted',
                GoalStatus.STATUS_CANCELED: 'cancelled',
                GoalStatus.STATUS_UNKNOWN: 'not known to the server (rejected?)'}


class Progress:
    """A bar rewritten in place on a terminal; a line per step (or per 10 %) otherwise."""

    def __init__(self, out=sys.stderr):
        self.out = out
        self.tty = out.isatty()
        self.last_key = None
        self.width = 0

    def show(self, fraction: float, text: str, key) -> None:
        if self.tty:
            filled = round(30 * min(1.0, max(0.0, fraction)))
            line = f'[{"#" * filled}{"." * (30 - filled)}] {100 * fraction:5.1f} %  {text}'
            self.out.write('\r' + line.ljust(self.width))
            self.width = len(line)
            self.out.flush()
        elif key != self.last_key:
            self.out.write(f'{100 * fraction:5.1f} %  {text}\n')
            self.out.flush()
        self.last_key = key

    def end(self) -> None:
        if self.tty and self.width:
            self.out.write('\n')
            self.out.flush()
        self.width = 0


def run_goal(session: Session, action_type, name: str, goal, *, on_feedback, timeout_s: float,
             what: str, hint: str, before: Callable[[], None] | None = None):
    """(status, result) of one goal; a stop signal cancels it and its result is still awaited.

    `before` runs once the server is there, before the goal is sent.
    """
    client = ActionClient(session.node, action_type, name)
    try:
        if not session.spin_until(client.server_is_ready, timeout_s):
            raise CliError(f'no {what} answers on {session.resolve(name)} (waited '
                           f'{timeout_s:g} s): {hint}', NO_ANSWER)
        if before is not None:
            before()
        try:
            handle = session.send_goal(client, goal, timeout_s, f'the {what} (goal acceptance)',
                                       feedback_callback=lambda m: on_feedback(m.feedback))
        except Interrupted:
            print(f'\ninterrupted before the {what} answered the goal; a cancel for it was '
                  'sent', file=sys.stderr, flush=True)
            raise
        if not handle.accepted:
            raise CliError(f'the {what} rejected the goal')
        result_future = handle.get_result_async()
        try:
            session.spin_until(result_future.done, None)
        except Interrupted:
            print(f'\ncancelling the {what} goal ...', file=sys.stderr, flush=True)
            handle.cancel_goal_async()
            # Later signals are only counted (pma_common.stop): wait for the real end.
            if not session.spin_until(result_future.done, CANCEL_WAIT_S, interruptible=False):
                raise CliError(f'the {what} did not confirm the cancel within '
                               f'{CANCEL_WAIT_S:g} s', FAILED) from None
            response = result_future.result()
            return response.status, response.result, True
        response = result_future.result()
        return response.status, response.result, False
    finally:
        client.destroy()


def sweep_goal(args) -> Sweep.Goal:
    """The Sweep goal `pma sweep`'s flags describe.

    Only the flags given are filled in, so a flag the profile does not use is refused with
    its field's name (the driver's checks, which checked_sweep_goal runs first), not ignored.
    """
    hold_s = args.hold_s
    if hold_s is None:
        hold_s = DEFAULT_STEP_HOLD_S if args.profile in ('staircase', 'forc') else 0.0
    times, pressures = [], []
    if args.profile_csv is not None:
        try:
            times, pressures = read_profile_csv(args.profile_csv)
        except SweepError as error:
            raise CliError(str(error), USAGE) from None
    # The recorder resolves a relative path against its own working directory: send the one
    # the user meant, relative to where they typed it.
    bag_path = os.path.abspath(args.record) if args.record else ''
    return Sweep.Goal(
        profile=args.profile, max_gauge_pressure_pa=args.max_pa, step_pa=args.step_pa,
        hold_s=hold_s, cycles=args.cycles, rest_s=args.rest_s,
        reversal_pressures_pa=args.reversals, ramp_rate_pa_s=args.rate_pa_s,
        sine_amplitude_pa=args.amplitude_pa, sine_offset_pa=args.offset_pa,
        sine_frequency_hz=args.frequency_hz, profile_time_s=times,
        profile_pressure_pa=pressures, forc_count=args.forc_count,
        forc_family=args.forc_family, record=args.record is not None, bag_path=bag_path,
        note=args.note)


# The flag of `pma sweep` behind each goal field, for a refusal that names the field.
FLAG_OF_FIELD = {
    'max_gauge_pressure_pa': '--max', 'step_pa': '--step', 'hold_s': '--hold',
    'cycles': '--cycles', 'rest_s': '--rest', 'reversal_pressures_pa': '--reversals',
    'ramp_rate_pa_s': '--rate', 'sine_amplitude_pa': '--amplitude',
    'sine_offset_pa': '--offset', 'sine_frequency_hz': '--frequency',
    'profile_time_s': '--csv', 'profile_pressure_pa': '--csv', 'forc_count': '--forc-count',
    'forc_family': '--forc-family',
}


def checked_sweep_goal(args) -> Sweep.Goal:
    """sweep_goal, checked before the graph is joined as the driver checks it, but for the
    driver's ceiling (its parameter, which only the driver knows).

    A goal the driver would refuse (`pma sweep` without `--max`, a ramp without `--rate`) is
    refused at once, and a length controller holding a length is not released for nothing.
    """
    goal = sweep_goal(args)
    try:
        plan_goal(SweepGoal.of(goal), ceiling_pa=math.inf)
    except SweepError as error:
        reason = str(error)
        named = sorted((reason.find(name), flag) for name, flag in FLAG_OF_FIELD.items()
                       if name in reason)                 # the field the reason names first
        flag = f' ({named[0][1]})' if named else ''
        raise CliError(f'{reason}{flag}; nothing was sent', USAGE) from None
    return goal


def describe(goal: Sweep.Goal) -> str:
    """One line saying what the goal will do, in kPa and seconds."""
    top = q.kpa(goal.max_gauge_pressure_pa, 0)
    reversals = (f', reversals at {", ".join(q.kpa(r, 0) for r in goal.reversal_pressures_pa)}'
                 if len(goal.reversal_pressures_pa) else '')
    if goal.profile == 'forc':
        text = (f'FORC set: {goal.forc_count} {goal.forc_family or "ascending"} reversal '
                f'curves up to {top} in {q.kpa(goal.step_pa, 0)} steps, hold '
                f'{q.seconds(goal.hold_s)}')
    elif goal.profile == 'ramp':
        text = (f'ramp 0 -> {top} at {goal.ramp_rate_pa_s / 1000.0:g} kPa/s{reversals}, hold '
                f'{q.seconds(goal.hold_s)} at each turn')
    elif goal.profile == 'sine':
        text = (f'sine {q.kpa(goal.sine_offset_pa, 0)} +/- {q.kpa(goal.sine_amplitude_pa, 0)} '
                f'at {goal.sine_frequency_hz:g} Hz')
    elif goal.profile == 'csv':
        duration = goal.profile_time_s[-1] - goal.profile_time_s[0] if len(
            goal.profile_time_s) else 0.0
        text = f'profile of {len(goal.profile_time_s)} points over {q.seconds(duration)}'
    else:
        text = (f'sweep 0 -> {top} in {q.kpa(goal.step_pa, 0)} steps, hold '
                f'{q.seconds(goal.hold_s)}{reversals}')
    text += f', {goal.cycles} {"period" if goal.profile == "sine" else "cycle"}(s)'
    if goal.rest_s:
        text += f', rest {q.seconds(goal.rest_s)} between'
    if goal.record:
        text += f'; recording to {goal.bag_path or "an auto-named bag"}'
    return text


def _say_result(line: str, as_asked: bool) -> None:
    """A goal's last line: on stdout when it did what was asked (or was cancelled by the
    user), on stderr when it was refused or failed, as every verb's refusal is."""
    print(line, file=sys.stdout if as_asked else sys.stderr, flush=True)


def sweep(session: Session, goal: Sweep.Goal, *, timeout_s: float) -> int:
    """Run the goal; a length controller that holds a target is released first, as `pma vent`
    does, or it would take the muscle back (pressurised) once the sweep ends."""
    state = session.latest(PmaState, 'pma/state')
    control = session.latest(ControlState, CONTROL_TOPIC)
    progress = Progress()
    unit = 'setpoint' if goal.profile in STREAMED_PROFILES else 'step'

    def on_feedback(feedback) -> None:
        measured = state.message.gauge_pressure_pa if state.message else math.nan
        progress.show(feedback.progress,
                      f'{unit} {feedback.step_index + 1}/{feedback.step_count}  setpoint '
                      f'{q.kpa(feedback.gauge_setpoint_pa, 0)}  pressure {q.kpa(measured)}  '
                      f'{feedback.sample_count} samples',
                      feedback.step_index if unit == 'step' else round(10 * feedback.progress))

    print(describe(goal), flush=True)
    started = time.monotonic()
    try:
        status, result, cancelled = run_goal(
            session, Sweep, 'pma/sweep', goal, on_feedback=on_feedback, timeout_s=timeout_s,
            what='driver', hint=session.where_hint('pma/state', 'driver_node'),
            before=lambda: release_holding_controller(session, control, timeout_s))
    finally:
        progress.end()
    word = STATUS_WORDS.get(status, f'status {status}')
    _say_result(f'sweep {word} after {q.seconds(time.monotonic() - started)}: '
                f'{result.message} ({result.sample_count} samples)', result.success or cancelled)
    if result.bag_path:
        print(f'bag: {result.bag_path}')
    if holds_target(control.message):          # one that came into the graph too late
        print(f'pma sweep: warning: the length controller holds '
              f'{q.cm(control.message.target_length_m)} and takes the muscle back; `pma vent` '
              'releases it', file=sys.stderr)
    if cancelled:
        return INTERRUPTED
    return OK if result.success else FAILED


def move(session: Session, *, length_m: float, tolerance_m: float, settle_s: float,
         goal_timeout_s: float, timeout_s: float) -> int:
    goal = MoveToLength.Goal(length_m=length_m, tolerance_m=tolerance_m, settle_s=settle_s,
                             timeout_s=goal_timeout_s)
    progress = Progress()
    started = time.monotonic()
    limit = goal_timeout_s or 30.0

    def on_feedback(feedback) -> None:
        progress.show(min(1.0, (time.monotonic() - started) / limit),
                      f'length {q.cm(feedback.estimated_length_m)} (target {q.cm(length_m)}, '
                      f'error {feedback.error_m * 1000:+.1f} mm)  command '
                      f'{q.kpa(feedback.gauge_pressure_command_pa)}', None)

    print(f'moving to {q.cm(length_m)}', flush=True)
    try:
        status, result, cancelled = run_goal(
            session, MoveToLength, 'pma/move_to_length', goal, on_feedback=on_feedback,
            timeout_s=timeout_s, what='length controller',
            hint=session.where_hint('pma/control_state', 'length_controller'))
    finally:
        progress.end()
    word = STATUS_WORDS.get(status, f'status {status}')
    settle = (f', settled after {q.seconds(result.settle_time_s)}'
              if result.success else '')
    _say_result(f'move {word}: {result.message} (at {q.cm(result.final_length_m)}{settle})',
                result.success or cancelled)
    if cancelled:
        return INTERRUPTED
    return OK if result.success else FAILED
