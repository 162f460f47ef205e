"""One short-lived ROS node per `pma` command, spun on the main thread until there is an answer.

Waits check the process's stop request (pma_common.stop) every spin, so Ctrl-C, SIGTERM and
SIGHUP end a wait with `Interrupted` and the verb can clean up (cancel its goal) with the
context still valid. Names given to the session are relative, so `--namespace left` points
every topic, service and action at /left/... as `__ns:=/left` does for the nodes.
"""

from __future__ import annotations

import os
import sys
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
WAITING_NOTE_S = 1.0   # a node not in the graph by then: say what is waited for
# How to start each node of a muscle by hand, for a verb that waits for one (`pma up` starts
# them all); `{ns}` takes `-r __ns:=/left` outside the root namespace.
START = {'driver_node': 'pma run pma_driver driver_node --ros-args{ns} -p port:=/dev/pma0',
         'model_node': 'pma run pma_model model_node{ros_args}',
         'length_controller': 'pma run pma_control length_controller{ros_args}',
         'recorder': 'pma run pma_bag record --idle{ros_args}'}


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

    def __init__(self, namespace: str, stop: StopRequest, verb: str = '', up: bool = False):
        self.stop = stop
        self.verb = verb                       # names the notes on stderr: `pma set: ...`
        self.up = up                           # `pma up` exists: hints name it
        self._waiting_said: set[str] = set()
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

    def running(self, node: str) -> bool:
        """Whether the node (relative to our namespace, or absolute) is in the graph."""
        wanted = self.node_name(node)
        return any(f'{ns.rstrip("/")}/{name}' == wanted
                   for name, ns in self.node.get_node_names_and_namespaces())

    def start_hint(self, node: str) -> str:
        """`pma up`, or `pma run ...`: how to start one of a muscle's nodes (START) in our
        namespace; '' for another node."""
        name = node.rsplit('/', 1)[-1]
        if name not in START:
            return ''
        ns = '' if self.namespace == '/' else f' -r __ns:={self.namespace}'
        by_hand = START[name].format(ns=ns, ros_args=f' --ros-args{ns}' if ns else '')
        up = 'pma up' + ('' if self.namespace == '/' else
                         f' --namespace {self.namespace.lstrip("/")}')
        return ', or '.join([f'`{up}`'] * self.up + [f'`{by_hand}`'])

    def waiting_note(self, node: str) -> str:
        """What a verb waits for, and how to start it: said when it is not there."""
        name = node.rsplit('/', 1)[-1]
        namespace = self.node_name(node).rsplit('/', 1)[0] or '/'
        start = self.start_hint(node)
        return (f'waiting for {name} in {namespace} (not seen yet): is it running?'
                + (f' ({start})' if start else '') + self._elsewhere(name))

    def _elsewhere(self, name: str) -> str:
        found = sorted({ns for n, ns in self.node.get_node_names_and_namespaces()
                        if n == name and ns != self.namespace})
        if not found:
            return ''
        flags = ', '.join(f'--namespace {n.lstrip("/") or "/"}' for n in found)
        return f' It runs in {", ".join(found)}: add {flags}.'

    # -- waiting -----------------------------------------------------------------------

    def spin_for(self, duration_s: float) -> None:
        self.spin_until(lambda: False, duration_s)

    def spin_until(self, done: Callable[[], bool], timeout_s: float | None,
                   interruptible: bool = True, waiting_for: str = '') -> bool:
        """Spin until `done()`; False on timeout; Interrupted on a stop signal (if asked).

        `waiting_for` names a node `done` needs: if it is not in the graph WAITING_NOTE_S into
        the wait, a note on stderr says once what is waited for and how to start it, so that a
        wait for a node that is not running is not a silent one.
        """
        started = time.monotonic()
        deadline = None if timeout_s is None else started + timeout_s
        while True:
            if interruptible and self.stop.is_set():
                raise Interrupted(self.stop.reason)
            if done():
                return True
            if waiting_for and waiting_for not in self._waiting_said \
                    and time.monotonic() - started >= WAITING_NOTE_S:
                self._waiting_said.add(waiting_for)
                if not self.running(waiting_for):
                    print(f'{" ".join(("pma", self.verb)).strip()}: '
                          f'{self.waiting_note(waiting_for)}', file=sys.stderr, flush=True)
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

    def wait_for_service(self, client, timeout_s: float, hint: str, *, node: str = '') -> None:
        """Until the service is there; `node`, its server, is named while waited for."""
        if not self.spin_until(client.service_is_ready, timeout_s, waiting_for=node):
            raise CliError(f'nothing serves {client.srv_name} (waited {timeout_s:g} s): {hint}',
                           NO_ANSWER)

    def answer(self, client, request, timeout_s: float, query: bool = False):
        """The response to `request` on a service already seen as ready; a query is resent
        while unanswered (pma_common.service), and so is a command that a resend cannot
        repeat (one named by a request ID); any other command is sent once."""
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

    def call(self, client, request, timeout_s: float, hint: str, query: bool = False, *,
             node: str = ''):
        """Call a service once it is there; its response (see `answer` for `query`)."""
        self.wait_for_service(client, timeout_s, hint, node=node)
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
        self.received_at: float | None = None     # monotonic time of the newest message
        self.count = 0
        self.history: list = []
        self._keep = keep
        self._callbacks: list[Callable] = []
        self.subscription = node.create_subscription(msg_type, topic, self._on_message, qos)

    def _on_message(self, message) -> None:
        self.message = message
        self.received_at = time.monotonic()
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
