"""Hints name a command that works on the user's path: `pma run` without a ros2 CLI."""

from __future__ import annotations

import os
import stat

import pytest

from pma_common.commands import has_ros2_cli, run_command

pytestmark = pytest.mark.in_process


@pytest.fixture
def fake_ros2(tmp_path):
    ros2 = tmp_path / 'ros2'
    ros2.write_text('#!/bin/sh\n')
    ros2.chmod(ros2.stat().st_mode | stat.S_IXUSR)
    return str(tmp_path)


def test_wheels_mode_says_pma_run_even_with_a_ros2_on_path(fake_ros2):
    environ = {'PMA_ROS_MODE': 'wheels', 'PATH': fake_ros2}
    assert not has_ros2_cli(environ)
    assert run_command('pma_bag', 'recover', '/tmp/b', environ=environ) == \
        'pma run pma_bag recover /tmp/b'


def test_no_ros2_on_path_says_pma_run(tmp_path):
    environ = {'PMA_ROS_MODE': 'system', 'PATH': str(tmp_path)}
    assert run_command('pma_bag', 'recover', 'B', environ=environ) == 'pma run pma_bag recover B'


def test_a_full_install_says_ros2_run(fake_ros2):
    environ = {'PMA_ROS_MODE': 'system', 'PATH': fake_ros2}
    assert has_ros2_cli(environ)
    assert run_command('pma_bag', 'record', '--idle', environ=environ) == \
        'ros2 run pma_bag record --idle'


def test_this_shell_matches_its_mode():
    expected = 'pma run' if os.environ.get('PMA_ROS_MODE') == 'wheels' else None
    if expected:
        assert run_command('a', 'b').startswith(expected)
