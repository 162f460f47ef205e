"""Test helper: subscribe one topic and dump (receive time, field value) pairs as JSON.

    subscriber.py --topic /pma/state --type pma_interfaces/msg/PmaState --field seq
                  --count 400 --out got.json [--timeout 30]

Exits when `count` messages arrived or after `timeout` s (or SIGINT), writing what it got.
"""

import argparse
import importlib
import json
import os
import sys
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy

RESUME_GRACE_S = 1.0


def field_value(msg, path):
    for part in path.split('.'):
        msg = msg[int(part)] if part.isdigit() else getattr(msg, part)
    return msg


def resume(node, subscription, service: str, deadline: float, gate: str | None) -> None:
    """Once our reader has matched the player's writer (and `gate`, a file the test creates
    when its other listeners have matched, exists), call its Trigger service.

    The reader matching the writer does not prove the writer has matched the reader yet
    (each side learns of the other from its own SEDP message, and a lost one is resent only
    at the next discovery heartbeat, seen to take over 1 s under load), and a volatile
    writer drops what it publishes before then: hence the grace period after the match.
    """
    from std_srvs.srv import Trigger

    while (subscription.get_publisher_count() < 1 or (gate and not os.path.exists(gate))) \
            and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    client = node.create_client(Trigger, service)
    if not client.wait_for_service(timeout_sec=max(0.0, deadline - time.monotonic())):
        print(f'subscriber: no service {service}', flush=True)
        return
    time.sleep(RESUME_GRACE_S)
    future = client.call_async(Trigger.Request())
    rclpy.spin_until_future_complete(node, future, timeout_sec=10)
    print(f'subscriber: called {service}: {future.result()}', flush=True)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--topic', required=True)
    parser.add_argument('--type', required=True)
    parser.add_argument('--field', action='append', default=[],
                        help='dotted field path to keep; repeat for a list per message')
    parser.add_argument('--count', type=int, default=0)
    parser.add_argument('--timeout', type=float, default=30.0)
    parser.add_argument('--best-effort', action='store_true')
    parser.add_argument('--out', required=True)
    parser.add_argument('--resume-service', metavar='SRV',
                        help='once a publisher matched, call this std_srvs/Trigger service '
                             '(e.g. /player/resume of a player started with --start-paused)')
    parser.add_argument('--resume-gate', metavar='PATH',
                        help='with --resume-service: also wait until this file exists')
    args = parser.parse_args()
    package, _, name = args.type.split('/')
    msg_type = getattr(importlib.import_module(f'{package}.msg'), name)
    rclpy.init()
    node = rclpy.create_node('test_subscriber')
    received = []

    def plain(value):
        """A JSON-able value: Time as ns, a ROS `byte` (bytes of one) as int."""
        if hasattr(value, 'sec') and hasattr(value, 'nanosec'):
            return value.sec * 1_000_000_000 + value.nanosec
        if isinstance(value, bytes) and len(value) == 1:
            return value[0]
        return value

    def on_message(msg):
        values = [plain(field_value(msg, path)) for path in args.field]
        value = values[0] if len(values) == 1 else (values or None)
        received.append([time.time_ns(), value])

    reliability = (ReliabilityPolicy.BEST_EFFORT if args.best_effort
                   else ReliabilityPolicy.RELIABLE)
    subscription = node.create_subscription(msg_type, args.topic, on_message,
                                            QoSProfile(depth=1000, reliability=reliability))
    print(f'subscriber: listening on {args.topic}', flush=True)
    deadline = time.monotonic() + args.timeout
    if args.resume_service:
        resume(node, subscription, args.resume_service, deadline, args.resume_gate)
    matched = False
    try:
        while time.monotonic() < deadline and not (args.count and len(received) >= args.count):
            rclpy.spin_once(node, timeout_sec=0.05)
            if not matched and subscription.get_publisher_count() >= 1:
                matched = True
                print('subscriber: matched', flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # SIGINT: stop here and write what arrived
    with open(args.out, 'w', encoding='utf-8') as out:
        json.dump(received, out)
    print(f'subscriber: got {len(received)}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
