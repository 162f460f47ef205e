"""A stand-in for pma_bag's recorder node: serves `~/start` and `~/stop` over DDS, writes no bag.

Answers StartRecording / StopRecording as the recorder does, and appends every request it
got, with what it saw meanwhile, to `--calls` (one JSON object per line), so a test can check
what the driver asked: the bag path, the custom_data, and that the sweep's samples arrived
between start and stop (it counts the pma/state messages it receives while "recording").

    python recorder_stand_in.py --calls calls.jsonl [--refuse REASON] [--ros-args -r __ns:=/rig1]
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data

from pma_common import names
from pma_common.node import WorkerPoolExecutor, ros_context, spin_until_stopped
from pma_interfaces.msg import PmaState
from pma_interfaces.srv import StartRecording, StopRecording


class RecorderStandIn(Node):
    def __init__(self, calls: Path, refuse: str):
        super().__init__('recorder')
        self.calls = calls
        self.refuse = refuse
        self.lock = threading.Lock()
        self.bag = ''
        self.request_id = ''
        self.setpoints: list[float] = []
        self.auto_count = 0
        self.create_subscription(PmaState, names.STATE, self.on_state, qos_profile_sensor_data)
        self.create_service(StartRecording, '~/start', self.on_start)
        self.create_service(StopRecording, '~/stop', self.on_stop)

    def write(self, entry: dict) -> None:
        with self.calls.open('a', encoding='utf-8') as out:
            out.write(json.dumps(entry) + '\n')

    def on_state(self, msg: PmaState) -> None:
        with self.lock:
            if self.bag:
                self.setpoints.append(msg.gauge_setpoint_pa)

    def on_start(self, request, response):
        with self.lock:
            if request.request_id and request.request_id == self.request_id and self.bag:
                # A resend whose first answer was lost: the same start, as the recorder does.
                response.success, response.message = True, f'recording to {self.bag}'
                response.bag_path = self.bag
                response.topics = [self.resolve_topic_name(names.STATE)]
                return response
        self.write({'call': 'start', 'node': self.get_fully_qualified_name(),
                    'bag_path': request.bag_path, 'topics': list(request.topics),
                    'custom_data': {kv.key: kv.value for kv in request.custom_data}})
        if self.refuse:
            response.success, response.message = False, self.refuse
            return response
        if not request.bag_path:
            self.auto_count += 1
        bag = Path(request.bag_path or f'stand_in_bag_{self.auto_count}').absolute()
        with self.lock:
            self.bag, self.setpoints, self.request_id = str(bag), [], request.request_id
        response.success, response.message = True, f'recording to {bag}'
        response.bag_path = str(bag)
        response.topics = [self.resolve_topic_name(names.STATE)]
        return response

    def on_stop(self, _request, response):
        with self.lock:
            bag, setpoints, self.bag, self.setpoints = self.bag, self.setpoints, '', []
        self.write({'call': 'stop', 'bag_path': bag, 'setpoints_pa': setpoints})
        response.success = True
        response.message = f'finished {bag}' if bag else 'was not recording'
        response.bag_path = bag
        response.message_count = len(setpoints)
        response.lost_message_count = 0
        return response


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('--calls', type=Path, required=True)
    parser.add_argument('--refuse', default='', help='answer every start with this failure')
    args, ros_args = parser.parse_known_args(argv)
    with ros_context([sys.argv[0], *ros_args]) as stop:
        node = RecorderStandIn(args.calls, args.refuse)
        print(f'recorder_stand_in: ready as {node.get_fully_qualified_name()}', flush=True)
        try:
            spin_until_stopped(WorkerPoolExecutor(num_threads=2), node, stop)
        finally:
            node.destroy_node()
    return 0


if __name__ == '__main__':
    sys.exit(main())
