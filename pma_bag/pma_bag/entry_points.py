"""Nodes of `ros2 run pma_bag ...` (the `ros2 bag` verbs), stopping cleanly on any stop signal.

`recover` and `info` are plain commands (pma_bag.recover:main, pma_bag.info:main).
"""

from pma_common.stop import entry_point

record = entry_point('pma_bag.record:main')
play = entry_point('pma_bag.play:main')
