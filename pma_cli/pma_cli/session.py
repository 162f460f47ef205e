"""One short-lived ROS node per `pma` command, spun on the main thread until there is an answer.

Waits check the process's stop request (pma_common.stop) every spin, so Ctrl-C, SIGTERM and
SIGHUP end a wait with `Interrupted` and the verb can clean up (cancel its goal) with the
context still valid. Names given to the session are relative, so `--namespace left` points
every topic, service and action at /left/... as `__ns:=/left` does for the nodes.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.task import Future

from pma_common.action import send_goal
from pma_common.service import ask
from pma_common.stop import StopRequest

# Exit codes of every verb (docs/cli.md).
OK = 0
FAILED = 1          # refused, aborted or failed; the message says why
USAGE = 2           # a wrong argument (argparse's own code)
NO_ANSWER = 3       # nobody answered: the node is not running, or in another namespace
INTERRUPTED = 130   # stopped by Ctrl-C (or SIGTERM/SIGHUP) before it finished; goals cancelled

SPIN_S = 0.05
CANCEL_SEND_S = 0.5    # a cancel sent on the way out (send_goal) is given this long to leave


class Interrupted(Exception):  # noqa: N818  (a stop, not an error)
    """A stop signal arrived while waiting."""


class CliError(Exception):
    """A failure to report in one line, with its exit code."""

    def __init__(self, message: str, code: int = FAILED):
        super().__init__(message)
        self.code = code


def namespace_of(text: str) -> str:
    """`left`, `/left`, `/left/` -> `/left`; '' or `/` -> `/`."""
    stripped = text.strip().strip('/')
    return f'/{stripped}'


class Session:
    """A hidden node in the command's namespace, and waits that a stop signal interrupts."""

    def __init__(self, namespace: str, stop: StopRequest):
        self.stop = stop
        self.started = time.monotonic()        # discovery of the other nodes began here
        self.namespace = namespace_of(namespace)
        # A leading underscore hides the node from `ros2 node list`.
        self.node = Node(f'_pma_cli_{os.getpid()}', namespace=self.namespace)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown(timeout_sec=0.0)

    # -- names -------------------------------------------------------------------------

    def resolve(self, name: str) -> str:
        """Fully qualified name of a relative topic or service name, as the nodes see it."""
        return self.node.resolve_topic_name(name)

    def node_name(self, name: str) -> str:
        """`driver_node` -> `/left/driver_node`; absolute names stay."""
        if name.startswith('/'):
            return name
        return f'{self.namespace.rstrip("/")}/{name}'

    # -- waiting -----------------------------------------------------------------------

    def spin_for(self, duration_s: float) -> None:
        self.spin_until(lambda: False, duration_s)

    def spin_until(self, done: Callable[[], bool], timeout_s: float | None,
                   interruptible: bool = True) -> bool:
        """Spin until `done()`; False on timeout; Interrupted on a stop signal (if asked)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            if interruptible and self.stop.is_set():
                raise Interrupted(self.stop.reason)
            if done():
                return True
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return False
            self.executor.spin_once(timeout_sec=SPIN_S if remaining is None
                                    else min(SPIN_S, remaining))

    def wait_future(self, future: Future, timeout_s: float, what: str):
        """The future's result; CliError(NO_ANSWER) if none comes within the timeout."""
        if not self.spin_until(future.done, timeout_s):
            raise CliError(f'no answer from {what} within {timeout_s:g} s', NO_ANSWER)
        return future.result()

    def send_goal(self, client, goal, timeout_s: float, what: str, feedback_callback=None):
        """The goal's handle from `client`'s server (ready); sent again under its goal ID
        while unanswered, so it runs once (pma_common.action). Given up on (no answer, or
        Interrupted), the goal was cancelled by its ID; the cancel gets CANCEL_SEND_S to
        leave before the node goes."""
        try:
            handle = send_goal(client, goal, timeout_s, self.spin_until,
                               feedback_callback=feedback_callback)
        except Interrupted:
            self.spin_until(lambda: False, CANCEL_SEND_S, interruptible=False)
            raise
        if handle is None:
            self.spin_until(lambda: False, CANCEL_SEND_S, interruptible=False)
            raise CliError(f'no answer from {what} within {timeout_s:g} s; a cancel for the '
                           'goal was sent, as it may run all the same', NO_ANSWER)
        return handle

    def wait_for_service(self, client, timeout_s: float, hint: str) -> None:
        if not self.spin_until(client.service_is_ready, timeout_s):
            raise CliError(f'nothing serves {client.srv_name} (waited {timeout_s:g} s): {hint}',
                           NO_ANSWER)

    def answer(self, client, request, timeout_s: float, query: bool = False):
        """The response to `request` on a service already seen as ready; a query is resent
        while unanswered (pma_common.service), a command is sent once."""
        if query:
            response = ask(client, request, timeout_s, self.spin_until)
            if response is None:
                raise CliError(f'no answer from {client.srv_name} within {timeout_s:g} s',
                               NO_ANSWER)
            return response
        future = client.call_async(request)
        if not self.spin_until(future.done, timeout_s):
            raise CliError(f'no answer from {client.srv_name} within {timeout_s:g} s; it may '
                           'have been carried out all the same (an answer to a new client can '
                           'be lost), so check before repeating it', NO_ANSWER)
        return future.result()

    def call(self, client, request, timeout_s: float, hint: str, query: bool = False):
        """Call a service once it is there; its response (see `answer` for `query`)."""
        self.wait_for_service(client, timeout_s, hint)
        return self.answer(client, request, timeout_s, query)

    # -- topics ------------------------------------------------------------------------

    def latest(self, msg_type, topic: str, qos: QoSProfile = qos_profile_sensor_data,
               keep: int = 0) -> Latest:
        """Subscribe and keep the newest message (and the last `keep`) as they come."""
        return Latest(self.node, msg_type, topic, qos, keep)

    def other_namespaces_with(self, topic: str) -> list[str]:
        """Namespaces where `topic` (relative) exists, other than ours: a hint for --namespace."""
        found = set()
        suffix = '/' + topic.strip('/')
        for name, _ in self.node.get_topic_names_and_types():
            if name.endswith(suffix):
                namespace = name[:-len(suffix)] or '/'
                if namespace != self.namespace:
                    found.add(namespace)
        return sorted(found)

    def where_hint(self, topic: str, what: str) -> str:
        """'is X running? ...' with the namespaces where the topic does exist."""
        others = self.other_namespaces_with(topic)
        hint = f'is {what} running in namespace {self.namespace}?'
        if others:
            # The root namespace is `--namespace /` (an empty flag would read as a typo).
            flags = ', '.join(f'--namespace {n.lstrip("/") or "/"}' for n in others)
            hint += f' It runs in {", ".join(others)}: add {flags}.'
        return hint


class Latest:
    """The newest message of a topic, a count, and optionally a short history."""

    def __init__(self, node: Node, msg_type, topic: str, qos: QoSProfile, keep: int):
        self.message = None
        self.count = 0
        self.history: list = []
        self._keep = keep
        self._callbacks: list[Callable] = []
        self.subscription = node.create_subscription(msg_type, topic, self._on_message, qos)

    def _on_message(self, message) -> None:
        self.message = message
        self.count += 1
        if self._keep:
            self.history.append(message)
            del self.history[:-self._keep]
        for callback in self._callbacks:
            callback(message)

    def on_message(self, callback: Callable) -> None:
        self._callbacks.append(callback)


def ros_time_s(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec
