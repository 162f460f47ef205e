"""Exceptions of the bag package, one module so reader, writer and CLIs share them."""


class BagError(Exception):
    """A bag cannot be read: missing, empty, truncated beyond use or not a rosbag2 MCAP bag."""


class BagWriteError(BagError):
    """A bag cannot be written: unwritable path, disk full, or the writer already failed."""


class SchemaError(BagError):
    """The definition of a message type cannot be found in the sourced environment."""
