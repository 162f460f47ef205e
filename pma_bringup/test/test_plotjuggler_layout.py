"""The PlotJuggler layout (plotjuggler/pma_testbed.xml) is well-formed and names only what exists.

Checked without PlotJuggler (none here): the XML has the shape PlotJuggler's "Save layout"
writes (root, tabbed_widget of main_window, tabs, nested DockSplitters whose count and sizes
match their children, DockAreas holding one plot of a known mode); the loop is an XY curve of
values from one message (PlotJuggler pairs x and y by time: two topics would not pair); every
series name, `/topic/field`, is a topic a node of this project publishes (found in the code, as
test_layout.py finds them for the Foxglove layout) and a numeric field of that topic's type in
pma_interfaces/msg/*.msg, parsed here from the .msg text; the streaming and bag plugins select
exactly the layout's topics.
"""

from __future__ import annotations

import functools
import importlib.util
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.in_process

PACKAGE = Path(__file__).resolve().parents[1]
ROOT = PACKAGE.parent
LAYOUT = PACKAGE / 'plotjuggler' / 'pma_testbed.xml'
MSG_DIR = ROOT / 'pma_interfaces' / 'msg'
NUMERIC = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
           'int32', 'uint32', 'int64', 'uint64'}
MODES = {'TimeSeries', 'XYPlot'}
PLUGINS = {'ROS2 Topic Subscriber', 'DataLoad ROS2 bags'}


def parse_msg(text: str) -> dict[str, str]:
    """{field: type} of a .msg text: comments and constants (NAME=value) left out."""
    fields = {}
    for raw in text.splitlines():
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        type_name, rest = line.split(None, 1)
        if '=' in rest:
            continue
        fields[rest.split()[0]] = type_name
    return fields


def interfaces() -> dict[str, dict[str, str]]:
    """{'pma_interfaces/msg/PmaState': {field: type}} from the .msg files."""
    return {f'pma_interfaces/msg/{path.stem}': parse_msg(path.read_text())
            for path in sorted(MSG_DIR.glob('*.msg'))}


@functools.cache
def published_topics() -> dict[str, str]:
    spec = importlib.util.spec_from_file_location(
        'pma_layout_checks', PACKAGE / 'test' / 'test_layout.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.published_topics()


def layout() -> ET.Element:
    return ET.parse(LAYOUT).getroot()


def plots(root: ET.Element) -> list[tuple[str, ET.Element]]:
    return [(area.get('name'), plot) for area in root.iter('DockArea')
            for plot in area.findall('plot')]


def series_names(root: ET.Element) -> list[str]:
    """Every series the layout plots: time series names, XY curves' x and y."""
    names = []
    for _, plot in plots(root):
        for curve in plot.findall('curve'):
            if plot.get('mode') == 'XYPlot':
                names += [curve.get('curve_x'), curve.get('curve_y')]
            else:
                names.append(curve.get('name'))
    return names


def split_series(name: str, topics: dict[str, str]) -> tuple[str, list[str]]:
    """'/pma/state/length_m' -> ('/pma/state', ['length_m']): the longest published topic."""
    matches = [t for t in topics if name.startswith(t + '/')]
    assert matches, f'{name}: no node of this project publishes its topic'
    topic = max(matches, key=len)
    return topic, name[len(topic) + 1:].split('/')


def resolve(name: str, topics: dict[str, str], types: dict[str, dict[str, str]]) -> str:
    """The leaf type of a series, field by field through the interface definitions."""
    topic, parts = split_series(name, topics)
    current = topics[topic]
    for part in parts:
        assert current in types, f'{name}: {current} is not a pma_interfaces message'
        fields = types[current]
        assert part in fields, f'{name}: {current} has no field {part!r} (it has {list(fields)})'
        kind = fields[part]
        if '/' in kind or kind[:1].isupper():       # a nested message: pkg/Type or Type
            package, _, short = kind.rpartition('/')
            current = f'{package or "pma_interfaces"}/msg/{short}'
        else:
            current = kind
    return current


def test_the_layout_is_shaped_as_plotjuggler_saves_it():
    root = layout()
    assert root.tag == 'root'
    widget = root.find('tabbed_widget')
    assert widget is not None and widget.get('parent') == 'main_window'
    tabs = widget.findall('Tab')
    assert tabs and all(int(t.get('containers')) == len(t.findall('Container')) for t in tabs)
    for splitter in root.iter('DockSplitter'):
        children = [c for c in splitter if c.tag in ('DockSplitter', 'DockArea')]
        sizes = [float(s) for s in splitter.get('sizes').split(';')]
        assert int(splitter.get('count')) == len(children) == len(sizes)
        assert abs(sum(sizes) - 1) < 1e-6 and splitter.get('orientation') in ('|', '-')
    for name, plot in plots(root):
        assert plot.get('mode') in MODES, name
        assert plot.get('style') in ('Lines', 'Dots', 'LinesAndDots', 'Sticks'), name
        assert plot.findall('curve'), f'{name}: no curve'
        for curve in plot.findall('curve'):
            assert re.fullmatch(r'#[0-9a-fA-F]{6}', curve.get('color')), name
            xy = curve.get('curve_x') is not None, curve.get('curve_y') is not None
            assert xy == ((True, True) if plot.get('mode') == 'XYPlot' else (False, False))
        assert re.search(r'\[[^\]]+\]', name), f'{name}: its title gives no unit'
    assert {p.get('ID') for p in root.find('Plugins')} == PLUGINS


def test_the_loop_is_an_xy_curve_of_pressure_and_length_from_one_message():
    loops = [plot for _, plot in plots(layout()) if plot.get('mode') == 'XYPlot']
    assert len(loops) == 1
    curves = {(c.get('curve_x'), c.get('curve_y')): c.get('name')
              for c in loops[0].findall('curve')}
    assert set(curves) == {('/pma/state/gauge_pressure_pa', '/pma/state/length_m'),
                           ('/pma/prediction/gauge_pressure_pa',
                            '/pma/prediction/predicted_length_m')}
    for (x, y), name in curves.items():
        topic = x.rsplit('/', 1)[0]
        assert y.rsplit('/', 1)[0] == topic, 'x and y of a loop come from one message'
        assert name == f'{topic}/[{x.rsplit("/", 1)[1]};{y.rsplit("/", 1)[1]}]'


def test_time_plots_show_pressure_length_prediction_and_the_controllers_target():
    names = set(series_names(layout()))
    for wanted in ('/pma/state/gauge_pressure_pa', '/pma/state/length_m',
                   '/pma/prediction/predicted_length_m', '/pma/control_state/target_length_m',
                   '/pma/control_state/setpoint_length_m'):
        assert wanted in names


def test_every_series_is_a_numeric_field_of_a_published_topic():
    topics = published_topics()
    types = interfaces()
    assert 'pma_interfaces/msg/PmaState' in types and types['pma_interfaces/msg/PmaState'][
        'length_m'] == 'float64', 'the .msg parser reads the interface files'
    named = set()
    for name in series_names(layout()):
        leaf = resolve(name, topics, types)
        assert leaf in NUMERIC, f'{name} is a {leaf}, not a number'
        named.add(split_series(name, topics)[0])
    for plugin in layout().find('Plugins'):
        selected = plugin.find('selected_topics').get('value').split(';')
        assert set(selected) == named, plugin.get('ID')
        assert plugin.find('use_header_stamp').get('value') == 'true', (
            'time plots use the samples\' header stamps, as the Foxglove layout does')
    for topic in named:
        assert 'header' in types[topics[topic]], f'{topic} has no header stamp'


def test_a_wrong_field_or_topic_is_caught():
    topics = published_topics()
    types = interfaces()
    with pytest.raises(AssertionError, match='has no field'):
        resolve('/pma/state/length_mm', topics, types)
    with pytest.raises(AssertionError, match='no node of this project publishes'):
        resolve('/pma/stat/length_m', topics, types)
    assert resolve('/pma/state/header', topics, types) == 'std_msgs/msg/Header'
