"""Which processes make up one muscle, with which arguments and parameters: the one list.

bringup.launch.py builds its launch actions from `node_set(options)` (`ros2 launch` on a full
install) and `pma up` builds the argv of each process from the same list (`ros2 run`'s
`install/PKG/lib/PKG/EXE ARGS --ros-args ...`), so the two start the same nodes with the same
parameters files. Plain Python: no `launch`, no rclpy (PyYAML renders `-p` values).

    from pma_bringup.node_set import Options, node_set
    for spec in node_set(Options(simulated=True, namespace='left'), share=share_of):
        print(spec.name, spec.arguments, spec.ros_arguments())
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from datetime import datetime
from pathlib import Path

from pma_common.experiment import RECORDER_ARGUMENTS, recorder_flags

DEVICE_PORT = '/dev/ttyACM0'
LIVE_HOST = '127.0.0.1'
LIVE_PORT = 8765

# The parameters files each node loads unless told otherwise: option -> (package, path in
# the package's share/ directory, where setup.py installs config/*.yaml).
DEFAULT_PARAMS_FILES = {
    'driver_params_file': ('pma_driver', 'config/driver_node.yaml'),
    'model_params_file': ('pma_model', 'config/model_node.yaml'),
    'control_params_file': ('pma_control', 'config/length_controller.yaml'),
    'recorder_params_file': ('pma_bag', 'config/record.yaml'),
}

# The order in which `pma up` stops them (processes not named here stop after these, in
# reverse start order; the simulated device last of all): the controller first, so that it
# stops commanding; then the driver, which vents the muscle as it stops (through the device,
# which must still run) while the recorder still records; then the rest.
STOP_ORDER = ('length_controller', 'driver_node')


def live_port(text: str | int) -> int:
    """The live view's TCP port as the integer parameter foxglove_live declares."""
    try:
        port = int(text)
    except ValueError:
        raise ValueError(f'live_port:={text} is not a port number') from None
    if not 0 <= port <= 65535:
        raise ValueError(f'live_port:={text} is outside 0..65535')
    return port


def flag(value: str) -> bool:
    """'true'/'false' as launch's IfCondition reads them."""
    return value.strip().lower() in ('true', '1')


def default_port(namespace: str, simulated: bool) -> str:
    """A per-namespace /tmp path for the simulated device (never a real /dev node)."""
    if not simulated:
        return DEVICE_PORT
    return f'/tmp/pma_{namespace.strip("/").replace("/", "_") or "muscle"}'


def default_bag_dir(namespace: str) -> str:
    """pma_bag_[<namespace>_]<date-time>, so two muscles never write into the same bag."""
    stem = namespace.strip('/').replace('/', '_')
    stamp = datetime.now().strftime('%Y_%m_%d-%H_%M_%S')
    return f'pma_bag_{stem + "_" if stem else ""}{stamp}'


def package_share(package: str) -> str:
    """The package's share/ directory, as launch's FindPackageShare finds it."""
    from ament_index_python.packages import get_package_share_directory
    return get_package_share_directory(package)


# bringup.launch.py's argument name -> the Options field, where they differ.
LAUNCH_NAMES = {'use_fake_arduino': 'simulated'}


@dataclass(frozen=True)
class Options:
    """One muscle's bring-up; the fields are bringup.launch.py's arguments (see
    `from_launch_arguments`). An empty params file is the package's default one."""

    namespace: str = ''
    port: str = ''                      # '' = default_port(namespace, simulated)
    simulated: bool = False             # launch: use_fake_arduino
    fake_arduino_seed: str = '0'
    # false: that node runs on another computer (the rig's driver, docs/lab-network.md)
    driver: bool = True
    model: bool = True
    control: bool = True
    record: bool = False
    bag_dir: str = ''                   # '' = default_bag_dir(namespace)
    live: bool = False
    live_host: str = LIVE_HOST
    live_port: int = LIVE_PORT
    autostart: bool = True
    driver_params_file: str = ''
    model_params_file: str = ''
    refit_params_file: str = ''
    control_params_file: str = ''
    recorder_params_file: str = ''
    # The experiment's facts for the recorder's bags, by launch argument name
    # (pma_common.experiment.RECORDER_ARGUMENTS: muscle, load_kg, ..., note).
    experiment: Mapping[str, str] = field(default_factory=dict)
    # Not launch arguments of bringup.launch.py: the values its nodes always got.
    control_mode: str = 'ff_fb'
    use_sim_time: bool = False

    @classmethod
    def from_launch_arguments(cls, arguments: Mapping[str, str]) -> Options:
        """Options from launch arguments as strings (`use_fake_arduino: 'true'`, ...); names
        that are not options (launch's own) are left out."""
        kinds = {f.name: f.type for f in fields(cls)}
        values, experiment = {}, {}
        for name, text in arguments.items():
            if name in RECORDER_ARGUMENTS:
                if text:
                    experiment[name] = str(text)
                continue
            key = LAUNCH_NAMES.get(name, name)
            if key not in kinds:
                continue
            kind = kinds[key]
            values[key] = (flag(text) if kind == 'bool' else live_port(text)
                           if key == 'live_port' else str(text))
        return cls(**values, experiment=experiment)

    def resolved_port(self) -> str:
        return self.port or default_port(self.namespace, self.simulated)

    def params_file(self, option: str, share: Callable[[str], str]) -> str:
        given = getattr(self, option)
        if given:
            return given
        package, relative = DEFAULT_PARAMS_FILES[option]
        return str(Path(share(package)) / relative)


@dataclass(frozen=True)
class NodeSpec:
    """One process: `package`'s `executable` with `arguments`; for a ROS node (`ros`) also
    its node name, namespace, parameters files, then parameters (typed values, applied after
    the files), and remappings, all of which go after --ros-args."""

    name: str                           # the node's name; its log's name
    package: str
    executable: str
    arguments: tuple[str, ...] = ()
    ros: bool = True                    # False: a plain program (fake_arduino), no --ros-args
    namespace: str = ''
    params_files: tuple[str, ...] = ()
    parameters: Mapping[str, object] = field(default_factory=dict)
    remappings: tuple[tuple[str, str], ...] = ()
    lifecycle: bool = False             # launch: a LifecycleNode (the driver)
    env: Mapping[str, str] = field(default_factory=dict)

    def fully_qualified_namespace(self) -> str:
        return '/' + self.namespace.strip('/')

    def ros_arguments(self) -> list[str]:
        """What `ros2 launch` gives the node after --ros-args (launch writes the parameters
        to a file of its own; `-p` gives the same values with the same types)."""
        if not self.ros:
            return []
        argv = ['--ros-args', '-r', f'__node:={self.name}']
        if self.namespace.strip('/'):
            argv += ['-r', f'__ns:={self.fully_qualified_namespace()}']
        for path in self.params_files:
            argv += ['--params-file', path]
        for name, value in self.parameters.items():
            argv += ['-p', f'{name}:={yaml_value(value)}']
        for source, target in self.remappings:
            argv += ['-r', f'{source}:={target}']
        return argv


def yaml_value(value) -> str:
    """A `-p name:=VALUE` value that rcl reads back with its type: '' and 'true' as
    strings stay strings ('' and 'true' quoted), 8765 an integer, 0.5 a double."""
    import yaml
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 20).strip()
    return text.removesuffix('...').strip()


def node_set(options: Options, share: Callable[[str], str] = package_share) -> list[NodeSpec]:
    """The processes of one muscle, in start order: [fake_arduino], [driver_node],
    [model_node], [length_controller], [recorder], [foxglove_live]. `share(package)` finds
    the default parameters files (launch passes what its arguments resolved to)."""
    namespace = options.namespace
    port = options.resolved_port()
    specs = []
    if options.driver and options.simulated:
        # A plain executable, not a ROS node: no --ros-args.
        specs.append(NodeSpec(
            name='fake_arduino', package='pma_sim', executable='fake_arduino', ros=False,
            arguments=('--link', port, '--seed', str(options.fake_arduino_seed)),
            env={'PYTHONUNBUFFERED': '1'}))
    if options.driver:
        # The port and autostart given after the file win over the file's.
        specs.append(NodeSpec(
            name='driver_node', package='pma_driver', executable='driver_node',
            namespace=namespace, lifecycle=True,
            params_files=(options.params_file('driver_params_file', share),),
            parameters={'port': port, 'autostart': options.autostart}))
    if options.model:
        specs.append(NodeSpec(
            name='model_node', package='pma_model', executable='model_node',
            namespace=namespace,
            params_files=(options.params_file('model_params_file', share),),
            parameters={'params_file': options.refit_params_file,
                        'use_sim_time': options.use_sim_time}))
    if options.control:
        specs.append(NodeSpec(
            name='length_controller', package='pma_control', executable='length_controller',
            namespace=namespace,
            params_files=(options.params_file('control_params_file', share),),
            parameters={'mode': options.control_mode}))
    if options.record:
        specs.append(NodeSpec(
            name='recorder', package='pma_bag', executable='record', namespace=namespace,
            arguments=('-o', options.bag_dir or default_bag_dir(namespace),
                       *recorder_flags(options.experiment)),
            params_files=(options.params_file('recorder_params_file', share),)))
    if options.live:
        specs.append(NodeSpec(
            name='foxglove_live', package='pma_bringup', executable='foxglove_live',
            namespace=namespace,
            parameters={'host': options.live_host, 'port': live_port(options.live_port)}))
    return specs


def stop_order(specs: list[NodeSpec]) -> list[list[NodeSpec]]:
    """The stages in which `pma up` stops `specs`: one at a time as STOP_ORDER says, then
    every other ROS node together, then the simulated device (the driver vents through it)."""
    by_name = {spec.name: spec for spec in specs}
    stages = [[by_name[name]] for name in STOP_ORDER if name in by_name]
    ordered = {spec.name for stage in stages for spec in stage}
    rest = [spec for spec in reversed(specs) if spec.name not in ordered and spec.ros]
    devices = [spec for spec in reversed(specs) if spec.name not in ordered and not spec.ros]
    return stages + [stage for stage in (rest, devices) if stage]
