"""The PMA model node alone.

    ros2 launch pma_model model.launch.py
    ros2 launch pma_model model.launch.py namespace:=left refit_params_file:=runs/left/refit.yaml
    ros2 launch pma_model model.launch.py use_sim_time:=true     # with `replay BAG --clock`

`params_file` is the node's ROS parameters (defaults in config/model_node.yaml);
`refit_params_file` is a `refit --params-out` file that model_node loads at start and reloads
whenever it changes (its `params_file` parameter), so a new fit takes effect without a restart.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    model = Node(
        package='pma_model', executable='model_node', name='model_node',
        namespace=LaunchConfiguration('namespace'),
        parameters=[
            LaunchConfiguration('params_file'),
            # ParameterValue(str): an empty path must stay '' (YAML would read it as null).
            {'params_file': ParameterValue(LaunchConfiguration('refit_params_file'),
                                           value_type=str),
             'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                            value_type=bool)},
        ],
        output='screen', emulate_tty=True)

    return LaunchDescription([
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of this muscle, e.g. left: /left/pma/state in, '
                        '/left/pressure_for_length served'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare('pma_model'), 'config', 'model_node.yaml']),
            description='model_node parameters (YAML with /** so any namespace matches)'),
        DeclareLaunchArgument(
            'refit_params_file', default_value='',
            description='refit --params-out YAML, hot-reloaded when it changes; empty = none'),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', choices=['true', 'false'],
            description='true when the clock comes from a bag replayed with --clock'),
        model,
    ])
