"""A PressureForLength server and a Sweep action server with trivial logic.

Used only to prove that the generated service and action types work across
processes; the real servers live in model_node and driver_node.
"""

import math
import time

import rclpy
from rclpy.action import ActionServer
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from pma_common import names
from pma_common.node import WorkerPoolExecutor
from pma_interfaces.action import Sweep
from pma_interfaces.srv import PressureForLength


class InterfaceServers(Node):
    def __init__(self):
        super().__init__('interface_servers')
        self.create_service(PressureForLength, names.PRESSURE_FOR_LENGTH, self.on_request)
        self._action = ActionServer(self, Sweep, names.SWEEP, self.on_goal)

    def on_request(self, request, response):
        # A straight line from 0.30 m at 0 Pa to 0.24 m at 500 kPa.
        if not math.isfinite(request.length_m) or not 0.24 <= request.length_m <= 0.30:
            response.success = False
            response.message = f'length {request.length_m} m outside 0.24..0.30 m'
            return response
        response.success = True
        response.gauge_pressure_pa = (0.30 - request.length_m) / 0.06 * 500_000.0
        response.branch = request.branch or PressureForLength.Request.BRANCH_INCREASING
        response.min_length_m, response.max_length_m = 0.24, 0.30
        return response

    def on_goal(self, handle):
        steps = max(1, round(handle.request.max_gauge_pressure_pa / handle.request.step_pa))
        for i in range(steps + 1):
            feedback = Sweep.Feedback()
            feedback.progress = i / steps
            feedback.gauge_setpoint_pa = i * handle.request.step_pa
            feedback.step_index, feedback.step_count = i, steps + 1
            handle.publish_feedback(feedback)
            time.sleep(0.05)
        handle.succeed()
        result = Sweep.Result()
        result.success, result.message, result.sample_count = True, 'done', steps + 1
        return result


def main() -> None:
    rclpy.init()
    node = InterfaceServers()
    executor = WorkerPoolExecutor(num_threads=4)
    executor.add_node(node)
    print('interface_servers: ready', flush=True)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
