"""Test helper: publish numbered PmaState messages at a fixed rate, then exit.

    bag_state_publisher.py --topic /pma/state --rate 200 --count 400 [--wait-subscribers 1]
                           [--best-effort]

`seq` runs 0..count-1 so a recording can be checked for gaps.
"""

import argparse
import sys
import time

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from pma_interfaces.msg import ModelParams, PmaState


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--topic', default='/pma/state')
    parser.add_argument('--rate', type=float, default=200.0)
    parser.add_argument('--count', type=int, default=400)
    parser.add_argument('--wait-subscribers', type=int, default=0)
    parser.add_argument('--transient-local', action='store_true')
    parser.add_argument('--best-effort', action='store_true',
                        help="as a driver with qos_reliability best_effort publishes")
    parser.add_argument('--latched-params', metavar='TOPIC',
                        help='also publish one latched ModelParams on TOPIC before the states')
    parser.add_argument('--linger', type=float, default=1.0, help='seconds to stay up at the end')
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node('bag_state_publisher')
    qos = QoSProfile(depth=1000, reliability=(ReliabilityPolicy.BEST_EFFORT if args.best_effort
                                              else ReliabilityPolicy.RELIABLE),
                     durability=(DurabilityPolicy.TRANSIENT_LOCAL if args.transient_local
                                 else DurabilityPolicy.VOLATILE))
    publisher = node.create_publisher(PmaState, args.topic, qos)
    if args.latched_params:
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        params = node.create_publisher(ModelParams, args.latched_params, latched)
        params.publish(ModelParams(form='sigmoid', memory='switch', deadband_pa=500.0,
                                   max_gauge_pressure_pa=5e5))
    print(f'publisher: ready on {args.topic}', flush=True)
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < args.wait_subscribers:
        if time.monotonic() > deadline:
            print('publisher: no subscriber', flush=True)
            return 1
        time.sleep(0.02)
    period = 1.0 / args.rate
    start = time.monotonic()
    for seq in range(args.count):
        target = start + seq * period
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        msg = PmaState(seq=seq, device_time_s=seq * period, gauge_pressure_pa=1000.0 * seq,
                       length_m=0.3 - 1e-6 * seq, status=seq % 16)
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = 'muscle'
        publisher.publish(msg)
    publisher.wait_for_all_acked(rclpy.duration.Duration(seconds=5))
    print(f'publisher: done {args.count} in {time.monotonic() - start:.3f} s', flush=True)
    time.sleep(args.linger)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
