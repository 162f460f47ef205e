"""Executables of `ros2 run pma_bringup ...` that are nodes; each stops cleanly on SIGINT,
SIGTERM and SIGHUP (`demo` is the operator script: pma_bringup.demo:main)."""

from pma_common.stop import entry_point

foxglove_live = entry_point('pma_bringup.foxglove_live:main')
