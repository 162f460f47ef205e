"""One PMA muscle in one namespace: driver, model, length controller (+ simulated rig, recorder).

    ros2 launch pma_bringup bringup.launch.py port:=/dev/pma0
    ros2 launch pma_bringup bringup.launch.py use_fake_arduino:=true record:=true
    ros2 launch pma_bringup bringup.launch.py use_fake_arduino:=true live:=true
        # + the live view: Foxglove -> Open connection -> ws://127.0.0.1:8765 (docs/live-view.md)
    # two muscles side by side (two terminals, or include this file twice):
    ros2 launch pma_bringup bringup.launch.py namespace:=left port:=/dev/pma0
    ros2 launch pma_bringup bringup.launch.py namespace:=right port:=/dev/pma1

The driver comes from driver.launch.py (a LifecycleNode that autostarts; that file says why)
and the model from pma_model's model.launch.py, each included in its own scope so their
`params_file` arguments do not leak into each other. With use_fake_arduino:=true,
fake_arduino makes `port` a symlink to its pty; the driver retries the port until it appears,
so start order does not matter. docs/user-guide.md walks through the whole bring-up.
"""

from datetime import datetime

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    ExecuteProcess,
    GroupAction,
    IncludeLaunchDescription,
    OpaqueFunction,
)
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackagePrefix, FindPackageShare

DEVICE_PORT = '/dev/ttyACM0'
LIVE_PORT = 8765


def live_port(text: str) -> int:
    """The live view's TCP port as the integer parameter foxglove_live declares."""
    try:
        port = int(text)
    except ValueError:
        raise ValueError(f'live_port:={text} is not a port number') from None
    if not 0 <= port <= 65535:
        raise ValueError(f'live_port:={text} is outside 0..65535')
    return port


def _flag(value: str) -> bool:
    """'true'/'false' as IfCondition reads them (choices already refuse anything else)."""
    return value.strip().lower() in ('true', '1')


def default_port(namespace: str, use_fake_arduino: bool) -> str:
    """A per-namespace /tmp path for the simulated device (never a real /dev node)."""
    if not use_fake_arduino:
        return DEVICE_PORT
    return f'/tmp/pma_{namespace.strip("/").replace("/", "_") or "muscle"}'


def default_bag_dir(namespace: str) -> str:
    """pma_bag_[<namespace>_]<date-time>, so two muscles never write into the same bag."""
    stem = namespace.strip('/').replace('/', '_')
    stamp = datetime.now().strftime('%Y_%m_%d-%H_%M_%S')
    return f'pma_bag_{stem + "_" if stem else ""}{stamp}'


def _bringup(context):
    """Resolve the arguments once, then build this muscle's actions from plain strings."""
    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    namespace = arg('namespace')
    use_fake_arduino = _flag(arg('use_fake_arduino'))
    port = arg('port') or default_port(namespace, use_fake_arduino)
    actions = []

    if use_fake_arduino:
        # A plain executable, not a ROS node: ExecuteProcess, so no --ros-args are appended.
        actions.append(ExecuteProcess(
            cmd=[PathJoinSubstitution(
                [FindPackagePrefix('pma_driver'), 'lib', 'pma_driver', 'fake_arduino']),
                '--link', port, '--seed', arg('fake_arduino_seed')],
            name='fake_arduino', output='screen', additional_env={'PYTHONUNBUFFERED': '1'}))

    actions.append(GroupAction([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution(
            [FindPackageShare('pma_driver'), 'launch', 'driver.launch.py'])),
        launch_arguments={'namespace': namespace, 'port': port,
                          'params_file': arg('driver_params_file'),
                          'autostart': arg('autostart')}.items())]))

    actions.append(GroupAction([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(PathJoinSubstitution(
            [FindPackageShare('pma_model'), 'launch', 'model.launch.py'])),
        launch_arguments={'namespace': namespace,
                          'params_file': arg('model_params_file'),
                          'refit_params_file': arg('refit_params_file')}.items())]))

    if _flag(arg('control')):
        actions.append(GroupAction([IncludeLaunchDescription(
            PythonLaunchDescriptionSource(PathJoinSubstitution(
                [FindPackageShare('pma_control'), 'launch', 'length_controller.launch.py'])),
            launch_arguments={'namespace': namespace,
                              'params_file': arg('control_params_file')}.items())]))

    if _flag(arg('record')):
        actions.append(Node(
            package='pma_bag', executable='record', name='recorder', namespace=namespace,
            arguments=['-o', arg('bag_dir') or default_bag_dir(namespace)],
            parameters=[arg('recorder_params_file')], output='screen', emulate_tty=True))

    if _flag(arg('live')):
        actions.append(Node(
            package='pma_bringup', executable='foxglove_live', name='foxglove_live',
            namespace=namespace, output='screen', emulate_tty=True,
            parameters=[{'host': arg('live_host'), 'port': live_port(arg('live_port'))}]))
    return actions


def generate_launch_description():
    driver_config = PathJoinSubstitution([FindPackageShare('pma_driver'), 'config'])
    return LaunchDescription([
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of this muscle (left, right, ...): /left/pma/state, '
                        '/left/pressure_for_length, ...'),
        DeclareLaunchArgument(
            'port', default_value='',
            description=f'serial port; empty = {DEVICE_PORT}, or /tmp/pma_<namespace> with '
                        'use_fake_arduino. Prefer /dev/pma0 (udev rule) on the real rig'),
        DeclareLaunchArgument(
            'use_fake_arduino', default_value='false', choices=['true', 'false'],
            description='true: start fake_arduino (simulated rig) with --link at `port`'),
        DeclareLaunchArgument(
            'fake_arduino_seed', default_value='0',
            description='seed of the simulated sensor noise (use_fake_arduino only)'),
        DeclareLaunchArgument(
            'control', default_value='true', choices=['true', 'false'],
            description='true: also run the length controller (idle until given a target)'),
        DeclareLaunchArgument(
            'control_params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('pma_control'), 'config', 'length_controller.yaml']),
            description='length_controller parameters'),
        DeclareLaunchArgument(
            'record', default_value='false', choices=['true', 'false'],
            description='true: also run the recorder (MCAP bag of this namespace\'s topics)'),
        DeclareLaunchArgument(
            'bag_dir', default_value='',
            description='bag directory to create; empty = pma_bag_[<namespace>_]<date-time>'),
        DeclareLaunchArgument(
            'live', default_value='false', choices=['true', 'false'],
            description='true: also run foxglove_live, the live view for Foxglove (its ws:// URL '
                        'is in the log; docs/live-view.md)'),
        DeclareLaunchArgument(
            'live_host', default_value='127.0.0.1',
            description='address the live view listens on: 127.0.0.1 = this machine only, '
                        '0.0.0.0 = the lab network too (no authentication; docs/live-view.md)'),
        DeclareLaunchArgument(
            'live_port', default_value=str(LIVE_PORT),
            description='TCP port of the live view; one per bridge (two muscles: two ports, or '
                        "one bridge with topics:=['/*/pma/state', ...])"),
        DeclareLaunchArgument(
            'autostart', default_value='true', choices=['true', 'false'],
            description='driver configures/activates itself (true) or launch does it (false)'),
        DeclareLaunchArgument(
            'driver_params_file',
            default_value=PathJoinSubstitution([driver_config, 'driver_node.yaml']),
            description='driver_node parameters'),
        DeclareLaunchArgument(
            'model_params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('pma_model'), 'config', 'model_node.yaml']),
            description='model_node parameters'),
        DeclareLaunchArgument(
            'refit_params_file', default_value='',
            description='refit --params-out YAML that model_node hot-reloads; empty = none'),
        DeclareLaunchArgument(
            'recorder_params_file',
            default_value=PathJoinSubstitution([FindPackageShare('pma_bag'), 'config',
                                                'record.yaml']),
            description='recorder parameters (the topic list)'),
        OpaqueFunction(function=_bringup),
    ])
