"""Publish PmaState at a fixed rate, holding ~250 kPa (a stand-in rig for interface tests)."""

import argparse
import math

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from pma_interfaces.msg import PmaState


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument('--rate', type=float, default=50.0)
    parser.add_argument('--topic', default='pma/state')
    parser.add_argument('--nan-every', type=int, default=0,
                        help='every Nth sample carries a NaN pressure (a broken reading)')
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=ros_args)
    node = Node('rig_stand_in')
    pub = node.create_publisher(PmaState, args.topic, 10)
    seq = 0

    def tick():
        nonlocal seq
        msg = PmaState()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = 'pma_link'
        msg.seq = seq
        msg.device_time_s = seq / args.rate
        msg.gauge_pressure_pa = 250_000.0 + 1000.0 * math.sin(seq / 10.0)
        if args.nan_every and seq % args.nan_every == args.nan_every - 1:
            msg.gauge_pressure_pa = math.nan
        msg.length_m = 0.26
        msg.gauge_setpoint_pa = 250_000.0
        msg.valve_state = PmaState.VALVE_HOLD
        msg.pressure_adc = 511
        msg.echo_us = 816
        pub.publish(msg)
        seq += 1

    node.create_timer(1.0 / args.rate, tick)
    print('rig_stand_in: ready', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
