"""ROS arguments a node cannot start with, as `ros2 run PKG EXE --ros-args ...` gives them.

A params file that is missing or not YAML, or a malformed remap rule, makes rcl refuse to
initialise; every PMA executable then exits with code 2 and rcl's reason on one line (the
bad *values* of parameters: test_length_controller, test_model_node, test_driver_node).
"""

from __future__ import annotations

import pytest

from support.procs import executable as procs_executable

pytestmark = pytest.mark.integration

EXECUTABLES = [('pma_driver', 'driver_node'), ('pma_model', 'model_node'),
               ('pma_control', 'length_controller'), ('pma_bag', 'record'),
               ('pma_bringup', 'foxglove_live')]


@pytest.mark.parametrize('package, exe', EXECUTABLES, ids=[exe for _, exe in EXECUTABLES])
def test_a_params_file_that_is_not_yaml_ends_it_with_one_line(procs, tmp_path, package, exe):
    broken = tmp_path / 'rig.yaml'
    broken.write_text('/**:\n  ros__parameters:\n    kp: [1,\n')
    proc = procs.ros2_run(package, exe, ros_args=['--params-file', str(broken)], cwd=tmp_path)
    assert proc.popen.wait(20) == 2
    line = proc.wait_for_line(f'{exe}: cannot start: ')
    assert f"Couldn't parse params file: '--params-file {broken}'" in line
    assert ', at /' not in line                    # rcl's C source locations left out
    assert 'Traceback' not in proc.output
    assert not list(tmp_path.glob('pma_bag_*'))    # the recorder opened no bag


def test_a_missing_params_file_and_a_bad_remap_say_which(procs, tmp_path):
    missing = procs.ros2_run('pma_model', 'model_node',
                             ros_args=['--params-file', str(tmp_path / 'nowhere.yaml')])
    remap = procs.ros2_run('pma_control', 'length_controller', ros_args=['-r', 'foo'])
    assert missing.popen.wait(20) == 2 and remap.popen.wait(20) == 2
    assert 'Error opening YAML file' in missing.wait_for_line('model_node: cannot start: ')
    assert "Couldn't parse remap rule: '-r foo'" in \
        remap.wait_for_line('length_controller: cannot start: ')


NODES_WITHOUT_OWN_ARGUMENTS = [e for e in EXECUTABLES if e[1] != 'record']


@pytest.mark.parametrize('package, exe', NODES_WITHOUT_OWN_ARGUMENTS,
                         ids=[exe for _, exe in NODES_WITHOUT_OWN_ARGUMENTS])
def test_a_parameter_without_ros_args_is_refused_not_ignored(procs, tmp_path, package, exe):
    """`foxglove_live -p host:=0.0.0.0` (as the README once said) ran on its defaults: rcl
    ignores what is not after --ros-args, and the server stayed on localhost."""
    proc = procs.start([str(procs_executable(package, exe)), '-p', 'host:=0.0.0.0'],
                       name=exe, cwd=tmp_path)
    assert proc.popen.wait(20) == 2
    line = proc.wait_for_line(f'{exe}: unexpected argument')
    assert "'-p host:=0.0.0.0'" in line
    assert f'`{exe} --ros-args -p host:=0.0.0.0`' in line
    assert 'Traceback' not in proc.output


def test_the_recorder_refuses_a_parameter_without_ros_args_too(procs, tmp_path):
    """The recorder parses arguments of its own; a stray -p is one it does not know."""
    proc = procs.start([str(procs_executable('pma_bag', 'record')), '-p', 'topics:=[a]'],
                       name='record', cwd=tmp_path)
    assert proc.popen.wait(20) == 2
    assert 'Traceback' not in proc.output
    assert not list(tmp_path.glob('pma_bag_*'))
