"""Test helper: write numbered PmaState messages into a BagWriter at a fixed rate until killed.

    bag_writer_process.py BAG_DIR [--rate 500]

Prints `writer: wrote N` after each flush, so a test knows what had reached the disk
before it sends SIGKILL.
"""

import argparse
import sys
import time

from rclpy.serialization import serialize_message

from pma_bag import BagWriter
from pma_interfaces.msg import PmaState


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('bag')
    parser.add_argument('--rate', type=float, default=500.0)
    args = parser.parse_args()
    writer = BagWriter(args.bag, flush_interval_s=1.0)
    writer.add_topic('/pma/state', 'pma_interfaces/msg/PmaState')
    period = 1.0 / args.rate
    start = time.monotonic()
    print('writer: started', flush=True)
    seq = 0
    reported = 0
    while True:
        delay = start + seq * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        writer.write('/pma/state', serialize_message(PmaState(seq=seq)), time.time_ns())
        seq += 1
        if writer.messages_flushed != reported:
            reported = writer.messages_flushed
            print(f'writer: wrote {reported}', flush=True)


if __name__ == '__main__':
    sys.exit(main())
