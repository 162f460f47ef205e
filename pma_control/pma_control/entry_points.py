"""Executables of `ros2 run pma_control ...`; each stops cleanly on SIGINT/SIGTERM/SIGHUP."""

from pma_common.stop import entry_point

length_controller = entry_point('pma_control.length_controller:main')
