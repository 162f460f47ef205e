"""The test's view of a length controller on a rig: its states, the controller's steps, the
setpoints every node publishes, and the MoveToLength client `ros2 action send_goal` would be.

Used by the controller's process tests (tests/test_length_controller.py, test_control_faults.py).
"""

from __future__ import annotations

import threading
import time

import numpy as np
from rclpy.action import ActionClient
from std_msgs.msg import Float64

from pma_common import names
from pma_interfaces.action import MoveToLength
from pma_interfaces.msg import ControlState, LengthSetpoint, PmaState
from support.ros import SpinningNode, wait_until


class ControlProbe:
    def __init__(self, name: str = 'control_test_probe'):
        self.spinning = SpinningNode(name)
        node = self.spinning.node
        self.lock = threading.Lock()
        self.states: list[tuple[float, PmaState]] = []
        self.control: list[ControlState] = []
        self.commands: list[tuple[float, float]] = []    # (monotonic, Pa) on pma/pressure_setpoint
        node.create_subscription(PmaState, names.STATE, self._on_state, 1000)
        node.create_subscription(ControlState, names.CONTROL_STATE, self._on_control, 1000)
        node.create_subscription(Float64, names.PRESSURE_SETPOINT, self._on_command, 1000)
        self.setpoints = node.create_publisher(LengthSetpoint, names.LENGTH_SETPOINT, 10)
        self.move = ActionClient(node, MoveToLength, names.MOVE_TO_LENGTH)

    def _on_state(self, msg: PmaState) -> None:
        with self.lock:
            self.states.append((time.monotonic(), msg))

    def _on_control(self, msg: ControlState) -> None:
        with self.lock:
            self.control.append(msg)

    def _on_command(self, msg: Float64) -> None:
        with self.lock:
            self.commands.append((time.monotonic(), msg.data))

    def latest(self) -> PmaState:
        with self.lock:
            return self.states[-1][1]

    def latest_control(self) -> ControlState:
        with self.lock:
            return self.control[-1]

    def states_since(self, since: float) -> list[PmaState]:
        with self.lock:
            return [s for t, s in self.states if t >= since]

    def lengths_since(self, since: float) -> np.ndarray:
        return np.array([s.length_m for s in self.states_since(since)])

    def commands_since(self, since: float) -> list[float]:
        with self.lock:
            return [pa for t, pa in self.commands if t >= since]

    def state_count(self) -> int:
        with self.lock:
            return len(self.states)

    def send_goal(self, length_m: float, timeout_s: float = 20.0, **fields):
        assert self.move.wait_for_server(20), 'no pma/move_to_length server'
        goal = MoveToLength.Goal(length_m=length_m, timeout_s=timeout_s, **fields)
        handle = self.spinning.send_goal(self.move, goal)
        assert handle.accepted
        return handle

    @staticmethod
    def _wait(future, timeout: float):
        wait_until(future.done, timeout, 'the action server')
        return future.result()

    def response(self, handle, timeout: float = 40.0):
        """The goal's (status, result) response."""
        return self._wait(self.spinning.in_executor(handle.get_result_async), timeout)

    def result(self, handle, timeout: float = 40.0):
        return self.response(handle, timeout).result

    def close(self):
        self.spinning.close()
