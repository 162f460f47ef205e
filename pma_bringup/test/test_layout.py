"""The Foxglove layout (foxglove/pma_testbed.json) is well-formed and names only what exists.

Checked without the app (none runs here): the file is a layout as Foxglove's "Export..." writes
it and "Import from file..." reads it (configById, layout, globalVariables, userNodes,
playbackConfig); every panel's settings are ones that panel has, with allowed values, as the
foxglove-sdk's own layout model (foxglove.layouts) describes them; every topic is one a node of
this project publishes (found in the code), and every message path resolves, field by field,
against the `ros2msg` schema of that topic's type as the live bridge advertises it and rosbag2
stores it (pma_bag.schemas), parsed by rosbags, an independent parser; plotted values are
numbers and axes and series say their unit. tests/test_foxglove_live.py checks the same topics
against what the running nodes advertise through the bridge.
"""

from __future__ import annotations

import ast
import json
import re
import typing
from dataclasses import fields
from pathlib import Path

import foxglove.layouts as fl
import pytest
from rosbags.interfaces import Nodetype
from rosbags.typesys import get_types_from_msg

from pma_bag.schemas import message_definition
from pma_common import names

pytestmark = pytest.mark.in_process

PACKAGE = Path(__file__).resolve().parents[1]
ROOT = PACKAGE.parent
LAYOUT = PACKAGE / 'foxglove' / 'pma_testbed.json'
# Panel type as the app stores it -> the SDK's model of its settings, and of nested items.
PANELS = {
    'Plot': (fl.PlotConfig, {'paths': fl.PlotSeries, 'xAxisPath': fl.PlotXAxisPath}),
    'StateTransitions': (fl.StateTransitionsConfig, {'paths': fl.StateTransitionsSeries}),
    'RawMessages': (fl.RawMessagesConfig, {}),
    'DiagnosticSummary': (fl.DiagnosticsSummaryConfig, {}),
    'DiagnosticStatusPanel': (fl.DiagnosticsDetailConfig, {}),
}
TITLE_KEY = 'foxglovePanelTitle'     # where the app keeps a panel's title in an exported file
NUMERIC = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
           'int32', 'uint32', 'int64', 'uint64'}
UNIT = re.compile(r'\[[^\]]+\]')


def camel_to_snake(name: str) -> str:
    return re.sub(r'(?<!^)(?=[A-Z])', '_', name).lower()


def check_settings(settings: dict, model: type, nested: dict, where: str) -> list[str]:
    """Keys the SDK's model has, values within its Literal choices; nested items recursively."""
    errors = []
    names = {f.name for f in fields(model)}
    hints = typing.get_type_hints(model)
    for key, value in settings.items():
        if key == TITLE_KEY and where.count('.') == 0:
            continue
        name = camel_to_snake(key)
        if name not in names:
            errors.append(f'{where}.{key}: not a setting of {model.__name__}')
            continue
        choices = [arg for arg in typing.get_args(hints[name])
                   if typing.get_origin(arg) is typing.Literal]
        allowed = [v for literal in choices for v in typing.get_args(literal)]
        if allowed and value not in allowed:
            errors.append(f'{where}.{key}: {value!r} is not one of {allowed}')
        if key in nested:
            items = value if isinstance(value, list) else [value]
            for index, item in enumerate(items):
                errors += check_settings(item, nested[key], {}, f'{where}.{key}[{index}]')
    return errors


def topic_name(argument: ast.expr) -> str | None:
    """A topic argument's name: a literal, or a constant of pma_common.names."""
    if isinstance(argument, ast.Constant):
        return argument.value
    if (isinstance(argument, ast.Attribute) and isinstance(argument.value, ast.Name)
            and argument.value.id == 'names'):
        return getattr(names, argument.attr)
    return None


def published_topics() -> dict[str, str]:
    """{'/pma/state': 'pma_interfaces/msg/PmaState', ...}: what the project's nodes publish."""
    found = {}
    for path in sorted(ROOT.glob('pma_*/pma_*/**/*.py')):
        tree = ast.parse(path.read_text(), filename=str(path))
        classes = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or '').endswith('.msg'):
                package = node.module.split('.')[0]
                for alias in node.names:
                    classes[alias.asname or alias.name] = f'{package}/msg/{alias.name}'
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ('create_publisher', 'create_lifecycle_publisher')
                    and len(node.args) >= 2 and isinstance(node.args[0], ast.Name)
                    and node.args[0].id in classes):
                topic = topic_name(node.args[1])
                if topic is not None:
                    found['/' + topic.lstrip('/')] = classes[node.args[0].id]
    return found


def resolve(path: str, schemas: dict[str, tuple[str, str]]) -> tuple[str, str]:
    """'/pma/state.header.stamp' -> (topic, leaf type: a primitive name or 'pkg/msg/Type').

    `schemas`: {topic: (type name, ros2msg schema text)}, the way Foxglove knows a topic.
    """
    topic, _, rest = path.partition('.')
    assert topic in schemas, f'{path}: no node of this project publishes {topic}'
    type_name, text = schemas[topic]
    types = get_types_from_msg(text, type_name)
    current = type_name
    for part in filter(None, rest.split('.')):
        assert re.fullmatch(r'[A-Za-z_][A-Za-z0-9_]*', part), (
            f'{path}: {part!r} is not a plain field name (the layout uses only those)')
        assert current in types, f'{path}: {current} is a primitive, it has no field {part!r}'
        members = dict(types[current][1])
        assert part in members, (f'{path}: {current} has no field {part!r} '
                                 f'(it has {", ".join(members)})')
        kind, detail = members[part]
        if kind == Nodetype.NAME:
            current = detail
        elif kind == Nodetype.BASE:
            current = detail[0]
        else:
            raise AssertionError(f'{path}: {part} is an array; the layout plots scalars only')
    return topic, current


def check_paths(layout: dict, schemas: dict[str, tuple[str, str]]) -> set[str]:
    """Every message path of the layout resolves, to a number where plotted; the topics."""
    named = set()
    for panel_id, path, series in layout_paths(layout):
        topic, leaf = resolve(path, schemas)
        named.add(topic)
        panel_type = panel_id.split('!')[0]
        if panel_type in ('Plot', 'StateTransitions'):
            assert leaf in NUMERIC, f'{panel_id}: {path} is a {leaf}, not a number'
        if panel_type.startswith('Diagnostic'):
            assert leaf == 'diagnostic_msgs/msg/DiagnosticArray', f'{panel_id}: {path}'
        if series.get('timestampMethod') == 'headerStamp':
            stamp = resolve(f'{topic}.header.stamp', schemas)[1]
            assert stamp == 'builtin_interfaces/msg/Time', f'{panel_id}: {path} has no header'
    return named


def layout_paths(layout: dict) -> list[tuple[str, str, dict]]:
    """(panel id, message path, the series or settings it belongs to) for every path."""
    found = []
    for panel_id, settings in layout['configById'].items():
        for series in settings.get('paths', []):
            found.append((panel_id, series['value'], series))
            if 'xValuePath' in series:
                found.append((panel_id, series['xValuePath'], series))
        if 'xAxisPath' in settings:
            found.append((panel_id, settings['xAxisPath']['value'], settings))
        for key in ('topicPath', 'topicToRender'):
            if key in settings:
                found.append((panel_id, settings[key], settings))
    return found


@pytest.fixture(scope='module')
def layout() -> dict:
    return json.loads(LAYOUT.read_text())


@pytest.fixture(scope='module')
def topics() -> dict[str, str]:
    return published_topics()


@pytest.fixture(scope='module')
def schemas(topics) -> dict[str, tuple[str, str]]:
    """What the live bridge would advertise for each published topic (type, ros2msg text)."""
    return {topic: (type_name, message_definition(type_name))
            for topic, type_name in topics.items()}


def leaves(tree) -> list[str]:
    if isinstance(tree, str):
        return [tree]
    assert set(tree) <= {'first', 'second', 'direction', 'splitPercentage'}, tree
    assert tree['direction'] in ('row', 'column')
    assert 0 < tree.get('splitPercentage', 50) < 100
    return leaves(tree['first']) + leaves(tree['second'])


def test_the_file_is_an_exported_layout_whose_panels_all_show(layout):
    assert set(layout) == {'configById', 'layout', 'globalVariables', 'userNodes',
                           'playbackConfig'}
    shown = leaves(layout['layout'])
    assert sorted(shown) == sorted(layout['configById']), 'panels configured but not shown'
    assert len(set(shown)) == len(shown)
    for panel_id in shown:
        panel_type, bang, _ = panel_id.partition('!')
        assert bang and panel_type in PANELS, f'{panel_id}: unknown panel type'


def test_every_panel_setting_is_one_the_panel_has(layout):
    errors = []
    for panel_id, settings in layout['configById'].items():
        model, nested = PANELS[panel_id.split('!')[0]]
        errors += check_settings(settings, model, nested, panel_id)
    assert not errors, '\n'.join(errors)


def test_the_checker_refuses_a_wrong_setting():
    """check_settings is not vacuous: a misspelt key and an unknown choice are reported."""
    model, nested = PANELS['Plot']
    errors = check_settings({'xAxisVal': 'pressure', 'pathz': [],
                             'paths': [{'value': '/x', 'timestampMethod': 'clock'}]},
                            model, nested, 'Plot!t')
    assert len(errors) == 3, errors


def test_the_project_publishes_what_the_layout_asks_for(topics):
    assert topics['/pma/state'] == 'pma_interfaces/msg/PmaState'
    assert topics['/pma/prediction'] == 'pma_interfaces/msg/PmaPrediction'
    assert topics['/pma/control_state'] == 'pma_interfaces/msg/ControlState'
    assert topics['/diagnostics'] == 'diagnostic_msgs/msg/DiagnosticArray'


def test_every_message_path_resolves_against_the_interface_definitions(layout, schemas):
    assert len(layout_paths(layout)) > 20
    named = check_paths(layout, schemas)
    assert {'/pma/state', '/pma/prediction', '/pma/control_state', '/diagnostics'} <= named


def test_resolve_refuses_what_does_not_exist(schemas):
    with pytest.raises(AssertionError, match='has no field'):
        resolve('/pma/state.length_cm', schemas)
    with pytest.raises(AssertionError, match='no node'):
        resolve('/pma/lenght.data', schemas)
    with pytest.raises(AssertionError, match='primitive'):
        resolve('/pma/state.length_m.value', schemas)


def test_the_loop_is_length_against_pressure_measured_and_model(layout):
    loop = layout['configById']['Plot!loop']
    assert loop['xAxisVal'] == 'custom' and loop['timeRange'] == 'all'
    series = {s['value']: s.get('xValuePath') for s in loop['paths']}
    assert series == {'/pma/state.length_m': '/pma/state.gauge_pressure_pa',
                      '/pma/prediction.predicted_length_m': '/pma/prediction.gauge_pressure_pa'}


def test_plots_say_their_units(layout):
    for panel_id, settings in layout['configById'].items():
        if not panel_id.startswith('Plot!'):
            continue
        for key in ('yAxisLabel', 'xAxisLabel'):
            if key in settings or settings.get('xAxisVal') == 'custom':
                assert UNIT.search(settings.get(key, '')), f'{panel_id}.{key} has no [unit]'
        for series in settings['paths']:
            assert UNIT.search(series.get('label', '')), f'{panel_id}: {series} has no [unit]'
