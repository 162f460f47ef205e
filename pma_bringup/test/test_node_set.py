"""pma_bringup.node_set without ROS: the values `-p` carries, and the stop order of `pma up`
(tests/test_launch_files.py checks the list against the launch file and the real nodes)."""

import pytest
import yaml

from pma_bringup.node_set import Options, node_set, stop_order, yaml_value

pytestmark = pytest.mark.in_process


def share(package: str) -> str:
    return f'/share/{package}'


def test_parameter_values_keep_their_type_through_the_command_line():
    for value in ('', 'true', '1', '/dev/pma0', 'ff_fb', True, False, 8765, 0.5, 1e-9,
                  'a b', "it's", ['x', 'y']):
        assert yaml.safe_load(yaml_value(value)) == value, value
        assert type(yaml.safe_load(yaml_value(value))) is type(value), value
    assert yaml_value('') == "''" and yaml_value('/dev/pma0') == '/dev/pma0'


def test_stop_order_controller_then_driver_then_the_rest_then_the_device():
    specs = node_set(Options(simulated=True, record=True, live=True), share=share)
    assert [s.name for s in specs] == ['fake_arduino', 'driver_node', 'model_node',
                                       'length_controller', 'recorder', 'foxglove_live']
    stages = [[s.name for s in stage] for stage in stop_order(specs)]
    assert stages == [['length_controller'], ['driver_node'],
                      ['foxglove_live', 'recorder', 'model_node'], ['fake_arduino']]
    hardware = stop_order(node_set(Options(control=False), share=share))
    assert [[s.name for s in stage] for stage in hardware] == [['driver_node'], ['model_node']]


def test_ros_arguments_name_namespace_files_then_values():
    [driver] = [s for s in node_set(Options(namespace='left', port='/dev/pma0'), share=share)
                if s.name == 'driver_node']
    assert driver.ros_arguments() == [
        '--ros-args', '-r', '__node:=driver_node', '-r', '__ns:=/left',
        '--params-file', '/share/pma_driver/config/driver_node.yaml',
        '-p', 'port:=/dev/pma0', '-p', 'autostart:=true']
    [fake] = node_set(Options(simulated=True, namespace='a/b'), share=share)[:1]
    assert fake.ros_arguments() == [] and fake.arguments == ('--link', '/tmp/pma_a_b',
                                                             '--seed', '0')


def test_options_from_launch_arguments():
    options = Options.from_launch_arguments({
        'use_fake_arduino': 'true', 'control': 'false', 'live_port': '8766',
        'namespace': 'left', 'launch_own_argument': 'x'})
    assert options == Options(simulated=True, control=False, live_port=8766, namespace='left')
