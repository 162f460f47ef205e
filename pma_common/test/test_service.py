"""`ask` resends a query whose answer never came, over a real rclpy service.

A server cannot be made to lose a reply in discovery on demand, but it can leave a request
unanswered: an async callback that waits forever. To the client the two look the same.
"""

from __future__ import annotations

import threading

import pytest
import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.task import Future
from std_srvs.srv import Trigger

from pma_common.service import ask, poll


@pytest.fixture
def server_and_client():
    """(client, requests seen, requests to leave unanswered: a list of numbers from 1)."""
    context = Context()
    rclpy.init(context=context)
    server = rclpy.create_node('ask_test_server', context=context)
    caller = rclpy.create_node('ask_test_client', context=context)
    seen: list[int] = []
    unanswered: set[int] = set()

    async def on_request(request, response):
        seen.append(len(seen) + 1)
        if seen[-1] in unanswered:
            await Future()                  # never done: this request gets no reply
        response.success, response.message = True, f'answer to request {seen[-1]}'
        return response

    # Reentrant: a request left waiting must not hold back the next one.
    server.create_service(Trigger, 'ask_test', on_request,
                          callback_group=ReentrantCallbackGroup())
    client = caller.create_client(Trigger, 'ask_test')
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(server)
    executor.add_node(caller)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    assert client.wait_for_service(timeout_sec=10)
    yield client, seen, unanswered
    context.try_shutdown()
    spinner.join(5)
    executor.shutdown()


def test_an_unanswered_query_is_sent_again_and_the_second_answer_returned(server_and_client):
    client, seen, unanswered = server_and_client
    unanswered.add(1)
    response = ask(client, Trigger.Request(), timeout_s=10, wait=poll, resend_s=0.3)
    assert response is not None and response.message == 'answer to request 2'
    assert seen == [1, 2]


def test_an_answered_query_is_sent_once(server_and_client):
    client, seen, _ = server_and_client
    response = ask(client, Trigger.Request(), timeout_s=10, wait=poll, resend_s=0.3)
    assert response.message == 'answer to request 1' and seen == [1]


def test_no_answer_within_the_timeout_is_none(server_and_client):
    client, seen, unanswered = server_and_client
    unanswered.update(range(1, 100))
    assert ask(client, Trigger.Request(), timeout_s=1.0, wait=poll, resend_s=0.3) is None
    assert 3 <= len(seen) <= 5, seen
