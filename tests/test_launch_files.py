"""The launch files, checked here without `launch` (not installable from PyPI) but against
the real nodes.

What runs for real: each launch file is imported and its generate_launch_description()
called; the nodes are started as processes and asked over DDS which parameters they declare
(rcl_interfaces ListParameters/DescribeParameters); fake_arduino's and the recorder's own
argument parsers read the arguments the launch files pass. What is stood in: the `launch` and
`launch_ros` modules, replaced in sys.modules for these tests only by small classes that record
what a launch file builds, resolve substitutions the way launch does (launch arguments, package
share/prefix, path joins, conditions, includes, OpaqueFunction) and refuse keyword arguments
the real Jazzy classes do not take. Not checked: that `ros2 launch` really starts them (no
launch here); docs/user-guide.md lists that as a check for a Jazzy install.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import sys
import types
from pathlib import Path

import pytest
import yaml
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import DescribeParameters, ListParameters

from pma_common import names
from support.procs import INSTALL, ROOT
from support.ros import SpinningNode, shutdown

LAUNCH_FILES = {
    'driver': ROOT / 'pma_driver' / 'launch' / 'driver.launch.py',
    'bringup': ROOT / 'pma_bringup' / 'launch' / 'bringup.launch.py',
    'model': ROOT / 'pma_model' / 'launch' / 'model.launch.py',
    'control': ROOT / 'pma_control' / 'launch' / 'length_controller.launch.py',
}
# (package, executable) -> the name the node gives itself in code.
NODE_NAMES = {('pma_driver', 'driver_node'): 'driver_node',
              ('pma_model', 'model_node'): 'model_node',
              ('pma_bag', 'record'): 'recorder',
              ('pma_control', 'length_controller'): 'length_controller',
              ('pma_bringup', 'foxglove_live'): 'foxglove_live'}

# ---------------------------------------------------------------------------------------
# Stand-ins for launch / launch_ros (Jazzy signatures, keyword names only).

_PROCESS_KWARGS = {'name', 'cwd', 'env', 'additional_env', 'shell', 'sigterm_timeout',
                   'sigkill_timeout', 'emulate_tty', 'output', 'output_format', 'log_cmd',
                   'cached_output', 'on_exit', 'respawn', 'respawn_delay', 'respawn_max_retries',
                   'prefix', 'condition'}
_NODE_KWARGS = _PROCESS_KWARGS | {'executable', 'package', 'namespace', 'exec_name',
                                  'parameters', 'remappings', 'ros_arguments', 'arguments'}


class Context:
    """The part of launch.LaunchContext that substitutions read."""

    def __init__(self, configurations: dict[str, str]):
        self.launch_configurations = dict(configurations)


def perform(value, context: Context) -> str:
    if isinstance(value, str | Path):
        return str(value)
    if isinstance(value, list | tuple):
        return ''.join(perform(part, context) for part in value)
    return value.perform(context)


class StandIn:
    ALLOWED: frozenset[str] = frozenset()
    POSITIONAL = 0

    def __init__(self, *args, **kwargs):
        name = type(self).__name__
        if len(args) > self.POSITIONAL:
            raise TypeError(f'{name}() takes {self.POSITIONAL} positional arguments')
        unknown = set(kwargs) - self.ALLOWED
        if unknown:
            raise TypeError(f'{name}() got unexpected keyword arguments {sorted(unknown)}')
        self.args, self.kwargs = args, kwargs

    @property
    def condition(self):
        return self.kwargs.get('condition')


def stand_in(name: str, allowed=(), positional: int = 0, **methods) -> type:
    return type(name, (StandIn,), {'ALLOWED': frozenset(allowed), 'POSITIONAL': positional,
                                   **methods})


def _launch_configuration_perform(self, context):
    name = self.args[0]
    if name in context.launch_configurations:
        return context.launch_configurations[name]
    if self.kwargs.get('default') is not None:
        return perform(self.kwargs['default'], context)
    raise KeyError(f'launch argument {name!r} used but never declared or given')


def _find_share(self, context):
    path = INSTALL / self.args[0] / 'share' / self.args[0]
    assert path.is_dir(), f'{path} missing: package not built (make setup)'
    return str(path)


def _find_prefix(self, context):
    path = INSTALL / self.args[0]
    assert path.is_dir(), f'{path} missing: package not built (make setup)'
    return str(path)


def _truth(text: str) -> bool:
    value = text.strip().lower()
    assert value in ('true', 'false', '1', '0'), f'not a launch boolean: {text!r}'
    return value in ('true', '1')


def _parameter_value(self, context):
    text = perform(self.args[0], context)
    value_type = self.kwargs.get('value_type')
    if value_type is str:
        return text
    value = yaml.safe_load(text)
    if value_type is not None:
        assert isinstance(value, value_type), f'{text!r} is not a {value_type.__name__}'
    return value


LaunchConfiguration = stand_in('LaunchConfiguration', ['default'], 1,
                               perform=_launch_configuration_perform)
PathJoinSubstitution = stand_in(
    'PathJoinSubstitution', [], 1,
    perform=lambda self, c: os.path.join(*[perform(p, c) for p in self.args[0]]))
TextSubstitution = stand_in('TextSubstitution', ['text'],
                            perform=lambda self, c: self.kwargs['text'])
FindPackageShare = stand_in('FindPackageShare', [], 1, perform=_find_share)
FindPackagePrefix = stand_in('FindPackagePrefix', [], 1, perform=_find_prefix)
ParameterValue = stand_in('ParameterValue', ['value_type'], 1, evaluate=_parameter_value)
IfCondition = stand_in('IfCondition', [], 1,
                       evaluate=lambda self, c: _truth(perform(self.args[0], c)))
UnlessCondition = stand_in('UnlessCondition', [], 1,
                           evaluate=lambda self, c: not _truth(perform(self.args[0], c)))
LaunchDescription = stand_in('LaunchDescription', [], 1)
DeclareLaunchArgument = stand_in('DeclareLaunchArgument',
                                 ['default_value', 'description', 'choices', 'condition'], 1)
GroupAction = stand_in('GroupAction', ['scoped', 'forwarding', 'launch_configurations',
                                       'condition'], 1)
IncludeLaunchDescription = stand_in('IncludeLaunchDescription',
                                    ['launch_arguments', 'condition'], 1)
PythonLaunchDescriptionSource = stand_in('PythonLaunchDescriptionSource', [], 1)
OpaqueFunction = stand_in('OpaqueFunction', ['function', 'args', 'kwargs', 'condition'])
ExecuteProcess = stand_in('ExecuteProcess', _PROCESS_KWARGS | {'cmd'})
Node = stand_in('Node', _NODE_KWARGS)
RegisterEventHandler = stand_in('RegisterEventHandler', ['condition'], 1)
EmitEvent = stand_in('EmitEvent', ['event', 'condition'])
OnProcessStart = stand_in('OnProcessStart', ['target_action', 'on_start', 'handle_once'])
OnStateTransition = stand_in('OnStateTransition', [
    'entities', 'target_lifecycle_node', 'transition', 'start_state', 'goal_state', 'matcher',
    'handle_once'])
ChangeState = stand_in('ChangeState', ['lifecycle_node_matcher', 'transition_id'])
MatchesAction = stand_in('MatchesAction', [], 1)


class LifecycleNode(Node):
    """Jazzy's LifecycleNode requires both name and namespace."""

    def __init__(self, **kwargs):
        for required in ('name', 'namespace'):
            if required not in kwargs:
                raise TypeError(f'LifecycleNode() missing keyword argument {required!r}')
        super().__init__(**kwargs)


STAND_INS = {
    'launch': {'LaunchDescription': LaunchDescription},
    'launch.actions': {c.__name__: c for c in (
        DeclareLaunchArgument, GroupAction, IncludeLaunchDescription, OpaqueFunction,
        ExecuteProcess, RegisterEventHandler, EmitEvent)},
    'launch.substitutions': {c.__name__: c for c in (
        LaunchConfiguration, PathJoinSubstitution, TextSubstitution)},
    'launch.conditions': {'IfCondition': IfCondition, 'UnlessCondition': UnlessCondition},
    'launch.event_handlers': {'OnProcessStart': OnProcessStart},
    'launch.events': {'matches_action': MatchesAction},
    'launch.launch_description_sources': {
        'PythonLaunchDescriptionSource': PythonLaunchDescriptionSource},
    'launch_ros': {},
    'launch_ros.actions': {'Node': Node, 'LifecycleNode': LifecycleNode},
    'launch_ros.substitutions': {'FindPackageShare': FindPackageShare,
                                 'FindPackagePrefix': FindPackagePrefix},
    'launch_ros.parameter_descriptions': {'ParameterValue': ParameterValue},
    'launch_ros.event_handlers': {'OnStateTransition': OnStateTransition},
    'launch_ros.events': {},
    'launch_ros.events.lifecycle': {'ChangeState': ChangeState},
}


@pytest.fixture
def stand_ins(monkeypatch):
    """Install the stand-in modules for one test; monkeypatch removes them afterwards."""
    for name, members in STAND_INS.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        monkeypatch.setitem(sys.modules, name, module)
    for name in STAND_INS:
        parent, _, child = name.rpartition('.')
        if parent:
            setattr(sys.modules[parent], child, sys.modules[name])


# ---------------------------------------------------------------------------------------
# Walking a launch description the way `ros2 launch` would, recording what would start.


class Launched:
    def __init__(self):
        self.arguments: dict[str, StandIn] = {}
        self.nodes: list[dict] = []
        self.processes: list[list[str]] = []
        self.handlers: list[StandIn] = []
        self.included: list[Path] = []


def load_description(path: Path):
    spec = importlib.util.spec_from_file_location(f'launch_file_{path.stem}', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def evaluate_parameters(parameters, context: Context) -> list:
    """Files -> their path (must exist); dicts -> {name: value} as launch would write them."""
    evaluated = []
    for item in parameters or []:
        if isinstance(item, dict):
            evaluated.append({key: value.evaluate(context) if isinstance(value, ParameterValue)
                              else yaml.safe_load(perform(value, context))
                              if isinstance(value, StandIn) else value
                              for key, value in item.items()})
        else:
            evaluated.append(Path(perform(item, context)))
    return evaluated


def walk(entities, context: Context, out: Launched) -> None:
    for entity in entities:
        if entity.condition is not None and not entity.condition.evaluate(context):
            continue
        kind = type(entity)
        if kind is DeclareLaunchArgument:
            name = entity.args[0]
            assert entity.kwargs.get('description'), f'launch argument {name} has no description'
            out.arguments[name] = entity
            if name not in context.launch_configurations:
                default = entity.kwargs.get('default_value')
                if default is not None:
                    context.launch_configurations[name] = perform(default, context)
            choices = entity.kwargs.get('choices')
            value = context.launch_configurations.get(name)
            assert not choices or value in choices, f'{name}:={value} not in {choices}'
        elif kind is GroupAction:
            scoped = entity.kwargs.get('scoped', True)
            walk(entity.args[0], Context(context.launch_configurations) if scoped else context,
                 out)
        elif kind is IncludeLaunchDescription:
            path = Path(perform(entity.args[0].args[0], context))
            assert path.is_file(), f'included {path} is not installed (make setup)'
            out.included.append(path)
            for key, value in entity.kwargs.get('launch_arguments') or ():
                context.launch_configurations[perform(key, context)] = perform(value, context)
            walk(load_description(path).args[0], context, out)
        elif kind is OpaqueFunction:
            function = entity.kwargs['function']
            walk(function(context, *entity.kwargs.get('args', ()),
                          **entity.kwargs.get('kwargs', {})) or [], context, out)
        elif kind in (Node, LifecycleNode):
            kw = entity.kwargs
            out.nodes.append({
                'action': entity, 'lifecycle': kind is LifecycleNode,
                'package': perform(kw['package'], context),
                'executable': perform(kw['executable'], context),
                'name': perform(kw['name'], context) if 'name' in kw else None,
                'namespace': perform(kw.get('namespace', ''), context),
                'parameters': evaluate_parameters(kw.get('parameters'), context),
                'arguments': [perform(a, context) for a in kw.get('arguments') or []]})
        elif kind is ExecuteProcess:
            out.processes.append([perform(part, context) for part in entity.kwargs['cmd']])
        elif kind is RegisterEventHandler:
            out.handlers.append(entity.args[0])
        else:
            raise AssertionError(f'the walker does not know {kind.__name__}')


def launch(name: str, **arguments: str) -> Launched:
    out = Launched()
    walk(load_description(LAUNCH_FILES[name]).args[0], Context(arguments), out)
    return out


def flatten(tree: dict, prefix: str = '') -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f'{prefix}{key}.'))
        else:
            flat[f'{prefix}{key}'] = value
    return flat


def parameters_given(node: dict) -> dict:
    """Every parameter the launch gives the node, from its files (all `/**`) and dicts."""
    given = {}
    for item in node['parameters']:
        if isinstance(item, Path):
            assert item.is_file(), f'params file {item} does not exist'
            document = yaml.safe_load(item.read_text())
            assert list(document) == ['/**'], (
                f'{item}: use the /** wildcard so the file fits any namespace')
            given.update(flatten(document['/**']['ros__parameters']))
        else:
            given.update(flatten(item))
    return given


# ---------------------------------------------------------------------------------------
# What the real nodes declare, asked over DDS.

_TYPE_OF = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
            float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}
_ARRAY_OF = {bool: ParameterType.PARAMETER_BOOL_ARRAY,
             int: ParameterType.PARAMETER_INTEGER_ARRAY,
             float: ParameterType.PARAMETER_DOUBLE_ARRAY,
             str: ParameterType.PARAMETER_STRING_ARRAY}


def parameter_type(value) -> int:
    if isinstance(value, list):
        kinds = {type(v) for v in value}
        assert len(kinds) == 1, f'mixed list {value}'
        return _ARRAY_OF[kinds.pop()]
    return _TYPE_OF[type(value)]


@pytest.fixture(scope='module')
def declared(module_procs, tmp_path_factory) -> dict[tuple[str, str], dict[str, int]]:
    """{(package, executable): {parameter name: declared type}} from the running nodes."""
    bag = tmp_path_factory.mktemp('bag') / 'b'
    module_procs.ros2_run('pma_driver', 'driver_node',
                          ros_args=['-p', 'port:=/nonexistent/pma_launch_test'])
    module_procs.ros2_run('pma_model', 'model_node')
    module_procs.ros2_run('pma_bag', 'record', '-o', str(bag))
    module_procs.ros2_run('pma_control', 'length_controller')
    module_procs.ros2_run('pma_bringup', 'foxglove_live', ros_args=['-p', 'port:=0'])
    probe = SpinningNode('launch_file_probe')
    try:
        result = {}
        for key, node_name in NODE_NAMES.items():
            names = probe.call(ListParameters, f'/{node_name}/list_parameters',
                               timeout=30.0, idempotent=True).result.names
            described = probe.call(DescribeParameters, f'/{node_name}/describe_parameters',
                                   DescribeParameters.Request(names=list(names)),
                                   timeout=30.0, idempotent=True).descriptors
            result[key] = {d.name: d.type for d in described}
        return result
    finally:
        probe.close()
        shutdown()


def check_nodes_against_code(launched: Launched, declared: dict) -> None:
    assert launched.nodes, 'no node would start'
    for node in launched.nodes:
        key = (node['package'], node['executable'])
        exe = INSTALL / key[0] / 'lib' / key[0] / key[1]
        assert exe.is_file() and os.access(exe, os.X_OK), f'{exe} is not installed'
        assert key in NODE_NAMES, f'unexpected node {key}'
        assert node['name'] in (None, NODE_NAMES[key]), (
            f'{key}: launch renames the node to {node["name"]}; docs use {NODE_NAMES[key]}')
        for name, value in parameters_given(node).items():
            assert name in declared[key], f'{key[1]} does not declare parameter {name!r}'
            assert parameter_type(value) == declared[key][name], (
                f'{key[1]}: {name}={value!r} has another type than the node declares')
        if key[1] == 'record':
            from pma_bag.record import parse_args
            assert parse_args(node['arguments']).output is not None


# ---------------------------------------------------------------------------------------
# Tests


@pytest.mark.integration
def test_driver_launch_defaults_and_manual_lifecycle(stand_ins, declared):
    default = launch('driver')
    assert [n['executable'] for n in default.nodes] == ['driver_node']
    driver = default.nodes[0]
    assert driver['lifecycle'] and driver['namespace'] == ''
    assert driver['parameters'][0] == (INSTALL / 'pma_driver' / 'share' / 'pma_driver'
                                       / 'config' / 'driver_node.yaml')
    assert parameters_given(driver)['port'] == '/dev/ttyACM0'
    assert parameters_given(driver)['autostart'] is True
    assert default.handlers == [], 'with autostart the node drives its own lifecycle'
    check_nodes_against_code(default, declared)

    # autostart:=false: launch configures the process when it starts, activates once inactive.
    managed = launch('driver', autostart='false', namespace='left', port='/dev/pma0')
    check_nodes_against_code(managed, declared)
    driver = managed.nodes[0]
    assert parameters_given(driver)['autostart'] is False
    assert parameters_given(driver)['port'] == '/dev/pma0'
    on_start, on_inactive = managed.handlers
    from lifecycle_msgs.msg import Transition
    assert type(on_start) is OnProcessStart
    assert on_start.kwargs['target_action'] is driver['action']
    configure = on_start.kwargs['on_start'][0].kwargs['event']
    assert configure.kwargs['transition_id'] == Transition.TRANSITION_CONFIGURE
    assert configure.kwargs['lifecycle_node_matcher'].args[0] is driver['action']
    assert type(on_inactive) is OnStateTransition
    assert on_inactive.kwargs['target_lifecycle_node'] is driver['action']
    assert (on_inactive.kwargs['start_state'], on_inactive.kwargs['goal_state']) == (
        'configuring', 'inactive'), 'activate only after configure, not after a deactivate'
    activate = on_inactive.kwargs['entities'][0].kwargs['event']
    assert activate.kwargs['transition_id'] == Transition.TRANSITION_ACTIVATE


@pytest.mark.integration
def test_model_launch_passes_refit_file_for_hot_reload(stand_ins, declared, tmp_path):
    default = launch('model')
    check_nodes_against_code(default, declared)
    given = parameters_given(default.nodes[0])
    assert given['params_file'] == '' and given['use_sim_time'] is False
    assert given['increasing.sigmoid.l0_m'] == pytest.approx(0.3006)

    refit = tmp_path / 'refit.yaml'
    with_refit = launch('model', refit_params_file=str(refit), use_sim_time='true',
                        namespace='right')
    check_nodes_against_code(with_refit, declared)
    node = with_refit.nodes[0]
    assert node['namespace'] == 'right'
    assert parameters_given(node)['params_file'] == str(refit)
    assert parameters_given(node)['use_sim_time'] is True


@pytest.mark.integration
def test_bringup_on_hardware_starts_driver_and_model_only(stand_ins, declared):
    launched = launch('bringup')
    check_nodes_against_code(launched, declared)
    assert sorted(n['executable'] for n in launched.nodes) == ['driver_node',
                                                               'length_controller',
                                                               'model_node']
    assert launched.processes == [], 'no fake_arduino without use_fake_arduino'
    driver = next(n for n in launched.nodes if n['executable'] == 'driver_node')
    assert parameters_given(driver)['port'] == '/dev/ttyACM0'
    assert launched.included == [], 'the nodes come from pma_bringup.node_set, one list'


@pytest.mark.integration
def test_bringup_two_simulated_muscles_do_not_share_port_bag_or_namespace(stand_ins, declared,
                                                                         tmp_path):
    from pma_bag.record import parse_args as recorder_args
    from pma_sim.fake_arduino import parse_args as fake_arduino_args

    seen = {}
    for side in ('left', 'right'):
        launched = launch('bringup', namespace=side, use_fake_arduino='true', record='true')
        check_nodes_against_code(launched, declared)
        nodes = {n['executable']: n for n in launched.nodes}
        assert sorted(nodes) == ['driver_node', 'length_controller', 'model_node', 'record']
        assert {n['namespace'] for n in nodes.values()} == {side}
        [fake] = launched.processes
        assert fake[0] == str(INSTALL / 'pma_sim' / 'lib' / 'pma_sim' / 'fake_arduino')
        fake_args = fake_arduino_args(fake[1:])        # fake_arduino's own parser accepts them
        port = parameters_given(nodes['driver_node'])['port']
        assert str(fake_args.link) == port and port.startswith('/tmp/')
        bag = recorder_args(nodes['record']['arguments']).output
        topics = parameters_given(nodes['record'])['topics']
        assert names.STATE in topics and '/diagnostics' in topics
        seen[side] = (port, bag.name)
    assert seen['left'][0] != seen['right'][0]
    assert seen['left'][1] != seen['right'][1] and 'left' in seen['left'][1]

    explicit = launch('bringup', use_fake_arduino='true', record='true',
                      port=str(tmp_path / 'dev'), bag_dir=str(tmp_path / 'bag'))
    nodes = {n['executable']: n for n in explicit.nodes}
    assert fake_arduino_args(explicit.processes[0][1:]).link == tmp_path / 'dev'
    assert recorder_args(nodes['record']['arguments']).output == tmp_path / 'bag'


@pytest.mark.integration
def test_bringup_live_starts_the_bridge_in_the_muscles_namespace(stand_ins, declared):
    assert 'foxglove_live' not in [n['executable'] for n in launch('bringup').nodes]
    launched = launch('bringup', live='true', namespace='left', use_fake_arduino='true')
    check_nodes_against_code(launched, declared)
    [bridge] = [n for n in launched.nodes if n['executable'] == 'foxglove_live']
    assert bridge['namespace'] == 'left'
    assert parameters_given(bridge) == {'host': '127.0.0.1', 'port': 8765}
    lab = launch('bringup', live='true', live_host='0.0.0.0', live_port='8766')
    check_nodes_against_code(lab, declared)
    [bridge] = [n for n in lab.nodes if n['executable'] == 'foxglove_live']
    assert parameters_given(bridge) == {'host': '0.0.0.0', 'port': 8766}
    with pytest.raises(ValueError, match='not a port'):
        launch('bringup', live='true', live_port='http')


def test_launch_arguments_refuse_values_outside_their_choices(stand_ins):
    with pytest.raises(AssertionError, match='not in'):
        launch('bringup', use_fake_arduino='yes')


def test_launch_files_parse_and_use_known_api():
    """ast fallback, independent of the stand-ins: imports and node literals."""
    known = {module: set(members) for module, members in STAND_INS.items()}
    known['lifecycle_msgs.msg'] = {'Transition'}
    from pma_bringup import node_set
    known['pma_bringup.node_set'] = {name for name in dir(node_set) if not name.startswith('_')}
    for path in LAUNCH_FILES.values():
        tree = ast.parse(path.read_text(), filename=str(path))
        functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert 'generate_launch_description' in functions, path
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert node.module in known, f'{path.name}: unexpected import {node.module}'
                for alias in node.names:
                    assert alias.name in known[node.module], (
                        f'{path.name}: {node.module}.{alias.name} is not known Jazzy API')
            if isinstance(node, ast.Call):
                literal = {k.arg: k.value.value for k in node.keywords
                           if isinstance(k.value, ast.Constant)}
                if 'package' in literal and 'executable' in literal:
                    exe = (INSTALL / literal['package'] / 'lib' / literal['package']
                           / literal['executable'])
                    assert exe.is_file(), f'{path.name}: {exe} not installed'


def test_setup_py_installs_launch_and_config_files():
    """The share/ paths the launch files resolve come from these data_files globs."""
    for package in ('pma_driver', 'pma_model'):
        setup = (ROOT / package / 'setup.py').read_text()
        assert "glob('launch/*.launch.py')" in setup and "glob('config/*.yaml')" in setup
        for launch_file in (ROOT / package / 'launch').glob('*.launch.py'):
            installed = INSTALL / package / 'share' / package / 'launch' / launch_file.name
            assert installed.is_file(), f'{installed} missing: run make setup'
    assert (INSTALL / 'pma_bag' / 'share' / 'pma_bag' / 'config' / 'record.yaml'
            ).is_file()


def test_stand_ins_catch_a_wrong_keyword(stand_ins):
    """The stand-ins are strict, so a misspelt keyword in a launch file fails here too."""
    with pytest.raises(TypeError, match='parameter'):
        Node(package='pma_driver', executable='driver_node', parameter=[])
    with pytest.raises(TypeError, match='namespace'):
        LifecycleNode(package='pma_driver', executable='driver_node', name='pma_driver')
    context = Context({})
    with pytest.raises(KeyError, match='never declared'):
        LaunchConfiguration('nope').perform(context)


# ---------------------------------------------------------------------------------------
# `pma up` starts what the launch file starts: both build from pma_bringup.node_set.


def up_processes(*flags: str) -> tuple[list[dict], list[list[str]]]:
    """The nodes (as the walker records them) and plain processes `pma up FLAGS` starts,
    read back from the argv it would execute."""
    from pma_cli import up
    from pma_cli.main import parser

    nodes, processes = [], []
    for spec, argv in up.commands(up.options_from_args(parser().parse_args(['up', *flags]))):
        exe = Path(argv[0])
        assert exe.is_file() and exe.parent.parent.parent.parent == INSTALL, exe
        package, executable = exe.parent.name, exe.name
        if '--ros-args' not in argv:
            assert not spec.ros
            processes.append(argv)
            continue
        split = argv.index('--ros-args')
        node = {'package': package, 'executable': executable, 'name': None, 'namespace': '',
                'parameters': [], 'arguments': argv[1:split]}
        rest = iter(argv[split + 1:])
        for flag in rest:
            value = next(rest)
            if flag == '--params-file':
                node['parameters'].append(Path(value))
            elif flag == '-p':
                name, _, text = value.partition(':=')
                node['parameters'].append({name: yaml.safe_load(text)})
            elif flag == '-r' and value.startswith('__node:='):
                node['name'] = value.removeprefix('__node:=')
            elif flag == '-r' and value.startswith('__ns:='):
                node['namespace'] = value.removeprefix('__ns:=')
            else:
                raise AssertionError(f'unexpected ROS argument {flag} {value}')
        nodes.append(node)
    return nodes, processes


def same_node(launched: dict, started: dict, read_files: bool) -> None:
    key = (launched['package'], launched['executable'])
    assert (started['package'], started['executable']) == key
    assert started['name'] == (launched['name'] or NODE_NAMES[key])
    assert started['namespace'].strip('/') == launched['namespace'].strip('/')
    assert started['arguments'] == launched['arguments']
    files = [Path(p).resolve() for p in launched['parameters'] if isinstance(p, Path)]
    assert [p.resolve() for p in started['parameters'] if isinstance(p, Path)] == files
    values = {k: v for p in launched['parameters'] if isinstance(p, dict) for k, v in p.items()}
    assert {k: v for p in started['parameters'] if isinstance(p, dict)
            for k, v in p.items()} == values, key
    if read_files:
        assert parameters_given(started) == parameters_given(launched), key


@pytest.mark.parametrize(('flags', 'arguments'), [
    ((), {}),
    (('--port', '/dev/pma0'), {'port': '/dev/pma0'}),
    (('--simulated',), {'use_fake_arduino': 'true'}),
    (('--simulated', '--namespace', 'left', '--port', '/tmp/pma_left_x', '--seed', '3',
      '--record', '/tmp/pma_bag_left', '--live', '--live-port', '8766'),
     {'use_fake_arduino': 'true', 'namespace': 'left', 'port': '/tmp/pma_left_x',
      'fake_arduino_seed': '3', 'record': 'true', 'bag_dir': '/tmp/pma_bag_left',
      'live': 'true', 'live_port': '8766'}),
    (('--no-control', '--live', '--live-host', '0.0.0.0', '--namespace', '/right'),
     {'control': 'false', 'live': 'true', 'live_host': '0.0.0.0', 'namespace': 'right'}),
    (('--no-driver', '--simulated', '--record', '/tmp/b'),         # the workstation's half
     {'driver': 'false', 'use_fake_arduino': 'true', 'record': 'true', 'bag_dir': '/tmp/b'}),
    (('--no-model', '--no-control'), {'model': 'false', 'control': 'false'}),   # the rig's
    (('--refit-params', '/tmp/refit.yaml', '--driver-params', '/tmp/rig.yaml',
      '--model-params', '/tmp/model.yaml', '--control-params', '/tmp/control.yaml',
      '--record', '/tmp/b', '--recorder-params', '/tmp/record.yaml'),
     {'refit_params_file': '/tmp/refit.yaml', 'driver_params_file': '/tmp/rig.yaml',
      'model_params_file': '/tmp/model.yaml', 'control_params_file': '/tmp/control.yaml',
      'record': 'true', 'bag_dir': '/tmp/b', 'recorder_params_file': '/tmp/record.yaml'}),
    (('--record', '/tmp/b', '--muscle', 'm2', '--load-kg', '1.5', '--supply-kpa', '600',
      '--operator', 'ada', '--note', 'new sleeve'),
     {'record': 'true', 'bag_dir': '/tmp/b', 'muscle': 'm2', 'load_kg': '1.5',
      'supply_kpa': '600', 'operator': 'ada', 'note': 'new sleeve'}),
])
def test_pma_up_starts_what_the_launch_file_starts(stand_ins, flags, arguments):
    """The same options give the same processes, names, namespaces, arguments, parameters
    files and values (the files the last case names do not exist: compared by path)."""
    launched = launch('bringup', **arguments)
    nodes, processes = up_processes(*flags)
    assert processes == launched.processes
    assert [n['executable'] for n in nodes] == [n['executable'] for n in launched.nodes]
    read_files = '--driver-params' not in flags
    for launched_node, started in zip(launched.nodes, nodes, strict=True):
        same_node(launched_node, started, read_files)


def test_the_launch_file_declares_every_experiment_argument_the_recorder_takes(stand_ins):
    """Its literal declarations (the docs tests read them) are pma_common.experiment's."""
    from pma_common.experiment import RECORDER_ARGUMENTS
    assert set(RECORDER_ARGUMENTS) <= set(launch('bringup').arguments)
