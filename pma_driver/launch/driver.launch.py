"""The PMA driver alone.

    ros2 launch pma_driver driver.launch.py port:=/dev/pma0
    ros2 launch pma_driver driver.launch.py port:=/dev/pma1 namespace:=right
    ros2 launch pma_driver driver.launch.py params_file:=my_rig.yaml autostart:=false

Why a LifecycleNode action and not a plain Node: driver_node is a lifecycle node either way,
and with `autostart` true (the default) it configures and activates itself, retrying every
`reconnect_period_s` while the port is missing; launch event handlers could not do that (a
failed configure leaves the node unconfigured for good). LifecycleNode lets `autostart:=false`
hand the transitions to this launch file instead (the transport_drivers pattern: configure
when the process starts, activate once it is inactive), and lets other launch files target the
driver with lifecycle events.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.conditions import UnlessCondition
from launch.event_handlers import OnProcessStart
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import LifecycleNode
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition


def generate_launch_description():
    namespace = LaunchConfiguration('namespace')
    port = LaunchConfiguration('port')
    params_file = LaunchConfiguration('params_file')
    autostart = LaunchConfiguration('autostart')

    driver = LifecycleNode(
        package='pma_driver', executable='driver_node', name='driver_node', namespace=namespace,
        # The launch argument `port` overrides the params file's `port` (last one wins).
        # ParameterValue(str) keeps a value such as '' or '1' from turning into YAML null/int.
        parameters=[params_file, {'port': ParameterValue(port, value_type=str),
                                  'autostart': ParameterValue(autostart, value_type=bool)}],
        output='screen', emulate_tty=True)

    # Only with autostart:=false: configure when the process starts, activate when configured.
    configure_on_start = RegisterEventHandler(
        OnProcessStart(target_action=driver, on_start=[EmitEvent(event=ChangeState(
            lifecycle_node_matcher=matches_action(driver),
            transition_id=Transition.TRANSITION_CONFIGURE))]),
        condition=UnlessCondition(autostart))
    activate_when_configured = RegisterEventHandler(
        OnStateTransition(
            target_lifecycle_node=driver, start_state='configuring', goal_state='inactive',
            entities=[EmitEvent(event=ChangeState(
                lifecycle_node_matcher=matches_action(driver),
                transition_id=Transition.TRANSITION_ACTIVATE))]),
        condition=UnlessCondition(autostart))

    return LaunchDescription([
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of this muscle, e.g. left: topics become /left/pma/...'),
        DeclareLaunchArgument(
            'port', default_value='/dev/ttyACM0',
            description='serial port (overrides the params file); prefer /dev/pma0 (udev rule) '
                        'or /dev/serial/by-id/...'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('pma_driver'), 'config', 'driver_node.yaml']),
            description='driver_node parameters (YAML with /** so any namespace matches)'),
        DeclareLaunchArgument(
            'autostart', default_value='true', choices=['true', 'false'],
            description='true: the node configures and activates itself and retries while '
                        'the port is missing; false: this launch file drives the transitions'),
        driver,
        configure_on_start,
        activate_when_configured,
    ])
