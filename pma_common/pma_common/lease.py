"""Holding a commander lease on the driver (pma/commander_lease), for a remote commander.

A node that keeps the muscle pressurised by commanding it (the length controller while it
holds a target, `pma sweep` while its goal runs) holds a lease while it does and releases it
when it stops. driver_node brings the muscle to its safe state when a held lease is not
renewed for its commander_timeout_s (0.8 s by default): the commander's host or the network
between them is gone (docs/lab-network.md). The renewals ride on the holder's own executor,
so a holder whose node stops spinning is taken for lost too, which is what it is.
"""

from __future__ import annotations

import os
import socket
import time
import uuid

from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from pma_common import names
from pma_interfaces.msg import CommanderLease

# Eight renewals a default commander_timeout_s: a loss is 0.8 s of silence, not one late
# message on a busy machine or a lossy Wi-Fi link.
RENEW_PERIOD_S = 0.1
# The shortest commander_timeout_s a driver takes. A holder whose renewals stopped this long
# (its process paused, its machine starved) may have been taken for lost and vented, so it
# must not command again without a new goal: what it would send predates the vent.
MIN_COMMANDER_TIMEOUT_S = 0.5
# A holder that stops cleanly waits at most this long for the driver to acknowledge the
# release (an unheard release would vent the muscle).
RELEASE_WAIT_S = 2.0
LEASE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def commander_name(node: Node, what: str = '') -> str:
    """Who holds the lease, as logs and /diagnostics say it: `what` (or the node's name),
    its host and process."""
    who = what or node.get_fully_qualified_name()
    return f'{who} (pid {os.getpid()} on {socket.gethostname()})'


class LeaseHolder:
    """One lease at a time: `hold` starts one (or keeps the running one), `release` ends it."""

    def __init__(self, node: Node, commander: str, period_s: float = RENEW_PERIOD_S):
        self._node = node
        self.commander = commander
        self.lease_id = ''
        self._renewed_at = time.monotonic()
        self._publisher = node.create_publisher(CommanderLease, names.COMMANDER_LEASE,
                                                LEASE_QOS)
        self._timer = node.create_timer(period_s, self._renew)

    @property
    def holding(self) -> bool:
        return bool(self.lease_id)

    def hold(self) -> None:
        if not self.lease_id:
            self.lease_id = uuid.uuid4().hex
            self._send(True)

    def release(self) -> None:
        if self.lease_id:
            self._send(False)
            self.lease_id = ''

    def _renew(self) -> None:
        if self.lease_id:
            self._send(True)

    def silent_s(self) -> float:
        """How long since the lease was last renewed (0 while none is held)."""
        return time.monotonic() - self._renewed_at if self.lease_id else 0.0

    def _send(self, holding: bool) -> None:
        self._renewed_at = time.monotonic()
        msg = CommanderLease(commander=self.commander, lease_id=self.lease_id, holding=holding)
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(msg)

    def release_before_exit(self, timeout_s: float = RELEASE_WAIT_S) -> None:
        """Release, if held, and wait up to `timeout_s` for the driver to have the release:
        a clean stop's last word, which must not be lost with the process."""
        if self.lease_id:
            self.release()
            self.wait_for_driver(timeout_s)

    def wait_for_driver(self, timeout_s: float) -> bool:
        """Whether every matched reader (the driver) acknowledged what was sent, within
        timeout_s: before a clean exit, so that a release is not lost with the process."""
        return self._publisher.wait_for_all_acked(Duration(seconds=timeout_s))
