"""Executables of `ros2 run pma_model ...` that stop cleanly on SIGINT/SIGTERM/SIGHUP.

`refit` is a plain command: Ctrl-C ends it at once (refit.main says so in one line).
"""

from pma_common.stop import entry_point

model_node = entry_point('pma_model.model_node:main')
