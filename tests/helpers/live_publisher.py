"""Publish PmaState (pma/state) and PmaPrediction (pma/prediction) pairs whose values follow
from their sequence number, so a receiver can check every value and the order.

    live_publisher.py --first-seq 0 --count 200 [--rate 100] [--best-effort]
                      [--wait-subscribers 1] [--duration S] [--go-file PATH]

Waits until each publisher counts --wait-subscribers readers (and a grace period: a reader that
matched our writer may not yet be matched by it), publishes, prints `live_publisher: published
N` and exits (with --go-file, it also waits for that file to exist before publishing: the
test's signal that its viewer is subscribed). Header stamps are the publish time
(time.time_ns), which the bench uses for latency. Used by tests/test_foxglove_live.py and
bench/bench_foxglove.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from pma_common import names
from pma_interfaces.msg import PmaPrediction, PmaState

MATCH_GRACE_S = 0.5


def state_fields(seq: int) -> dict:
    """What PmaState `seq` carries (besides its stamp)."""
    return {'seq': seq, 'device_time_s': seq * 0.01, 'gauge_pressure_pa': 1000.0 * seq + 0.5,
            'length_m': 0.3 - 1e-5 * seq, 'gauge_setpoint_pa': 1000.0 * seq,
            'valve_state': seq % 3, 'status': seq % 16, 'pressure_adc': seq % 1024,
            'echo_us': 800 + seq}


def prediction_fields(seq: int) -> dict:
    """What the PmaPrediction for PmaState `seq` carries (header.frame_id is f'seq{seq}')."""
    return {'gauge_pressure_pa': 1000.0 * seq + 0.5, 'measured_length_m': 0.3 - 1e-5 * seq,
            'predicted_length_m': 0.3 - 1.1e-5 * seq, 'residual_m': 1e-6 * seq,
            'branch': 1 + seq % 2, 'adaptation_offset_m': 0.0, 'adaptation_gain': 1.0}


def make_pair(seq: int, stamp_ns: int) -> tuple[PmaState, PmaPrediction]:
    state = PmaState(**state_fields(seq))
    prediction = PmaPrediction(**prediction_fields(seq))
    for msg in (state, prediction):
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    state.header.frame_id = 'pma_link'
    prediction.header.frame_id = f'seq{seq}'
    return state, prediction


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--first-seq', type=int, default=0)
    parser.add_argument('--count', type=int, default=0, help='0: until --duration or SIGINT')
    parser.add_argument('--duration', type=float, default=0.0)
    parser.add_argument('--rate', type=float, default=100.0)
    parser.add_argument('--best-effort', action='store_true')
    parser.add_argument('--wait-subscribers', type=int, default=1)
    parser.add_argument('--wait-timeout', type=float, default=30.0)
    parser.add_argument('--go-file', type=Path)
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=[sys.argv[0], *ros_args])
    node = rclpy.create_node('live_publisher')
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                     reliability=(ReliabilityPolicy.BEST_EFFORT if args.best_effort
                                  else ReliabilityPolicy.RELIABLE))
    publishers = [node.create_publisher(PmaState, names.STATE, qos),
                  node.create_publisher(PmaPrediction, names.PREDICTION, qos)]
    sent = 0
    try:
        deadline = time.monotonic() + args.wait_timeout
        while any(p.get_subscription_count() < args.wait_subscribers for p in publishers):
            if time.monotonic() > deadline:
                print('live_publisher: no subscribers', flush=True)
                return 1
            time.sleep(0.02)
        time.sleep(MATCH_GRACE_S)
        print('live_publisher: matched', flush=True)
        while args.go_file is not None and not args.go_file.exists():
            if time.monotonic() > deadline:
                print(f'live_publisher: no {args.go_file}', flush=True)
                return 1
            time.sleep(0.02)
        print('live_publisher: publishing', flush=True)
        period = 1.0 / args.rate
        start = time.monotonic()
        end = start + args.duration if args.duration else float('inf')
        while (not args.count or sent < args.count) and time.monotonic() < end:
            state, prediction = make_pair(args.first_seq + sent, time.time_ns())
            publishers[0].publish(state)
            publishers[1].publish(prediction)
            sent += 1
            delay = start + sent * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        time.sleep(0.5)     # reliable: let the readers acknowledge the tail before we go
    except KeyboardInterrupt:
        pass
    finally:
        print(f'live_publisher: published {sent}', flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
