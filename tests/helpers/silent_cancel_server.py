"""A goal server's cancel service that takes every request and never answers.

What `pma vent` meets when a length controller's or driver's answer is lost, or the node
hangs: the vent must not wait on it for ever, nor skip the 0 Pa setpoint.
Prints `silent_cancel_server: ready` once serving.

With `--goals`, a whole action server (MoveToLength, or Sweep for an action named `...sweep`)
whose cancels are taken and never answered: it accepts every goal, sends feedback every
0.1 s and never ends it (prints `goal accepted`). What `pma move` meets after a Ctrl-C when
the server hangs in the goal: the wait for the cancel must end.
"""

import argparse

import rclpy
from action_msgs.srv import CancelGoal
from rclpy.action import ActionServer, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

from pma_interfaces.action import MoveToLength, Sweep


def serve_goals(node: Node, action: str, heard: list) -> None:
    action_type = Sweep if action.endswith('sweep') else MoveToLength
    group = ReentrantCallbackGroup()

    async def pause(seconds: float) -> None:
        later = Future()
        timer = node.create_timer(seconds, lambda: later.done() or later.set_result(None),
                                  callback_group=group)
        await later
        timer.cancel()
        node.destroy_timer(timer)

    async def run_for_ever(goal_handle):
        print('goal accepted', flush=True)
        while True:
            goal_handle.publish_feedback(action_type.Feedback())
            await pause(0.1)

    async def never_answer(_goal_handle):
        heard.append(1)
        print(f'cancel request {len(heard)} taken, not answered', flush=True)
        await Future()

    # Reentrant: a cancel left waiting must not keep the next request (a resend, a result
    # query) from being taken.
    ActionServer(node, action_type, action, execute_callback=run_for_ever,
                 goal_callback=lambda _goal: GoalResponse.ACCEPT, cancel_callback=never_answer,
                 callback_group=group)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument('--action', default='pma/move_to_length')
    parser.add_argument('--goals', action='store_true',
                        help='a whole action server whose goals never end')
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=ros_args)
    node = Node('silent_cancel_server')
    heard = []

    async def never_answer(_request, _response):
        heard.append(1)
        node.get_logger().info(f'cancel request {len(heard)} taken, not answered')
        await Future()

    if args.goals:
        serve_goals(node, args.action, heard)
    else:
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
