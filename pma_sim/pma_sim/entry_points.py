"""The executables of `ros2 run pma_sim ...`; each stops cleanly on SIGINT/SIGTERM/SIGHUP."""

from pma_common.stop import entry_point

fake_arduino = entry_point('pma_sim.fake_arduino:main')
simavr_arduino = entry_point('pma_sim.simavr_arduino:main')
