"""Helpers shared by the tests: real processes, the workspace's executables, DDS waits."""
