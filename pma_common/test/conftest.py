"""Fixtures for pma_common's tests that need rclpy."""

from __future__ import annotations

import pytest
import rclpy
from rclpy.context import Context


@pytest.fixture
def context():
    """rclpy initialised in a context of the test's own, shut down after it."""
    context = Context()
    rclpy.init(context=context)
    yield context
    context.try_shutdown()
