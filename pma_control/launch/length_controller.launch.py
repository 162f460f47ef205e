"""The length controller alone (beside driver_node, and model_node if it runs).

    ros2 launch pma_control length_controller.launch.py
    ros2 launch pma_control length_controller.launch.py namespace:=left mode:=fb

Then: `ros2 action send_goal --feedback /pma/move_to_length
pma_interfaces/action/MoveToLength "{length_m: 0.265}"` or a stream on pma/length_setpoint.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    controller = Node(
        package='pma_control', executable='length_controller', name='length_controller',
        namespace=LaunchConfiguration('namespace'),
        parameters=[LaunchConfiguration('params_file'),
                    {'mode': ParameterValue(LaunchConfiguration('mode'), value_type=str)}],
        output='screen', emulate_tty=True)
    return LaunchDescription([
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of this muscle, e.g. left: /left/pma/state in, '
                        '/left/pma/move_to_length served'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('pma_control'), 'config', 'length_controller.yaml']),
            description='length_controller parameters (YAML with /**)'),
        DeclareLaunchArgument(
            'mode', default_value='ff_fb', choices=['ff_fb', 'ff', 'fb'],
            description='ff_fb: model feedforward + feedback; ff or fb alone (comparisons)'),
        controller,
    ])
