"""The executables of `ros2 run pma_driver ...`; each stops cleanly on SIGINT/SIGTERM/SIGHUP."""

from pma_common.stop import entry_point

driver_node = entry_point('pma_driver.driver_node:main')
