"""Test helper: a Foxglove viewer that offers one WebSocket subprotocol, counts what arrives.

    foxglove_viewer.py URL --subprotocol foxglove.websocket.v1 --topic /pma/state
                       --topic /pma/prediction --count 50 [--timeout 30]

Follows the topics, waits until each has `count` messages, prints one JSON line
({"subprotocol": ..., "counts": {topic: n}}) and exits 0; exits 1 on a timeout, saying what
came. For a viewer in another network namespace than the test (tests/test_lab_network.py).
"""

import argparse
import json
import sys

from pma_bringup.foxglove_client import FoxgloveClient


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument('url')
    parser.add_argument('--subprotocol', required=True)
    parser.add_argument('--topic', action='append', required=True)
    parser.add_argument('--count', type=int, default=50)
    parser.add_argument('--timeout', type=float, default=30.0)
    args = parser.parse_args()
    client = FoxgloveClient(args.url, subprotocols=[args.subprotocol])
    try:
        client.follow(args.topic)
        try:
            client.wait(lambda c: all(len(c.received(t)) >= args.count for t in args.topic),
                        args.timeout, f'{args.count} messages on each of {args.topic}')
            code = 0
        except TimeoutError as error:
            print(f'foxglove_viewer: {error}', file=sys.stderr)
            code = 1
        print(json.dumps({'subprotocol': client.subprotocol,
                          'counts': {t: len(client.received(t)) for t in args.topic}}),
              flush=True)
        return code
    finally:
        client.close()


if __name__ == '__main__':
    sys.exit(main())
