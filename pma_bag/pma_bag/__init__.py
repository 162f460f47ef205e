"""rosbag2-compatible MCAP bags without rosbag2: write, read and recover.

The layout follows what Jazzy's `ros2 bag record -s mcap` writes (docs/bags.md), so
`ros2 bag info/play`, Foxglove, rosbags and the mcap tools all read our bags. No rclpy
here: nodes (recorder, replay) and offline tools share this code.
"""

from pma_bag.errors import BagError, BagWriteError, SchemaError
from pma_bag.reader import BagMessage, BagReader, TopicInfo
from pma_bag.recover import recover_bag
from pma_bag.writer import BagWriter, qos_profile_dict

__all__ = [
    'BagError',
    'BagMessage',
    'BagReader',
    'BagWriteError',
    'BagWriter',
    'SchemaError',
    'TopicInfo',
    'qos_profile_dict',
    'recover_bag',
]
