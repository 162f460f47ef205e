"""Rewrite a bag cut short by a crash into a clean, indexed bag with metadata.yaml.

The Python counterpart of `mcap recover` (Go CLI, not on PyPI) followed by `ros2 bag
reindex`: every complete message is copied with its schema, QoS and timestamps. The damaged
input is never modified, so nothing is lost if recovery itself fails.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

from pma_bag.errors import BagError
from pma_bag.reader import BagReader, TruncatedBagWarning
from pma_bag.writer import BagWriter
from pma_common.console import closed_pipe_ends_quietly


@dataclass(frozen=True)
class RecoveryReport:
    """What recover_bag wrote: where, how many messages, and whether the input was damaged."""

    output: Path
    message_count: int
    topic_counts: dict[str, int]
    input_was_truncated: bool

    def summary(self) -> str:
        state = 'truncated' if self.input_was_truncated else 'intact'
        return (f'recovered {self.message_count} messages on {len(self.topic_counts)} topics '
                f'({state} input) into {self.output}')


def default_output(bag: Path) -> Path:
    """`<bag>_recovered` next to the input directory (or next to a bare .mcap's stem)."""
    bag = Path(bag)
    stem = bag.stem if bag.is_file() else bag.name
    return bag.parent / f'{stem}_recovered'


def recover_bag(bag: str | os.PathLike, output: str | os.PathLike | None = None) -> RecoveryReport:
    """Copy every complete message of `bag` into a new bag directory `output`."""
    source = Path(bag)
    target = Path(output) if output is not None else default_output(source)
    if target.resolve() == source.resolve():
        raise BagError(f'recover output {target} must differ from the input bag')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', TruncatedBagWarning)
        reader = BagReader(source)
    with reader:
        # The input's chunk compression and experiment metadata carry over; a split input
        # becomes one file (its parts are in log-time order already).
        compression = min(reader.compressions - {''}, default='')
        with BagWriter(target, compression=compression,
                       custom_data=reader.custom_data) as writer:
            for topic in reader.topics.values():
                writer.add_topic(topic.name, topic.type_name, topic.offered_qos_profiles,
                                 schema=topic.schema)
            for message in reader.messages():
                writer.write(message.topic, message.data, message.log_time_ns,
                             message.publish_time_ns)
        return RecoveryReport(target, writer.message_count, writer.topics, reader.truncated)


@closed_pipe_ends_quietly
def main(argv: list[str] | None = None) -> int:
    """`ros2 run pma_bag recover BAG [-o OUT]`: no ROS needed, so none is started."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(
        prog='recover', description='Rewrite a bag cut short by a crash (SIGKILL, power cut) '
        'into a clean indexed bag with metadata.yaml; the input is left as it is.')
    parser.add_argument('bag', type=Path, help='bag directory or .mcap file')
    parser.add_argument('-o', '--output', type=Path,
                        help='where to write (default: <bag>_recovered next to it)')
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        report = recover_bag(args.bag, args.output)
    except BagError as exc:
        print(f'recover: cannot recover {args.bag}: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'recover: interrupted; the output is incomplete, {args.bag} is unchanged',
              file=sys.stderr)
        return 130
    print(f'recover: {report.summary()}')
    return 0
