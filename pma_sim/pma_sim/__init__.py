"""The simulated rig: muscle families, pneumatics and the device side of the serial protocol.

Plain Python (no ROS), stepped by an explicit clock so tests can drive it exactly;
`pma_sim.fake_arduino` puts it behind a pseudo-terminal, `pma_sim.simavr_arduino` runs the
firmware's own image in its place. `pma_sim.registry` names every muscle family,
`pma_sim.evaluation` scores the model on them.
"""
