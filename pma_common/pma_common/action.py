"""Sending an action goal when an answer can be lost in discovery.

An action's services lose a new client's first answers as any service does
(pma_common.service): the server drops a reply its reply writer cannot deliver yet, and
`wait_for_server` only sees the request side. A lost goal answer leaves the goal running on
the rig while its sender waits in vain (seen in CI: a sweep accepted, its acceptance never
heard); a lost result answer leaves a finished goal's sender waiting for ever.

A goal request is a command, but its goal ID makes sending it again safe: an action server
accepts an ID at most once (rcl refuses a second goal handle with it), and rejects a request
for an ID it holds without calling its goal callback. So `send_goal`
- first asks for the result of a goal ID no server has seen, again while unanswered: the
  answer (STATUS_UNKNOWN, at once) shows the result replies reach this client, so the real
  goal's result cannot be lost;
- then sends the goal, again under the same ID while unanswered. A resend that is rejected
  means the server holds the ID already: the goal was accepted and its answer lost.
Every goal server here accepts every goal (one that cannot run is aborted with the reason);
with a server that rejects goals, a rejection of a resend is taken for acceptance, and the
goal's result then says STATUS_UNKNOWN.
"""

from __future__ import annotations

import contextlib
import time
import uuid
from collections.abc import Callable
from typing import Any, NamedTuple

from builtin_interfaces.msg import Time
from rclpy.action.client import ClientGoalHandle
from unique_identifier_msgs.msg import UUID

from pma_common.service import RESEND_QUERY_S

Wait = Callable[[Callable[[], bool], float], bool]


class _GoalAnswer(NamedTuple):
    """What a ClientGoalHandle reads of a SendGoal response."""
    accepted: bool
    stamp: Time


def new_goal_id() -> UUID:
    return UUID(uuid=list(uuid.uuid4().bytes))


def _direct(function: Callable[..., Any], *args, **kwargs) -> Any:
    return function(*args, **kwargs)


def results_answered(client, timeout_s: float, wait: Wait,
                     call: Callable[..., Any] = _direct,
                     resend_s: float = RESEND_QUERY_S) -> bool:
    """Whether `client`'s server answered a result query for an ID it never saw, resent
    every `resend_s` while unanswered, within `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    unknown = ClientGoalHandle(client, new_goal_id(), _GoalAnswer(True, Time()))
    while True:
        future = call(unknown.get_result_async)
        if wait(future.done, max(0.0, min(resend_s, deadline - time.monotonic()))):
            return True
        if time.monotonic() >= deadline:
            return False


def send_goal(client, goal, timeout_s: float, wait: Wait, *,
              feedback_callback: Callable[[Any], None] | None = None,
              call: Callable[..., Any] = _direct,
              resend_s: float = RESEND_QUERY_S) -> ClientGoalHandle | None:
    """`goal`'s handle from the server of `client` (an ActionClient whose server is ready),
    or None if the server did not answer within `timeout_s` (a cancel for the goal is sent
    then: it may run all the same).

    `wait(done, seconds)` waits until `done()` or the time is up and says which; `call(f,
    *args, **kwargs)` runs an ActionClient request where it must run (on the spinning thread:
    pma_common.background). The handle's `get_result_async` and `cancel_goal_async` work
    whether the acceptance was heard or inferred from a rejected resend. If `wait` raises
    (a stop signal), a cancel for the goal is sent and the exception goes on.
    """
    deadline = time.monotonic() + timeout_s
    if not results_answered(client, timeout_s, wait, call, resend_s):
        return None
    goal_id = new_goal_id()
    sent = []
    try:
        while True:
            sent.append(call(client.send_goal_async, goal, feedback_callback=feedback_callback,
                             goal_uuid=goal_id))
            remaining = deadline - time.monotonic()
            if wait(lambda: any(future.done() for future in sent),
                    max(0.0, min(resend_s, remaining))):
                answers = [future.result() for future in sent if future.done()]
                accepted = [handle for handle in answers if handle.accepted]
                if accepted:
                    return accepted[0]
                if sent[0].done():
                    return sent[0].result()      # the first request rejected: a real one
                return ClientGoalHandle(client, goal_id, _GoalAnswer(True, answers[0].stamp))
            if time.monotonic() >= deadline:
                _cancel(client, goal_id, call)
                return None
    except BaseException:
        _cancel(client, goal_id, call)
        raise


def _cancel(client, goal_id: UUID, call: Callable[..., Any]) -> None:
    """Cancel a goal given up on before its answer came (a stop signal, the timeout): the
    server may run it all the same. The cancel's answer is not awaited; a failure to send it
    does not hide what stopped the wait."""
    with contextlib.suppress(Exception):
        call(ClientGoalHandle(client, goal_id, _GoalAnswer(True, Time())).cancel_goal_async)
