"""Shared by every PMA testbed package; `stop` and `sequence` are free of ROS, `node` is not."""
