"""Length control of the pneumatic muscle: `controller` (no ROS) and `length_controller` (node)."""
