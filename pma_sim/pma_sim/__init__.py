"""The simulated rig: muscle, pneumatics and the device side of the serial protocol.

Plain Python (no ROS), stepped by an explicit clock so tests can drive it exactly;
`pma_sim.fake_arduino` puts it behind a pseudo-terminal.
"""
