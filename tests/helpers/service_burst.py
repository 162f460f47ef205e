"""Test/bench helper: fire bursts of service requests, all in flight at once, and time them.

    service_burst.py --count 50 --go-dir DIR [--services pressure_for_length,bench_trigger]
    service_burst.py --count 300 --go-dir DIR --services /recorder/pause,/recorder/resume

A service is named as a client resolves it (relative, absolute, a node's private service as
`/recorder/pause`, an action's `pma/sweep/_action/get_result`); its type and request come
from REQUESTS, by the longest key the name ends with. Waits
for every service and for one answer from each (the burst's own request, resent while
unanswered, so a reply lost while discovery completes, ros2/rmw_fastrtps#842, is not counted
as a loss of the burst: a burst repeats that request `count` times anyway), prints `ready`,
then for round 0, 1, ... waits for the file DIR/go-<round> (several of these processes start
a round within a millisecond of each other), reads the service names from it (one, or several
separated by commas: their bursts interleaved, all in flight together), sends `count`
requests to each without waiting for any answer, spins until all are answered or --timeout
passes, and prints one JSON line per service: round, service, sent, answered, succeeded (of
the answers, how many said `success`; null for a response without that field), latency_ms
(send to answer, per answered request). DIR/stop ends it.

The clients use SERVICE_QOS (pma_common.service), as the servers do: a burst deeper than the
default queue of 10 is lost in the client's own request writer and response reader unless
the client queues it too.
"""

import argparse
import json
import sys
import time
import uuid
from pathlib import Path

import rclpy
from action_msgs.msg import GoalInfo
from action_msgs.srv import CancelGoal
from std_srvs.srv import Trigger
from unique_identifier_msgs.msg import UUID

from pma_common import names
from pma_common.service import SERVICE_QOS, ask
from pma_interfaces.action import MoveToLength, Sweep
from pma_interfaces.srv import IsPaused, PressureForLength


def unknown_goal_id() -> UUID:
    return UUID(uuid=list(uuid.uuid4().bytes))


# By the end of the service's name: (type, request maker).
REQUESTS = {
    names.PRESSURE_FOR_LENGTH: (PressureForLength,
                            lambda: PressureForLength.Request(length_m=0.27, branch=1)),
    'bench_trigger': (Trigger, Trigger.Request),
    # the recorder's and the player's (pma_bag), the driver's
    'pause': (Trigger, Trigger.Request),
    'resume': (Trigger, Trigger.Request),
    'toggle_paused': (Trigger, Trigger.Request),
    'split_bagfile': (Trigger, Trigger.Request),
    'play_next': (Trigger, Trigger.Request),
    'tare': (Trigger, Trigger.Request),
    'is_paused': (IsPaused, IsPaused.Request),
    # an action server's services, asked about goals it does not know: answered at once
    # (a result request for a known goal waits for the goal's end; a cancel of the zero ID
    # would cancel every goal)
    'sweep/_action/get_result': (
        Sweep.Impl.GetResultService,
        lambda: Sweep.Impl.GetResultService.Request(goal_id=unknown_goal_id())),
    'move_to_length/_action/get_result': (
        MoveToLength.Impl.GetResultService,
        lambda: MoveToLength.Impl.GetResultService.Request(goal_id=unknown_goal_id())),
    '_action/cancel_goal': (
        CancelGoal, lambda: CancelGoal.Request(goal_info=GoalInfo(goal_id=unknown_goal_id()))),
}


def request_for(name: str):
    """(type, request maker) of the service `name`: REQUESTS' longest key it ends with."""
    name = name.rstrip('/')
    keys = [key for key in REQUESTS if name == key or name.endswith('/' + key)]
    if not keys:
        raise SystemExit(f'service_burst: no request for {name} (REQUESTS knows '
                         f'{", ".join(REQUESTS)})')
    return REQUESTS[max(keys, key=len)]


def burst(node, bursts, count: int, timeout: float) -> list[dict]:
    """Send `count` requests to each (client, make_request) of `bursts`, interleaved, without
    waiting; spin until all are answered or `timeout`. One result per burst."""
    sent_ns = [[] for _ in bursts]
    answered_ns = [{} for _ in bursts]
    futures = [[] for _ in bursts]
    for index in range(count):
        for which, (client, make_request) in enumerate(bursts):
            sent_ns[which].append(time.monotonic_ns())
            future = client.call_async(make_request())
            future.add_done_callback(
                lambda _f, index=index, answered=answered_ns[which]:
                    answered.setdefault(index, time.monotonic_ns()))
            futures[which].append(future)
    deadline = time.monotonic() + timeout
    while (sum(map(len, answered_ns)) < count * len(bursts)
           and time.monotonic() < deadline):
        rclpy.spin_once(node, timeout_sec=0.05)
    results = []
    for which, (client, _) in enumerate(bursts):
        for future in futures[which]:
            if not future.done():
                client.remove_pending_request(future)
        answers = [f.result() for f in futures[which] if f.done()]
        succeeded = (sum(1 for a in answers if a.success)
                     if answers and hasattr(answers[0], 'success') else None)
        answered = answered_ns[which]
        latency = [(answered[i] - sent_ns[which][i]) / 1e6 for i in sorted(answered)]
        results.append({'sent': count, 'answered': len(answered), 'succeeded': succeeded,
                        'latency_ms': latency})
    return results


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
        srv_type, make_request = request_for(name)
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
        names = [name for name in go.read_text().strip().split(',') if name]
        if not names:                    # seen between its creation and its write
            continue
        results = burst(node, [clients[name] for name in names], args.count, args.timeout)
        for name, result in zip(names, results, strict=True):
            print(json.dumps({'round': round_, 'service': name, **result}), flush=True)
        round_ += 1
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
