"""One PMA muscle in one namespace: driver, model, length controller (+ simulated rig, recorder).

    ros2 launch pma_bringup bringup.launch.py port:=/dev/pma0
    ros2 launch pma_bringup bringup.launch.py use_fake_arduino:=true record:=true
    ros2 launch pma_bringup bringup.launch.py use_fake_arduino:=true live:=true
        # + the live view: Foxglove -> Open connection -> ws://127.0.0.1:8765 (docs/live-view.md)
    # two muscles side by side (two terminals, or include this file twice):
    ros2 launch pma_bringup bringup.launch.py namespace:=left port:=/dev/pma0
    ros2 launch pma_bringup bringup.launch.py namespace:=right port:=/dev/pma1

Which nodes start, with which arguments and parameters files, comes from
pma_bringup.node_set, the list `pma up` starts too (the same nodes without `ros2 launch`:
docs/cli.md); this file turns it into launch actions. The driver is a LifecycleNode that
autostarts (pma_driver's driver.launch.py says why); with autostart:=false this file
configures it when its process starts and activates it once configured. With
use_fake_arduino:=true, fake_arduino makes `port` a symlink to its pty; the driver retries the
port until it appears, so start order does not matter. docs/user-guide.md walks through the
whole bring-up.
"""

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    ExecuteProcess,
    OpaqueFunction,
    RegisterEventHandler,
)
from launch.event_handlers import OnProcessStart
from launch.events import matches_action
from launch.substitutions import PathJoinSubstitution
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackagePrefix, FindPackageShare
from lifecycle_msgs.msg import Transition

from pma_bringup.node_set import (
    DEFAULT_PARAMS_FILES,
    DEVICE_PORT,
    LIVE_PORT,
    RECORDER_ARGUMENTS,
    Options,
    node_set,
)


def _parameters(spec) -> list:
    """The spec's files, then its values; a string as ParameterValue(str), so that launch
    does not read '' or 'true' as YAML (null, a bool)."""
    values = {name: ParameterValue(value, value_type=str) if isinstance(value, str) else value
              for name, value in spec.parameters.items()}
    return [*spec.params_files, *([values] if values else [])]


def _manual_lifecycle(driver) -> list:
    """autostart:=false: configure when the process starts, activate when configured."""
    def change(transition_id):
        return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(driver),
                                           transition_id=transition_id))
    return [RegisterEventHandler(OnProcessStart(
                target_action=driver, on_start=[change(Transition.TRANSITION_CONFIGURE)])),
            RegisterEventHandler(OnStateTransition(
                target_lifecycle_node=driver, start_state='configuring', goal_state='inactive',
                entities=[change(Transition.TRANSITION_ACTIVATE)]))]


def _bringup(context):
    """Resolve the arguments once, then one action per process of node_set."""
    options = Options.from_launch_arguments(context.launch_configurations)
    actions = []
    for spec in node_set(options):
        if not spec.ros:
            # A plain executable, not a ROS node: ExecuteProcess, so no --ros-args are appended.
            actions.append(ExecuteProcess(
                cmd=[PathJoinSubstitution([FindPackagePrefix(spec.package), 'lib',
                                           spec.package, spec.executable]), *spec.arguments],
                name=spec.name, output='screen', additional_env=dict(spec.env)))
            continue
        node = (LifecycleNode if spec.lifecycle else Node)(
            package=spec.package, executable=spec.executable, name=spec.name,
            namespace=spec.namespace, arguments=list(spec.arguments),
            parameters=_parameters(spec), remappings=list(spec.remappings),
            output='screen', emulate_tty=True)
        actions.append(node)
        if spec.lifecycle and not options.autostart:
            actions += _manual_lifecycle(node)
    return actions


def _default_params(option: str):
    package, relative = DEFAULT_PARAMS_FILES[option]
    return PathJoinSubstitution([FindPackageShare(package), *relative.split('/')])


def _recorder_help(name: str) -> str:
    return f"record: {RECORDER_ARGUMENTS[name]}; into every bag's custom_data"


def generate_launch_description():
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
            'driver', default_value='true', choices=['true', 'false'],
            description='false: no driver_node (nor fake_arduino) here: the rig computer runs '
                        'it (docs/lab-network.md)'),
        DeclareLaunchArgument(
            'model', default_value='true', choices=['true', 'false'],
            description='false: no model_node here (another computer runs it)'),
        DeclareLaunchArgument(
            'control', default_value='true', choices=['true', 'false'],
            description='true: also run the length controller (idle until given a target)'),
        DeclareLaunchArgument(
            'control_params_file',
            default_value=_default_params('control_params_file'),
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
            default_value=_default_params('driver_params_file'),
            description='driver_node parameters'),
        DeclareLaunchArgument(
            'model_params_file',
            default_value=_default_params('model_params_file'),
            description='model_node parameters'),
        DeclareLaunchArgument(
            'refit_params_file', default_value='',
            description='refit --params-out YAML that model_node hot-reloads; empty = none'),
        DeclareLaunchArgument(
            'recorder_params_file',
            default_value=_default_params('recorder_params_file'),
            description='recorder parameters (the topic list)'),
        # With record: the experiment's facts in every bag's custom_data (docs/bags.md):
        # pma_common.experiment.RECORDER_ARGUMENTS, which test_launch_files holds these to.
        DeclareLaunchArgument('muscle', default_value='',
                              description=_recorder_help('muscle')),
        DeclareLaunchArgument('load_kg', default_value='',
                              description=_recorder_help('load_kg')),
        DeclareLaunchArgument('supply_kpa', default_value='',
                              description=_recorder_help('supply_kpa')),
        DeclareLaunchArgument('operator', default_value='',
                              description=_recorder_help('operator')),
        DeclareLaunchArgument('note', default_value='', description=_recorder_help('note')),
        OpaqueFunction(function=_bringup),
    ])
