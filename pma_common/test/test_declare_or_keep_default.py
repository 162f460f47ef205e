"""declare_or_keep_default on a real rclpy node: the overrides rclpy refuses at declaration
(wrong type, out of range) leave the default and come back as one readable line."""

from __future__ import annotations

import pytest
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from pma_common.parameters import declare_or_keep_default, refusal_reason


@pytest.fixture
def node_with(context):
    """A node started with the given overrides, as `--ros-args -p name:=value` gives them."""
    nodes = []

    def make(**overrides) -> Node:
        nodes.append(Node('parameters_under_test', context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in overrides.items()]))
        return nodes[-1]

    yield make
    for node in nodes:
        node.destroy_node()


def _gain() -> ParameterDescriptor:
    return ParameterDescriptor(floating_point_range=[
        FloatingPointRange(from_value=0.0, to_value=10.0, step=0.0)])


def test_a_good_override_is_taken(node_with):
    node = node_with(kp=2.5)
    assert declare_or_keep_default(node, 'kp', 0.3, _gain()) is None
    assert node.get_parameter('kp').value == 2.5
    assert declare_or_keep_default(node, 'ki', 3.0, _gain()) is None   # no override
    assert node.get_parameter('ki').value == 3.0


@pytest.mark.parametrize('override, default, reason', [
    (400000, 500_000.0, 'x is a float parameter: write 400000.0, not 400000'),
    ('abc', 8765, "x must be of type INTEGER, got 'abc' (STRING)"),
])
def test_a_wrong_type_keeps_the_default_and_says_what_to_write(node_with, override, default,
                                                               reason):
    node = node_with(x=override)
    assert declare_or_keep_default(node, 'x', default, ParameterDescriptor()) == reason
    assert node.get_parameter('x').value == default


def test_an_out_of_range_override_keeps_the_default_with_rclpys_reason(node_with):
    node = node_with(kp=-1.0)
    reason = declare_or_keep_default(node, 'kp', 0.3, _gain())
    assert reason.startswith('Parameter kp out of range') and 'value: -1.0' in reason
    assert not reason.endswith(': kp')          # the name once, not echoed at the end
    assert node.get_parameter('kp').value == 0.3


def test_a_node_that_will_not_guess_gets_the_same_line(node_with):
    node = node_with(kp=20.0)
    with pytest.raises(ParameterException) as raised:
        node.declare_parameter('kp', 0.3, _gain())
    assert refusal_reason(raised.value) == 'Parameter kp out of range Min: 0.0, Max: 10.0, ' \
                                           'value: 20.0'
