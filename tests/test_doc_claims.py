"""What the README and the user guide say about the tree is what the tree does (issue 46).

Facts a reader acts on, read from their source instead of trusted: which make target installs
the AVR toolchain (the Makefile), how long the demo holds each pressure (demo.py's --hold-s),
and the bring-up launch file's arguments (its DeclareLaunchArgument calls, read with ast: no
`launch` here). Nothing is started.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from support.procs import ROOT

pytestmark = pytest.mark.in_process

README = ROOT / 'README.md'
GUIDE = ROOT / 'docs' / 'user-guide.md'
BRINGUP = ROOT / 'pma_bringup' / 'launch' / 'bringup.launch.py'
DEMO = ROOT / 'pma_bringup' / 'pma_bringup' / 'demo.py'


def paragraphs(path: Path) -> list[str]:
    """Text paragraphs (blank-line separated), each on one line."""
    return [' '.join(block.split()) for block in path.read_text(encoding='utf-8').split('\n\n')]


def sentences(path: Path) -> list[str]:
    return [s for p in paragraphs(path) for s in re.split(r'(?<=[.;])\s+(?=[A-Z`(])', p)]


def make_graph() -> dict[str, tuple[list[str], str]]:
    """target -> (prerequisites, recipe) of the Makefile."""
    graph, target = {}, None
    for line in (ROOT / 'Makefile').read_text().splitlines():
        rule = re.match(r'^([\w-]+):(?!=)\s*(.*)$', line)
        if rule:
            target = rule.group(1)
            graph[target] = (rule.group(2).split(), '')
        elif line.startswith('\t') and target:
            prerequisites, recipe = graph[target]
            graph[target] = (prerequisites, recipe + line + '\n')
        elif not line.strip() or line.startswith('#'):
            continue
        else:
            target = None
    return graph


def runs(graph, target: str, script: str) -> bool:
    """Whether `make target` runs `script`, itself or through a prerequisite."""
    prerequisites, recipe = graph[target]
    return script in recipe or any(runs(graph, p, script) for p in prerequisites)


def test_the_readme_names_the_make_target_that_installs_the_avr_toolchain():
    # It said the first run (make setup) installs the AVR toolchain and simavr; only
    # tools/firmware.sh does, which `make firmware` runs (and `make test` through it).
    graph = make_graph()
    installers = {t for t in graph if runs(graph, t, 'tools/firmware.sh')}
    assert installers == {'firmware', 'test'}, installers
    assert 'apt' in (ROOT / 'tools' / 'firmware.sh').read_text()
    setup = [line for line in (ROOT / 'tools' / 'setup.sh').read_text().splitlines()
             if not line.lstrip().startswith('#')]
    # (It watches pma_sim/simavr/ for changes to rebuild: a path, not an install.)
    installs_avr = re.compile(r'firmware\.sh|\bavr|gcc-avr|install.*simavr', re.IGNORECASE)
    assert not [line for line in setup if installs_avr.search(line)]
    about = [s for s in sentences(README) if 'AVR toolchain' in s and 'install' in s]
    assert about, 'the README does not say what installs the AVR toolchain'
    for sentence in about:
        named = set(re.findall(r'`make (\w+)`', sentence))
        assert named & installers, f'names no target that installs it: {sentence}'
        for target in named - installers:         # said, then, not to install it
            assert re.search(r'\bneither\b|\bnot\b', sentence), \
                f'`make {target}` does not install the AVR toolchain: {sentence}'
        assert 'first run' not in sentence or re.search(r'\bneither\b|\bnot\b', sentence), \
            sentence


def demo_default_hold_s() -> float:
    tree = ast.parse(DEMO.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'attr', '') == 'add_argument' \
                and node.args and getattr(node.args[0], 'value', None) == '--hold-s':
            return next(k.value.value for k in node.keywords if k.arg == 'default')
    raise AssertionError('demo.py has no --hold-s')


def test_the_readme_gives_the_demos_hold_time():
    # It called the demo's staircase "the paper's experiment", held 1 s, not the 5 s of the
    # documented full run.
    make_demo = next(p for p in paragraphs(README) if p.startswith('What `make demo` does'))
    held = re.findall(r'each held ([\d.]+) s', make_demo)
    assert held == [f'{demo_default_hold_s():g}'], make_demo
    assert "paper's experiment" not in make_demo


def declared_arguments(path: Path) -> list[str]:
    """The names of a launch file's DeclareLaunchArgument('name', ...) calls."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', '') == \
                'DeclareLaunchArgument':
            first = node.args[0] if node.args else None
            assert isinstance(first, ast.Constant), f'{path.name}: an argument name not a literal'
            names.append(first.value)
    return names


def guide_bringup_arguments() -> list[str]:
    paragraph = next(p for p in paragraphs(GUIDE)
                     if p.startswith('Arguments of `bringup.launch.py`'))
    return [name for name in re.findall(r'`([^`]+)`', paragraph)
            if re.fullmatch(r'[a-z][a-z0-9_]*', name)]


def test_the_user_guide_lists_every_bringup_argument():
    # `control` and `control_params_file` were missing from the guide's list.
    declared = declared_arguments(BRINGUP)
    assert len(declared) >= 10 and 'control' in declared, declared
    listed = guide_bringup_arguments()
    assert sorted(set(listed)) == sorted(declared), (
        f'in the launch file, not the guide: {sorted(set(declared) - set(listed))}; '
        f'in the guide, not the launch file: {sorted(set(listed) - set(declared))}')


def test_the_user_guide_says_what_the_plain_bringup_starts():
    # "driver + model": the bring-up also starts the length controller (control:=true).
    source = BRINGUP.read_text()
    control_default = re.search(r"'control', default_value='(\w+)'", source)
    assert control_default, 'bringup.launch.py: no control argument with a literal default'
    plain = next(line for line in GUIDE.read_text().splitlines()
                 if re.match(r'ros2 launch pma_bringup bringup\.launch\.py port:=\S+\s+#', line))
    comment = plain.split('#', 1)[1]
    assert ('controller' in comment) == (control_default.group(1) == 'true'), plain
