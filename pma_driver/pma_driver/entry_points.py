"""The executables of `ros2 run pma_driver ...`; each stops cleanly on SIGINT/SIGTERM/SIGHUP."""

from pma_common.stop import entry_point

driver_node = entry_point('pma_driver.driver_node:main')
fake_arduino = entry_point('pma_driver.fake_arduino:main')
simavr_arduino = entry_point('pma_driver.simavr_arduino:main')
recorder = entry_point('pma_bag.record:legacy_main')   # old name of `pma_bag record`
