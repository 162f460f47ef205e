"""Test/bench helper: fire bursts of service requests, all in flight at once, and time them.

    service_burst.py --count 50 --go-dir DIR [--services pressure_for_length,bench_trigger]

Waits for every service and for one answer from each (a query resent while unanswered, so a
reply lost while discovery completes, ros2/rmw_fastrtps#842, is not counted as a loss of the
burst), prints `ready`, then for round 0, 1, ... waits for the file
DIR/go-<round> (several of these processes start a round within a millisecond of each other),
reads the service name from it, sends `count` requests without waiting for any answer, spins
until all are answered or --timeout passes, and prints one JSON line: service, sent, answered,
latency_ms (send to answer, per answered request). DIR/stop ends it.

The client uses model_node's SERVICE_QOS: a burst deeper than the default queue of 10 is lost
in the client's own request writer and response reader unless the client queues it too.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import rclpy
from std_srvs.srv import Trigger

from pma_common.service import ask
from pma_interfaces.srv import PressureForLength
from pma_model.model_node import SERVICE_QOS

REQUESTS = {
    'pressure_for_length': (PressureForLength,
                            lambda: PressureForLength.Request(length_m=0.27, branch=1)),
    'bench_trigger': (Trigger, Trigger.Request),
}


def burst(node, client, make_request, count: int, timeout: float) -> dict:
    sent_ns, answered_ns = [], {}
    futures = []
    for index in range(count):
        sent_ns.append(time.monotonic_ns())
        future = client.call_async(make_request())
        future.add_done_callback(
            lambda _f, index=index: answered_ns.setdefault(index, time.monotonic_ns()))
        futures.append(future)
    deadline = time.monotonic() + timeout
    while len(answered_ns) < count and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    for future in futures:
        if not future.done():
            client.remove_pending_request(future)
    latency = [(answered_ns[i] - sent_ns[i]) / 1e6 for i in sorted(answered_ns)]
    return {'sent': count, 'answered': len(answered_ns), 'latency_ms': latency}


def spinning(node):
    """A `wait(done, seconds)` for pma_common.service.ask that spins this node."""
    def wait(done, seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        while not done():
            if time.monotonic() >= deadline:
                return False
            rclpy.spin_once(node, timeout_sec=0.05)
        return True
    return wait


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--count', type=int, default=50)
    parser.add_argument('--go-dir', type=Path, required=True)
    parser.add_argument('--services', default='pressure_for_length')
    parser.add_argument('--timeout', type=float, default=30.0)
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node('service_burst')
    clients = {}
    for name in args.services.split(','):
        srv_type, make_request = REQUESTS[name]
        clients[name] = (node.create_client(srv_type, name, qos_profile=SERVICE_QOS),
                         make_request)
        if not clients[name][0].wait_for_service(timeout_sec=30) or ask(
                clients[name][0], make_request(), 30, spinning(node)) is None:
            print(f'no {name} service', flush=True)
            return 1
    print('ready', flush=True)
    round_ = 0
    while not (args.go_dir / 'stop').exists():
        go = args.go_dir / f'go-{round_}'
        if not go.exists():
            time.sleep(0.0005)
            continue
        name = go.read_text().strip()
        if not name:                     # seen between its creation and its write
            continue
        client, make_request = clients[name]
        result = burst(node, client, make_request, args.count, args.timeout)
        print(json.dumps({'round': round_, 'service': name, **result}), flush=True)
        round_ += 1
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
