"""A goal server's cancel service that takes every request and never answers.

What `pma vent` meets when a length controller's or driver's answer is lost, or the node
hangs: the vent must not wait on it for ever, nor skip the 0 Pa setpoint.
Prints `silent_cancel_server: ready` once serving.
"""

import argparse

import rclpy
from action_msgs.srv import CancelGoal
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument('--action', default='pma/move_to_length')
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=ros_args)
    node = Node('silent_cancel_server')
    heard = []

    async def never_answer(_request, _response):
        heard.append(1)
        node.get_logger().info(f'cancel request {len(heard)} taken, not answered')
        await Future()

    # Reentrant: a request left waiting must not keep the next (a resend) from being taken.
    node.create_service(CancelGoal, f'{args.action}/_action/cancel_goal', never_answer,
                        callback_group=ReentrantCallbackGroup())
    print('silent_cancel_server: ready', flush=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
