"""`pma sweep` and `pma move`: an action goal with live feedback; Ctrl-C cancels it.

A stop signal while the goal runs cancels the goal and waits for its result (the driver vents
when a sweep is cancelled; a cancelled move leaves the pressure where it is), so the command
ends only when the rig has ended the run too.

No wait lasts for ever (issue 50; docs/cli.md, "Waits"):
- the result is awaited while the server is there (pma_common.action.ServerWatch: in the
  graph, and answering a liveness query or sending feedback); a server that left the graph
  (2 s) or went silent (3 s) ends the wait with exit 3 and what was lost; a move is also
  given up on GOAL_LATE_S after its own timeout_s, with a cancel;
- after a Ctrl-C, the cancel is sent (again every CANCEL_RESEND_S while unanswered:
  cancelling twice is cancelling once) and the result awaited, but a server that says
  nothing within HEARD_AFTER_STOP_S of the Ctrl-C is taken for gone, one that answers but not
  the cancel is given up on after CANCEL_ANSWER_S (both exit 3: the cancel could not be
  confirmed), and a second Ctrl-C at least SAME_STOP_S after the first ends the wait at once
  (exit 130). Two signals closer together are one Ctrl-C delivered twice (a terminal's and a
  launcher's) and do not cut the wait for the driver's vent short.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable

from action_msgs.msg import GoalStatus
from diagnostic_msgs.msg import KeyValue
from rclpy.action import ActionClient

from pma_cli import quantities as q
from pma_cli.commands import CONTROL_TOPIC, holds_target, release_holding_controller
from pma_cli.recording import Recording
from pma_cli.session import (
    CANCEL_SEND_S,
    FAILED,
    INTERRUPTED,
    NO_ANSWER,
    OK,
    USAGE,
    CliError,
    Interrupted,
    Session,
)
from pma_common import experiment, names
from pma_common.action import ServerWatch
from pma_common.lease import LeaseHolder, commander_name
from pma_common.sweep import (
    STREAMED_PROFILES,
    SweepError,
    SweepGoal,
    plan_goal,
    read_profile_csv,
)
from pma_interfaces.action import MoveToLength, Sweep
from pma_interfaces.msg import ControlState, PmaState

CANCEL_WAIT_S = 15.0         # a cancel answered: its goal's result (a sweep vents first)
CANCEL_ANSWER_S = 3.0        # a server heard from, but not answering the cancel: given up
CANCEL_RESEND_S = 0.5        # an unanswered cancel is sent again this often
HEARD_AFTER_STOP_S = 1.0     # a server that says nothing this long after a Ctrl-C is gone
SAME_STOP_S = 0.5            # signals closer than this to the first are one Ctrl-C
GOAL_LATE_S = 5.0            # a move's result given up on this long after its timeout_s
DRIVER_HEARD_S = 1.0         # a driver whose state was not heard this long acknowledges nothing
MOVE_DEFAULT_TIMEOUT_S = 30.0   # MoveToLength's timeout_s 0 (the action's definition)
DEFAULT_STEP_HOLD_S = 5.0    # pma sweep's hold at each step of a staircase or FORC set
# What a server gone during its goal leaves behind (the sentence after "its result is lost; ").
MOVE_LOST = ('the muscle holds what it was last commanded (the driver keeps the last '
             'setpoint; `pma vent` vents it)')
SWEEP_LOST = ('a driver that stops vents the muscle, and the device vents by itself once no '
              'host commands it (heartbeat_timeout_ms, 1 s by default); a driver cut off from '
              'this command by the network aborts the sweep and vents (commander_timeout_s); '
              '`pma status` shows the rig')
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
             what: str, hint: str, lost: str, before: Callable[[], None] | None = None,
             result_within_s: float | None = None, late: str = '', server: str = '',
             heard_from=None):
    """(status, result, cancelled) of one goal; a stop signal cancels it and its result is
    still awaited, as long as the server is there (module docstring).

    `on_feedback` is called only once the goal is known as accepted, so whatever it shows
    means that a stop signal will cancel the goal and wait for its result. `before` runs
    once the server is there, before the goal is sent. `server` names the
    server's node, said (with how to start it) while it is waited for. `lost` says what a
    server gone during the goal leaves behind; `result_within_s` (from the acceptance), if
    given, is how long the result may take (`late` says why), after which the goal is
    cancelled and given up on. `heard_from` (a session.Latest of a topic the server's node
    publishes) counts as hearing from the server: after a network outage its stream comes
    back at once, before the action's own traffic is resent.
    """
    client = ActionClient(session.node, action_type, name)
    watch = ServerWatch(client)
    if heard_from is not None:
        heard_from.on_message(lambda _: watch.alive())

    # Feedback can be taken before the acceptance it follows (another entity in the wait
    # set): it is held until then, so that a stop signal after feedback was shown cancels
    # a goal this client knows as accepted and waits for its result.
    early: list = []
    handle = None

    def feedback(message) -> None:
        watch.alive()
        if handle is None:
            early[:] = [message.feedback]
        else:
            on_feedback(message.feedback)

    try:
        if not session.spin_until(client.server_is_ready, timeout_s, waiting_for=server):
            start = session.start_hint(server) if server else ''
            raise CliError(f'no {what} answers on {session.resolve(name)} (waited '
                           f'{timeout_s:g} s): {hint}' + (f' Start it: {start}' if start else ''),
                           NO_ANSWER)
        if before is not None:
            before()
        try:
            handle = session.send_goal(client, goal, timeout_s, f'the {what} (goal acceptance)',
                                       feedback_callback=feedback)
        except Interrupted:
            print(f'\ninterrupted before the {what} answered the goal; a cancel for it was '
                  'sent', file=sys.stderr, flush=True)
            raise
        if not handle.accepted:
            raise CliError(f'the {what} rejected the goal')
        if early:
            on_feedback(early.pop())
        result_future = handle.get_result_async()
        watch.alive()                             # the acceptance was just heard
        deadline = None if result_within_s is None else time.monotonic() + result_within_s
        ended = {}

        def done_or_given_up() -> bool:
            if result_future.done():
                return True
            how = watch.poll()
            if how:
                ended['gone'] = how
            elif deadline is not None and time.monotonic() >= deadline:
                ended['late'] = True
            return bool(ended)

        try:
            session.spin_until(done_or_given_up, None)
        except Interrupted:
            print(f'\ncancelling the {what} goal ...', file=sys.stderr, flush=True)
            response = _cancel_and_wait(session, handle, result_future, watch, what=what,
                                        lost=lost)
            return response.status, response.result, True
        if not result_future.done():
            # Cancelled, so that a server that comes back does not run the goal unattended.
            handle.cancel_goal_async()
            session.spin_until(lambda: False, CANCEL_SEND_S, interruptible=False)
            if 'gone' in ended:
                raise CliError(f'the {what} {ended["gone"]} while the goal ran '
                               f'({watch.detail}): its result is lost; {lost}', NO_ANSWER)
            raise CliError(f'no result from the {what} within {late}: a cancel was sent, as the '
                           'goal may run all the same', NO_ANSWER)
        response = result_future.result()
        return response.status, response.result, False
    finally:
        client.destroy()


def _cancel_and_wait(session: Session, handle, result_future, watch: ServerWatch, *, what: str,
                     lost: str):
    """The result response of a goal cancelled after a stop signal; CliError when it cannot
    come or is no longer waited for (module docstring)."""
    stop = session.stop
    stopped_at = stop.requested_at or time.monotonic()
    watch.probe_now()
    cancels = [handle.cancel_goal_async()]
    sent_at = time.monotonic()
    state = {'answered': False, 'why': None}

    def second_stop() -> bool:
        return (stop.last_signal_at is not None
                and stop.last_signal_at - stopped_at >= SAME_STOP_S)

    def done_or_given_up() -> bool:
        nonlocal sent_at
        if result_future.done():
            return True
        now = time.monotonic()
        if not state['answered'] and any(future.done() for future in cancels):
            state['answered'] = True
            watch.alive()
        how = watch.poll()
        if second_stop():
            taken = ('it answered the cancel' if state['answered'] else
                     'the cancel was sent, not yet answered')
            state['why'] = CliError(f'interrupted again: stopped waiting for the {what} to end '
                                    f'the goal ({taken})', INTERRUPTED)
        elif how:
            state['why'] = CliError(f'the {what} {how} ({watch.detail}): the cancel could not '
                                    f'be confirmed and the result is lost; {lost}', NO_ANSWER)
        elif not state['answered'] and not watch.heard_since(stopped_at) \
                and now - stopped_at >= HEARD_AFTER_STOP_S:
            state['why'] = CliError(f'the {what} said nothing within {HEARD_AFTER_STOP_S:g} s '
                                    'of the stop (it left or hangs): the cancel could not be '
                                    f'confirmed and the result is lost; {lost}', NO_ANSWER)
        elif not state['answered'] and now - stopped_at >= CANCEL_ANSWER_S:
            state['why'] = CliError(f'the {what} did not answer the cancel within '
                                    f'{CANCEL_ANSWER_S:g} s (it answers otherwise): the goal may '
                                    'still run; `pma vent` stops it and vents the muscle',
                                    NO_ANSWER)
        elif state['answered'] and now - stopped_at >= CANCEL_WAIT_S:
            state['why'] = CliError(f'the {what} answered the cancel but did not end the goal '
                                    f'within {CANCEL_WAIT_S:g} s of the stop', FAILED)
        elif not state['answered'] and now - sent_at >= CANCEL_RESEND_S:
            cancels.append(handle.cancel_goal_async())     # cancelling twice is cancelling once
            sent_at = now
        return state['why'] is not None

    session.spin_until(done_or_given_up, None, interruptible=False)
    if not result_future.done():
        raise state['why']
    return result_future.result()


def recorded_facts(args, what: str, note_needs_record: bool = False) -> dict[str, str]:
    """The experiment's facts the flags give, for the bag `--record` asks for; CliError
    (USAGE) for a value that cannot be stored, or for facts with no bag to go into."""
    try:
        facts = experiment.from_arguments(args)
    except experiment.ExperimentError as error:
        raise CliError(str(error), USAGE) from None
    flags = [f.flag for f in experiment.FIELDS if f.key in facts]
    if note_needs_record and args.note:
        flags.append('--note')
    if flags and args.record is None:
        raise CliError(f'{", ".join(flags)}: the experiment\'s facts go into the {what}\'s '
                       'bag; add --record', USAGE)
    return facts


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
    custom_data = recorded_facts(args, 'sweep')
    return Sweep.Goal(
        profile=args.profile, max_gauge_pressure_pa=args.max_pa, step_pa=args.step_pa,
        hold_s=hold_s, cycles=args.cycles, rest_s=args.rest_s,
        reversal_pressures_pa=args.reversals, ramp_rate_pa_s=args.rate_pa_s,
        sine_amplitude_pa=args.amplitude_pa, sine_offset_pa=args.offset_pa,
        sine_frequency_hz=args.frequency_hz, profile_time_s=times,
        profile_pressure_pa=pressures, forc_count=args.forc_count,
        forc_family=args.forc_family, record=args.record is not None, bag_path=bag_path,
        note=args.note, start_pressurised=args.start_pressurised,
        custom_data=[KeyValue(key=key, value=value) for key, value in custom_data.items()])


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
    if goal.start_pressurised:
        text += '; from the pressure it has now (no vent to rest first)'
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
    state = session.latest(PmaState, names.STATE)
    control = session.latest(ControlState, CONTROL_TOPIC)
    progress = Progress()
    unit = 'setpoint' if goal.profile in STREAMED_PROFILES else 'step'

    def on_feedback(feedback) -> None:
        measured = state.message.gauge_pressure_pa if state.message else math.nan
        if feedback.phase == 'venting to rest':      # before the first level (docs/driver.md)
            progress.show(0.0, f'venting to rest: {q.kpa(measured)}', 'rest')
            return
        progress.show(feedback.progress,
                      f'{unit} {feedback.step_index + 1}/{feedback.step_count}  setpoint '
                      f'{q.kpa(feedback.gauge_setpoint_pa, 0)}  pressure {q.kpa(measured)}  '
                      f'{feedback.sample_count} samples',
                      feedback.step_index if unit == 'step' else round(10 * feedback.progress))

    # While the goal runs, a commander lease: if this command's host or its network to the
    # rig is lost, the driver aborts the sweep and vents (docs/lab-network.md).
    lease = LeaseHolder(session.node, commander_name(session.node, 'pma sweep'))

    def before() -> None:
        release_holding_controller(session, control, timeout_s)
        lease.hold()

    print(describe(goal), flush=True)
    started = time.monotonic()
    try:
        status, result, cancelled = run_goal(
            session, Sweep, names.SWEEP, goal, on_feedback=on_feedback, timeout_s=timeout_s,
            what='driver', hint=session.where_hint(names.STATE, 'driver_node'),
            lost=SWEEP_LOST, before=before, server='driver_node', heard_from=state)
    finally:
        progress.end()
        heard_at = started if state.received_at is None else state.received_at
        if time.monotonic() - heard_at < DRIVER_HEARD_S:
            lease.release_before_exit()
        else:
            lease.release()                  # a driver not heard from acknowledges nothing
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


MOVE_GOAL_FIELDS = ('length_m', 'tolerance_m', 'settle_s', 'timeout_s')


def move_metadata(goal: MoveToLength.Goal, note: str,
                  facts: dict[str, str]) -> dict[str, str]:
    """A recorded move's custom_data: the experiment's facts, the note, and the goal as sent
    (`move.<field>`; 0 is the action's default, as in the goal)."""
    return {**facts, 'note': note,
            **{f'move.{name}': repr(float(getattr(goal, name))) for name in MOVE_GOAL_FIELDS}}


def move(session: Session, *, length_m: float, tolerance_m: float, settle_s: float,
         goal_timeout_s: float, timeout_s: float, unit: str = 'cm', record: str | None = None,
         note: str = '', facts: dict[str, str] | None = None) -> int:
    """Move to `length_m` and hold it; lengths are printed in `unit` (the user's).

    `moving to ...` is said once the controller follows the goal (its first feedback): a
    target it cannot reach is refused at once, with the reachable range, and no move began.
    With `record` (a bag path, '' = auto-named) a running recorder writes the move, from
    before the goal is sent to its result, into a bag of its own.
    """
    goal = MoveToLength.Goal(length_m=length_m, tolerance_m=tolerance_m, settle_s=settle_s,
                             timeout_s=goal_timeout_s)
    recording = None
    if record is not None:
        recording = Recording(session, record, move_metadata(goal, note, facts or {}),
                              timeout_s)
    try:
        return _move(session, goal, timeout_s=timeout_s, unit=unit)
    finally:
        if recording is not None:
            recording.finish()


def _move(session: Session, goal: MoveToLength.Goal, *, timeout_s: float, unit: str) -> int:
    length_m, goal_timeout_s = goal.length_m, goal.timeout_s
    progress = Progress()
    started = time.monotonic()
    limit = goal_timeout_s or MOVE_DEFAULT_TIMEOUT_S
    moving = []

    def on_feedback(feedback) -> None:
        if not moving:
            moving.append(True)
            print(f'moving to {q.length(length_m, unit)}', flush=True)
        progress.show(min(1.0, (time.monotonic() - started) / limit),
                      f'length {q.length(feedback.estimated_length_m, unit)} (target '
                      f'{q.length(length_m, unit)}, error {feedback.error_m * 1000:+.1f} mm)  '
                      f'command {q.kpa(feedback.gauge_pressure_command_pa)}', None)

    try:
        status, result, cancelled = run_goal(
            session, MoveToLength, names.MOVE_TO_LENGTH, goal, on_feedback=on_feedback,
            timeout_s=timeout_s, what='length controller',
            hint=session.where_hint(names.CONTROL_STATE, 'length_controller'), lost=MOVE_LOST,
            result_within_s=limit + GOAL_LATE_S,
            late=f"{limit + GOAL_LATE_S:g} s (the goal's timeout_s, {limit:g} s, and "
                 f'{GOAL_LATE_S:g} s more)', server='length_controller')
    finally:
        progress.end()
    word = STATUS_WORDS.get(status, f'status {status}')
    settle = (f', settled after {q.seconds(result.settle_time_s)}'
              if result.success else '')
    _say_result(f'move {word}: {q.in_units(result.message, unit)} (measured '
                f'{q.length(result.measured_length_m, unit)}, estimated '
                f'{q.length(result.estimated_length_m, unit)}{settle})',
                result.success or cancelled)
    if cancelled:
        return INTERRUPTED
    return OK if result.success else FAILED
