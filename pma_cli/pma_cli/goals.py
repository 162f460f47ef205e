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

from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient

from pma_cli import quantities as q
from pma_cli.session import FAILED, INTERRUPTED, NO_ANSWER, OK, CliError, Interrupted, Session
from pma_interfaces.action import MoveToLength, Sweep
from pma_interfaces.msg import PmaState

CANCEL_WAIT_S = 15.0
STATUS_WORDS = {GoalStatus.STATUS_SUCCEEDED: 'succeeded', GoalStatus.STATUS_ABORTED: 'aborted',
                GoalStatus.STATUS_CANCELED: 'cancelled'}


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
             what: str, hint: str):
    """(status, result) of one goal; a stop signal cancels it and its result is still awaited."""
    client = ActionClient(session.node, action_type, name)
    try:
        if not session.spin_until(client.server_is_ready, timeout_s):
            raise CliError(f'no {what} answers on {session.resolve(name)} (waited '
                           f'{timeout_s:g} s): {hint}', NO_ANSWER)
        sent = client.send_goal_async(goal, feedback_callback=lambda m: on_feedback(m.feedback))
        handle = session.wait_future(sent, timeout_s, f'the {what} (goal acceptance)')
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


def sweep(session: Session, *, max_pa: float, step_pa: float, hold_s: float, cycles: int,
          reversals_pa: list[float], record: str | None, note: str, timeout_s: float) -> int:
    bag_path = ''
    if record is not None and record:
        # The recorder resolves a relative path against its own working directory: send the
        # one the user meant, relative to where they typed it.
        bag_path = os.path.abspath(record)
    goal = Sweep.Goal(max_gauge_pressure_pa=max_pa, step_pa=step_pa, hold_s=hold_s,
                      cycles=cycles, reversal_pressures_pa=reversals_pa,
                      record=record is not None, bag_path=bag_path, note=note)
    state = session.latest(PmaState, 'pma/state')
    progress = Progress()

    def on_feedback(feedback) -> None:
        measured = state.message.gauge_pressure_pa if state.message else math.nan
        progress.show(feedback.progress,
                      f'step {feedback.step_index + 1}/{feedback.step_count}  setpoint '
                      f'{q.kpa(feedback.gauge_setpoint_pa, 0)}  pressure {q.kpa(measured)}  '
                      f'{feedback.sample_count} samples', feedback.step_index)

    print(f'sweep 0 -> {q.kpa(max_pa, 0)} in {q.kpa(step_pa, 0)} steps, hold '
          f'{q.seconds(hold_s)}, {cycles} cycle(s)'
          + (f', reversals at {", ".join(q.kpa(r, 0) for r in reversals_pa)}'
             if reversals_pa else '')
          + (f'; recording to {bag_path or "an auto-named bag"}' if record is not None else ''),
          flush=True)
    started = time.monotonic()
    try:
        status, result, cancelled = run_goal(
            session, Sweep, 'pma/sweep', goal, on_feedback=on_feedback, timeout_s=timeout_s,
            what='driver', hint=session.where_hint('pma/state', 'driver_node'))
    finally:
        progress.end()
    word = STATUS_WORDS.get(status, f'status {status}')
    print(f'sweep {word} after {q.seconds(time.monotonic() - started)}: {result.message} '
          f'({result.sample_count} samples)')
    if result.bag_path:
        print(f'bag: {result.bag_path}')
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
    print(f'move {word}: {result.message} (at {q.cm(result.final_length_m)}{settle})')
    if cancelled:
        return INTERRUPTED
    return OK if result.success else FAILED
