"""Declaring a parameter so that a bad start-up override is refused, not fatal.

rclpy checks an override given at start (`--ros-args -p`, a params file) against the
declared type and range and raises, so a node would die with a traceback on `-p kp:=1` (an
integer where a float is declared) or a value outside the range. Nodes that can run on
their shipped defaults keep the default instead and report the refusal, as a refused
`ros2 param set` keeps the old value. Nodes that must not run on a guess (the hardware
driver, whose parameters include the pressure ceiling) are built through node_or_exit: the
same one-line reason, and no start.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import TypeVar

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.node import Node

from pma_common.node import exit_before_start

NodeT = TypeVar('NodeT', bound=Node)

BAD_OVERRIDE_ERRORS = (InvalidParameterTypeException, InvalidParameterValueException)
# rclpy's words for a wrong type (rclpy.exceptions.InvalidParameterTypeException)
_WRONG_TYPE = re.compile(
    r"Trying to set parameter '.*?' to '(.*)' of type '(\w+)', expecting type '([\w.]+)'")


def refusal_reason(error: Exception) -> str:
    """One line for a refused override: rclpy's reason, and for an integer given where a
    float is declared, how to write it."""
    text, name = str(error).rsplit(': ', 1)    # rclpy ends it with the parameter's name
    if isinstance(error, InvalidParameterValueException):
        return text.rsplit('Reason: ', 1)[-1]
    wrong_type = _WRONG_TYPE.match(text)
    if wrong_type is None:
        return text
    value, given, expected = wrong_type.groups()
    expected = expected.rsplit('.', 1)[-1]
    if given == 'INTEGER' and expected == 'DOUBLE':
        return f'{name} is a float parameter: write {value}.0, not {value}'
    return f'{name} must be of type {expected}, got {value!r} ({given})'


def declare_or_keep_default(node: Node, name: str, default,
                            descriptor: ParameterDescriptor) -> str | None:
    """Declare `name`; an override of the wrong type or out of range is dropped, the default
    kept. Returns why it was refused, or None when the override (or the default) was taken."""
    try:
        node.declare_parameter(name, default, descriptor)
        return None
    except BAD_OVERRIDE_ERRORS as error:
        node.declare_parameter(name, default, descriptor, ignore_override=True)
        return refusal_reason(error)


def node_or_exit(make_node: Callable[[], NodeT], program: str) -> NodeT:
    """`make_node()`; a parameter it refuses ends the process instead (exit code 2 and
    `program: bad parameter, not started: <reason>`), before anything runs."""
    try:
        return make_node()
    except ParameterException as error:
        exit_before_start(program, f'bad parameter, not started: {refusal_reason(error)}')
