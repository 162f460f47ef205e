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

While the goal runs, its sender waits for the result, which a server that went away never
sends: `ServerWatch` tells that the server is gone, so the wait ends with what was lost
instead of lasting for ever (issue 50).
"""

from __future__ import annotations

import contextlib
import math
import time
import uuid
from collections.abc import Callable
from typing import Any, NamedTuple

from builtin_interfaces.msg import Time
from rclpy.action.client import ClientGoalHandle
from unique_identifier_msgs.msg import UUID

from pma_common.service import RESEND_QUERY_S

Wait = Callable[[Callable[[], bool], float], bool]

# ServerWatch: each sign that the server is gone must last this long, so that a discovery
# hiccup or a busy moment does not end a goal.
GONE_GRACE_S = 2.0     # out of the graph (its node ended: discovery shows that at once)
SILENT_S = 3.0         # nothing heard: no answer to a liveness query, no feedback
PROBE_PERIOD_S = 0.5   # a liveness query is sent this often
GRAPH_CHECK_S = 0.2    # the graph is looked at this often


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


class ServerGone(RuntimeError):  # noqa: N818  (what became of a server, not a bug)
    """The action server went away while a goal of ours ran (ServerWatch says how)."""


class ServerWatch:
    """Whether the server that took a goal is still there, for a wait on the goal's result.

    A server that went away never sends the result. Two signs tell it, each only once it has
    lasted its grace period:
    - it left the graph: `client.server_is_ready()` false for `gone_grace_s`. A node that ends
      (a Ctrl-C, a crash that Python survives long enough) says goodbye in discovery;
    - it stopped answering: no answer to a result query for a goal ID it never saw, sent every
      `probe_s`, and no feedback (`alive()`) for `silent_s`. Every rclpy action server answers
      such a query at once (STATUS_UNKNOWN; results_answered relies on the same), so silence
      means a process that is dead or hung. A process killed outright (SIGKILL, the OOM
      killer, a power cut on a remote machine) says no goodbye, and DDS keeps it in the graph
      until its lease ends (Fast DDS: 20 s), so the graph alone would take that long.

    `poll()` is called from the wait's loop: it sends the queries (through `call`, on the
    spinning thread where there is one: pma_common.background) and says how the server went
    ('left the graph', 'stopped answering'; '' while it is there), `detail` since when.
    """

    def __init__(self, client, call: Callable[..., Any] = _direct, *,
                 gone_grace_s: float = GONE_GRACE_S, silent_s: float = SILENT_S,
                 probe_s: float = PROBE_PERIOD_S, clock: Callable[[], float] = time.monotonic):
        self.client = client
        self.call = call
        self.gone_grace_s = gone_grace_s
        self.silent_s = silent_s
        self.probe_s = probe_s
        self.clock = clock
        self.heard_at = clock()        # the goal's acceptance was the last word heard
        self.missing_since: float | None = None
        self.detail = ''
        self._graph_checked = -math.inf
        self._probed = -math.inf
        self._probes: list = []

    def alive(self) -> None:
        """A sign of life other than a query's answer (the goal's feedback)."""
        self.heard_at = self.clock()

    def probe_now(self) -> None:
        """Send a liveness query at the next poll, whenever the last one went."""
        self._probed = -math.inf

    def heard_since(self, moment: float) -> bool:
        return self.heard_at >= moment

    def poll(self) -> str:
        """How the server went ('' while it is there); sends the queries that are due."""
        now = self.clock()
        for future in [f for f in self._probes if f.done()]:
            self._probes.remove(future)
            self.heard_at = max(self.heard_at, now)
        if now - self._probed >= self.probe_s:
            self._probed = now
            unknown = ClientGoalHandle(self.client, new_goal_id(), _GoalAnswer(True, Time()))
            with contextlib.suppress(Exception):   # a client going away: the graph says so
                self._probes.append(self.call(unknown.get_result_async))
        if now - self._graph_checked >= GRAPH_CHECK_S:
            self._graph_checked = now
            if self.client.server_is_ready():
                self.missing_since = None
            elif self.missing_since is None:
                self.missing_since = now
        if self.missing_since is not None and now - self.missing_since >= self.gone_grace_s:
            self.detail = f'not in the graph for {now - self.missing_since:.0f} s'
            return 'left the graph'
        if now - self.heard_at >= self.silent_s:
            self.detail = f'nothing heard from it for {now - self.heard_at:.0f} s'
            return 'stopped answering'
        return ''
