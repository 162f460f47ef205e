"""The SweepRunner's Recorder as calls to a running recorder node (pma_bag record).

The recorder serves `~/start` (pma_interfaces/srv/StartRecording) and `~/stop`
(StopRecording). The clients are made once, with the node, so they are matched long before
the first goal (a client made just before its call can lose the answer while the server's
reply writer is still matching it). Called from the sweep's own thread, never from the
executor thread that must deliver the answer.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.client import Client
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher

from pma_common.commands import has_ros2_cli, run_command
from pma_common.service import ask, poll, start_recording_request
from pma_driver.sweep_runner import RecorderError, RecordingSummary
from pma_interfaces.srv import StartRecording, StopRecording

DEFAULT_NAME = 'recorder'


def how_to_start(start_service: str) -> str:
    """How to start the recorder whose `~/start` is this (fully qualified) service."""
    namespace, name, _ = start_service.rsplit('/', 2)
    run = run_command('pma_bag', 'record', '--idle')
    launch = 'ros2 launch pma_bringup bringup.launch.py record:=true'
    remaps = ''
    if namespace:
        remaps += f' -r __ns:={namespace}'
        launch += f' namespace:={namespace.lstrip("/")}'
    if name != DEFAULT_NAME:
        remaps += f' -r __node:={name}'
    if remaps:
        run += f' --ros-args{remaps}'
    if not has_ros2_cli():      # no `ros2 launch` on the wheels path
        return f'start one: `{run}`'
    return f'start one: `{run}`, or the bring-up launch with a recorder (`{launch}`)'


class RecorderClient:
    def __init__(self, node: Node, recorder: str, timeout_s: float,
                 publishers: Callable[[], Sequence[Publisher]] = tuple,
                 last_words: Callable[[], Sequence[Publisher]] = tuple):
        self._node = node
        self.recorder = recorder
        self.timeout_s = timeout_s
        self._publishers = publishers       # ours, whose samples the bag must not miss
        # ours (reliable), whose last message before ~/stop the bag must hold (a sweep's END)
        self._last_words = last_words
        group = MutuallyExclusiveCallbackGroup()   # answers come while the sweep thread waits
        self.start_service = node.resolve_service_name(f'{recorder}/start')
        self.stop_service = node.resolve_service_name(f'{recorder}/stop')
        self._start = node.create_client(StartRecording, self.start_service,
                                         callback_group=group)
        self._stop = node.create_client(StopRecording, self.stop_service,
                                        callback_group=group)

    def destroy(self) -> None:
        self._node.destroy_client(self._start)
        self._node.destroy_client(self._stop)

    def start(self, bag_path: str, custom_data: Mapping[str, str]) -> str:
        response = self._call(self._start, start_recording_request(bag_path, custom_data),
                              resend=True)
        if response is None:
            # It may have started after all: leave it idle rather than recording forever.
            self._call(self._stop, StopRecording.Request(), quiet=True)
            raise RecorderError(f'no answer from {self.start_service} within '
                                f'{self.timeout_s:g} s')
        if not response.success:
            raise RecorderError(f'the recorder refused to start: {response.message}')
        self._wait_until_heard()
        return response.bag_path

    def _wait_until_heard(self) -> None:
        """Until each of our publishers counts every reader the graph shows (<= timeout).

        The recorder's readers may have matched our writers before our writers know of them,
        and a writer sends only to readers it knows: without this the bag can miss the
        sweep's first samples.
        """
        deadline = time.monotonic() + self.timeout_s
        for publisher in self._publishers():
            readers = len(self._node.get_subscriptions_info_by_topic(publisher.topic_name))
            while publisher.get_subscription_count() < readers \
                    and time.monotonic() < deadline:
                time.sleep(0.01)

    def check(self) -> None:
        """RecorderError unless the recorder's ~/start is there (nothing is started)."""
        if not self._start.wait_for_service(timeout_sec=self.timeout_s):
            raise self._missing(self._start)

    def _missing(self, client: Client) -> RecorderError:
        return RecorderError(
            f'no recorder answers at {client.service_name} (parameter sweep.recorder = '
            f'{self.recorder!r}) within {self.timeout_s:g} s: ' + how_to_start(self.start_service))

    def stop(self) -> RecordingSummary:
        # The recorder ends the bag at the request: what is still on its way to it is not in
        # the bag, but for a model's late predictions (a sweep's END record was lost so).
        # Acknowledged by its reader first, a message is handled before the request (rclpy
        # takes subscriptions before services).
        for publisher in self._last_words():
            publisher.wait_for_all_acked(Duration(seconds=min(self.timeout_s, 2.0)))
        response = self._call(self._stop, StopRecording.Request())
        if response is None:
            raise RecorderError(f'no answer from {self.stop_service} within '
                                f'{self.timeout_s:g} s')
        if not response.success:
            raise RecorderError(f'the recorder could not finish the bag: {response.message}')
        return RecordingSummary(response.bag_path, response.message_count,
                                response.lost_message_count)

    def _call(self, client: Client, request, quiet: bool = False, resend: bool = False):
        """The answer, or None when none came within the timeout; RecorderError: no recorder.
        With `resend`, the request is sent again while unanswered (pma_common.service.ask)."""
        deadline = time.monotonic() + self.timeout_s
        if not client.wait_for_service(timeout_sec=self.timeout_s):
            if quiet:
                return None
            raise self._missing(client)
        if resend:
            return ask(client, request, max(0.0, deadline - time.monotonic()), poll)
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not done.wait(max(0.0, deadline - time.monotonic())):
            client.remove_pending_request(future)
            return None
        return future.result()
