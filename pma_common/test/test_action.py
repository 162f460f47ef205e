"""`send_goal` sends a goal again under its ID while unanswered, over a real rclpy action.

Discovery cannot be made to drop a goal answer on demand; a client that drops the first one
it receives looks the same to `send_goal` (the answer went out, the goal was accepted, and
nothing came back). Everything else is the real ActionServer and ActionClient.
"""

from __future__ import annotations

import threading
import time

import pytest
import rclpy
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.node import Node
from rclpy.task import Future

from pma_common import names
from pma_common.action import ServerGone, ServerWatch, results_answered, send_goal
from pma_common.background import BackgroundSpin
from pma_common.service import poll
from pma_interfaces.action import Sweep

RESEND_S = 0.3


class LosesGoalAnswers(ActionClient):
    """An ActionClient that never hears the first `lose` answers to its goal requests (1
    unless a test sets it), and counts the goal requests it sends."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.sent = 0
        self.lose = 1
        self.lost = 0

    def send_goal_async(self, *args, **kwargs):
        self.sent += 1
        return super().send_goal_async(*args, **kwargs)

    async def execute(self, taken_data):
        if 'goal' in taken_data and self.lost < self.lose:
            self.lost += 1
            del taken_data['goal']
        await super().execute(taken_data)


class Server:
    """A Sweep server that counts goal callbacks, executions and cancelled goals; `answer(n)`
    decides the n-th goal callback (from 1): 'accept', 'reject', 'late' (accept after 3
    resend periods) or 'never'. A goal runs until cancelled if `until_cancelled`."""

    def __init__(self, node: Node, name: str = names.SWEEP):
        self.node = node
        self.goal_calls = 0
        self.executions = 0
        self.cancelled = 0
        self.until_cancelled = False
        self.answer = lambda n: 'accept'
        self.action = ActionServer(node, Sweep, name, execute_callback=self._execute,
                                   goal_callback=self._on_goal,
                                   cancel_callback=lambda _: CancelResponse.ACCEPT,
                                   callback_group=ReentrantCallbackGroup())

    async def _pause(self, seconds: float) -> None:
        later = Future()
        timer = self.node.create_timer(seconds, lambda: later.done() or later.set_result(None))
        await later
        timer.cancel()

    async def _on_goal(self, _goal) -> GoalResponse:
        self.goal_calls += 1
        answer = self.answer(self.goal_calls)
        if answer == 'never':
            await Future()
        if answer == 'late':
            await self._pause(3 * RESEND_S)
        return GoalResponse.REJECT if answer == 'reject' else GoalResponse.ACCEPT

    async def _execute(self, goal_handle) -> Sweep.Result:
        self.executions += 1
        while self.until_cancelled:
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                self.cancelled += 1
                return Sweep.Result(message='cancelled')
            await self._pause(0.05)
        goal_handle.publish_feedback(Sweep.Feedback(progress=1.0))
        goal_handle.succeed()
        return Sweep.Result(success=True, message=f'execution {self.executions}')


@pytest.fixture
def rig(context):
    """(server, spun client node): each node spun by a thread of its own."""
    server_node = Node('send_goal_server', context=context)
    client_node = Node('send_goal_client', context=context)
    spins = [BackgroundSpin(server_node), BackgroundSpin(client_node)]
    yield Server(server_node), spins[1]
    for spin in spins:
        spin.close()
    for node in (server_node, client_node):
        node.destroy_node()


def ready(spin: BackgroundSpin, client_type=ActionClient, name: str = names.SWEEP):
    client = client_type(spin.node, Sweep, name)
    assert client.wait_for_server(timeout_sec=10)
    return client


def result_of(spin: BackgroundSpin, handle):
    future = spin.call(handle.get_result_async)
    assert poll(future.done, 10), 'no result'
    return future.result()


def test_a_goal_whose_answer_is_lost_is_sent_again_under_its_id_and_runs_once(rig):
    server, spin = rig
    client = ready(spin, LosesGoalAnswers)
    feedback = []
    handle = send_goal(client, Sweep.Goal(), 10, poll, call=spin.call, resend_s=RESEND_S,
                       feedback_callback=lambda m: feedback.append(m.feedback.progress))
    assert handle is not None and handle.accepted
    assert (client.lost, client.sent) == (1, 2)
    # The resend was rejected as the goal ID's duplicate, without a goal callback.
    assert (server.goal_calls, server.executions) == (1, 1)
    answer = result_of(spin, handle)
    assert answer.status == GoalStatus.STATUS_SUCCEEDED
    assert answer.result.message == 'execution 1'
    assert poll(lambda: feedback == [1.0], 5), feedback


def test_an_answered_goal_is_sent_once(rig):
    server, spin = rig
    client = ready(spin, LosesGoalAnswers)
    client.lose = 0
    handle = send_goal(client, Sweep.Goal(), 10, poll, call=spin.call, resend_s=RESEND_S)
    assert handle.accepted and client.sent == 1 and server.goal_calls == 1
    assert result_of(spin, handle).result.message == 'execution 1'


def test_a_server_slower_than_the_resend_period_runs_the_goal_once(rig):
    """The first request waits in the goal callback while its resends arrive: the resend
    that is accepted is the goal, and the first is refused once its callback returns."""
    server, spin = rig
    server.answer = lambda n: 'late' if n == 1 else 'accept'
    client = ready(spin)
    handle = send_goal(client, Sweep.Goal(), 10, poll, call=spin.call, resend_s=RESEND_S)
    assert handle.accepted
    assert result_of(spin, handle).result.message == 'execution 1'
    assert poll(lambda: server.goal_calls == 2, 5)      # the late first call has returned
    threading.Event().wait(2 * RESEND_S)
    assert server.executions == 1


def test_a_rejected_first_request_is_the_answer(rig):
    server, spin = rig
    server.answer = lambda n: 'reject'
    client = ready(spin)
    handle = send_goal(client, Sweep.Goal(), 10, poll, call=spin.call, resend_s=RESEND_S)
    assert handle is not None and not handle.accepted
    assert (server.goal_calls, server.executions) == (1, 0)


def test_a_server_that_never_answers_the_goal_gives_none(rig):
    server, spin = rig
    server.answer = lambda n: 'never'
    client = ready(spin)
    assert send_goal(client, Sweep.Goal(), 1.0, poll, call=spin.call, resend_s=RESEND_S) is None
    # No goal was created, so each resend reached the goal callback; none was answered.
    assert server.goal_calls >= 2 and server.executions == 0


def test_a_goal_whose_answers_are_all_lost_is_cancelled_when_given_up(rig):
    """None after the timeout, and the goal, which runs, cancelled by its ID."""
    server, spin = rig
    server.until_cancelled = True
    client = ready(spin, LosesGoalAnswers)
    client.lose = 1000
    assert send_goal(client, Sweep.Goal(), 1.0, poll, call=spin.call, resend_s=RESEND_S) is None
    assert client.sent >= 3 and server.executions == 1
    assert poll(lambda: server.cancelled == 1, 5), 'the goal was not cancelled'


def test_a_stop_while_the_answer_is_awaited_cancels_the_goal_by_its_id(rig):
    """Ctrl-C at `pma sweep` before the acceptance is heard: the sweep may be running, so it
    is cancelled (by the goal ID, the only name the client has for it)."""
    server, spin = rig
    server.until_cancelled = True
    client = ready(spin, LosesGoalAnswers)
    waits = []

    class Stop(Exception):  # noqa: N818  (a stop, not an error)
        pass

    def wait(done, seconds):
        waits.append(seconds)
        if len(waits) == 2:             # the goal's first wait (the first is the result query's)
            assert poll(lambda: server.executions == 1, 5)   # running; its answer was lost
            raise Stop
        return poll(done, seconds)

    with pytest.raises(Stop):
        send_goal(client, Sweep.Goal(), 10, wait, call=spin.call, resend_s=RESEND_S)
    assert poll(lambda: server.cancelled == 1, 5), 'the goal was not cancelled'
    assert client.sent == 1


def test_no_result_answer_without_a_server_is_false(context):
    node = Node('send_goal_alone', context=context)
    spin = BackgroundSpin(node)
    try:
        client = ActionClient(node, Sweep, 'pma/nobody')
        assert not results_answered(client, 1.0, poll, spin.call, resend_s=RESEND_S)
    finally:
        spin.close()
        node.destroy_node()


# -- ServerWatch: a server gone while its goal runs (issue 50) -----------------------------


@pytest.fixture
def watched(context):
    """(Server, its node's BackgroundSpin, the client node's BackgroundSpin, a client): a
    Sweep server whose goals run until cancelled, in a context of its own (a participant
    of its own, as a server in another process has: leaving, it says goodbye)."""
    server_context = Context()
    rclpy.init(context=server_context)
    server_node = Node('watched_server', context=server_context)
    client_node = Node('watching_client', context=context)
    server_spin, client_spin = BackgroundSpin(server_node), BackgroundSpin(client_node)
    # A name of its own: the servers of the tests above linger in the process (destroy_node
    # leaves an ActionServer in place).
    server = Server(server_node, 'pma/watched')
    server.until_cancelled = True
    client = ready(client_spin, name='pma/watched')
    yield server, server_spin, client_spin, client
    client_spin.close()
    client_node.destroy_node()
    if not getattr(server, 'ended', False):
        end(server, server_spin)


def end(server: Server, spin: BackgroundSpin) -> None:
    """The server's node ends as a process's does: its participant says goodbye."""
    server.ended = True
    spin.close()
    server.action.destroy()
    server.node.destroy_node()
    server.node.context.try_shutdown()
    server.node.context.destroy()


def test_a_server_that_answers_is_not_gone(watched):
    _, _, client_spin, client = watched
    watch = ServerWatch(client, call=client_spin.call, gone_grace_s=0.3, silent_s=0.6,
                        probe_s=0.1)
    assert not poll(lambda: bool(watch.poll()), 2.0), watch.detail


def test_a_server_that_stops_answering_is_gone_while_still_in_the_graph(watched):
    """A process killed outright stays in the graph until its DDS lease ends (20 s): its
    silence tells first."""
    _, server_spin, client_spin, client = watched
    watch = ServerWatch(client, call=client_spin.call, gone_grace_s=0.3, silent_s=0.6,
                        probe_s=0.1)
    assert not poll(lambda: bool(watch.poll()), 0.5)
    server_spin.close()                               # nothing answers from here on
    assert poll(lambda: watch.poll() == 'stopped answering', 3.0)
    assert client.server_is_ready()
    assert watch.detail.startswith('nothing heard from it for ')


def test_a_server_that_leaves_the_graph_is_gone_after_the_grace(watched):
    server, server_spin, client_spin, client = watched
    watch = ServerWatch(client, call=client_spin.call, gone_grace_s=0.5, silent_s=30.0,
                        probe_s=0.1)
    end(server, server_spin)
    assert poll(lambda: not client.server_is_ready(), 5.0)
    left = time.monotonic()
    assert poll(lambda: watch.poll() == 'left the graph', 3.0)
    assert time.monotonic() - left >= 0.5 - 0.25      # the grace (less one graph check)
    assert watch.detail.startswith('not in the graph for ')


def test_feedback_counts_as_a_sign_of_life(watched):
    _, server_spin, client_spin, client = watched
    watch = ServerWatch(client, call=client_spin.call, silent_s=0.5, probe_s=0.1)
    server_spin.close()
    for _ in range(8):
        time.sleep(0.1)
        watch.alive()                                 # what the goal's feedback calls
        assert watch.poll() == ''
    assert poll(lambda: watch.poll() == 'stopped answering', 3.0)


def test_wait_for_result_says_the_server_went_away(watched):
    """BackgroundSpin.wait_for_result (the demo's waits) ends with ServerGone, not at its
    timeout."""
    _, server_spin, client_spin, client = watched
    handle = client_spin.send_goal(client, Sweep.Goal(), 10)
    server_spin.close()
    started = time.monotonic()
    with pytest.raises(ServerGone, match='driver stopped answering while waiting for the '
                                         'sweep'):
        client_spin.wait_for_result(client, handle, 60, 'the sweep', server='driver',
                                    watch=ServerWatch(client, call=client_spin.call,
                                                      silent_s=0.5, probe_s=0.1))
    assert time.monotonic() - started < 3.0
