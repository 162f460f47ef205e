"""A bag of one command's run, written by a running recorder (`pma move --record`).

The recorder (`pma run pma_bag record --idle`, `pma up --record`, the launch file's
`record:=true`) serves `~/start` and `~/stop`; the bag carries the experiment's facts and the
command's goal in its custom_data (docs/bags.md). The Sweep action records through the same
services from the driver, so that a sweep's bag holds exactly its levels; a move is recorded
from here, as the length controller knows nothing of bags.
"""

from __future__ import annotations

import os
import sys

from pma_cli.session import CliError, Session
from pma_common.service import SERVICE_QOS, start_recording_request
from pma_interfaces.srv import StartRecording, StopRecording

RECORDER = 'recorder'     # the recorder's node name in the command's namespace
STOP_WAIT_S = 5.0         # for the bag to be finished, even after a Ctrl-C


class Recording:
    """A bag started on the recorder; `finish()` ends it and says what it holds."""

    def __init__(self, session: Session, bag_path: str, custom_data: dict[str, str],
                 timeout_s: float):
        self._session = session
        self._timeout_s = timeout_s
        node = session.node
        self._start = node.create_client(StartRecording, f'{RECORDER}/start',
                                         qos_profile=SERVICE_QOS)
        self._stop = node.create_client(StopRecording, f'{RECORDER}/stop',
                                        qos_profile=SERVICE_QOS)
        # The recorder resolves a relative path against its own working directory: send the
        # one the user meant, relative to where they typed it. The request_id makes a resend
        # the same start, so the start is sent again while unanswered, as a query is.
        request = start_recording_request(os.path.abspath(bag_path) if bag_path else '',
                                          custom_data)
        response = session.call(self._start, request, timeout_s,
                                session.start_hint(RECORDER) or 'is a recorder running?',
                                query=True, node=RECORDER)
        if not response.success:
            raise CliError(f'the recorder refused to start a bag: {response.message}')
        self.bag_path = response.bag_path
        print(f'recording to {self.bag_path}', flush=True)

    def finish(self) -> None:
        """Finish the bag (not interrupted by a Ctrl-C: a half-written bag helps nobody);
        says on stderr when the recorder does not answer, and the bag then stays open."""
        future = self._stop.call_async(StopRecording.Request())
        answered = self._session.spin_until(future.done, STOP_WAIT_S, interruptible=False)
        if not answered:
            print(f'pma: the recorder did not finish {self.bag_path} within {STOP_WAIT_S:g} s; '
                  'it finishes the bag at its next start or when it stops (Ctrl-C)',
                  file=sys.stderr)
            return
        response = future.result()
        if not response.success:
            print(f'pma: the recorder could not finish {self.bag_path}: {response.message}',
                  file=sys.stderr)
            return
        lost = (f', {response.lost_message_count} lost on the way'
                if response.lost_message_count else '')
        print(f'recorded {response.message_count} messages to {response.bag_path}{lost}',
              flush=True)
