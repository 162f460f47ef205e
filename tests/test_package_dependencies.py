"""Each package.xml says exactly what its package needs, in keys rosdep can resolve.

Every dependency must be a package of this workspace, a ROS 2 Jazzy package or a rosdep key
recorded (with where it was looked up) in support/dependency_keys.yaml; every module the
package's code, launch files and tests import must be covered by one of its dependencies; and
every run dependency must be used. So `rosdep install --from-paths src` installs what the
code imports, and nothing the code stopped using.
"""

from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from support.procs import ROOT

SOURCES = ROOT / 'ros2_ws' / 'src'
PACKAGES = {link.name: link.resolve() for link in sorted(SOURCES.iterdir())}
KEYS = yaml.safe_load((ROOT / 'tests' / 'support' / 'dependency_keys.yaml').read_text())
RUN_TAGS = ('depend', 'exec_depend', 'build_export_depend')
ALL_TAGS = (*RUN_TAGS, 'build_depend', 'buildtool_depend', 'test_depend')
ENTRY_POINT = re.compile(r'^([a-z_][a-z0-9_]*)\.[\w.]+:\w+$')


def dependencies(package: str, tags=ALL_TAGS) -> set[str]:
    root = ET.parse(PACKAGES[package] / 'package.xml').getroot()
    return {element.text.strip() for tag in tags for element in root.iter(tag)}


def is_python(package: str) -> bool:
    return (PACKAGES[package] / 'setup.py').is_file()


def imported_modules(files: list[Path]) -> set[str]:
    """Top-level modules imported, plus packages named in 'pkg.module:function' entry strings."""
    modules = set()
    for path in files:
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module.split('.')[0])
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                match = ENTRY_POINT.match(node.value)
                if match:
                    modules.add(match.group(1))
    return modules


def package_strings(files: list[Path]) -> set[str]:
    """Quoted names in launch files: package='pma_driver', FindPackageShare('pma_model')."""
    names = set()
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                names.add(node.value)
    return names


def code_files(package: str) -> list[Path]:
    root = PACKAGES[package]
    return sorted((root / package).rglob('*.py')) + sorted((root / 'launch').glob('*.py'))


def files_of_tests(package: str) -> list[Path]:
    return sorted((PACKAGES[package] / 'test').rglob('*.py'))


def provider(module: str, package: str) -> str | None:
    """The dependency that provides `module`; None for the standard library and for the
    documented pip-only modules of `package` (dependency_keys.yaml: pip_only)."""
    if module in sys.stdlib_module_names or module == '__future__':
        return None
    pip_only = KEYS['pip_only'].get(module)
    if pip_only is not None:
        assert package in pip_only['packages'], (
            f'{package} imports {module}, which no rosdep key provides; if it must, add '
            f'{package} to pip_only.{module}.packages in dependency_keys.yaml (and the comment '
            'to its package.xml)')
        return None
    if module in PACKAGES or module in KEYS['jazzy_packages']:
        return module
    if module in KEYS['modules']:
        return KEYS['modules'][module]
    raise AssertionError(f'import {module}: which rosdep key provides it? Add it to '
                         'tests/support/dependency_keys.yaml (look the key up in rosdistro)')


@pytest.mark.parametrize('package', sorted(PACKAGES))
def test_every_dependency_is_resolvable(package):
    known = set(PACKAGES) | set(KEYS['jazzy_packages']) | set(KEYS['rosdep_keys'])
    unknown = dependencies(package) - known
    assert not unknown, (f'{package}/package.xml names {sorted(unknown)}: neither a package '
                         'of this workspace, a Jazzy package nor a recorded rosdep key')


@pytest.mark.parametrize('package', sorted(p for p in PACKAGES if is_python(p)))
def test_every_import_is_covered_and_every_run_dependency_used(package):
    run_deps = dependencies(package, RUN_TAGS)
    test_deps = dependencies(package, ('test_depend',)) | run_deps
    used = set()
    for module in imported_modules(code_files(package)) - {package}:
        needed = provider(module, package)
        if needed is not None:
            assert needed in run_deps, (f'{package} imports {module}, but its package.xml '
                                        f'has no exec_depend on {needed}')
            used.add(needed)
    local = {path.stem for path in files_of_tests(package)}     # one test importing another
    for module in imported_modules(files_of_tests(package)) - {package, 'conftest'} - local:
        needed = provider(module, package)
        if needed is not None:
            assert needed in test_deps, (f"{package}'s tests import {module}, but its "
                                         f'package.xml has no test_depend on {needed}')
    launched = package_strings(sorted((PACKAGES[package] / 'launch').glob('*.py')))
    unused = run_deps - used - launched - set(KEYS['used_without_import'].get(package, {}))
    assert not unused, f'{package}/package.xml depends on {sorted(unused)} but never uses it'


@pytest.mark.parametrize('module', sorted(KEYS['pip_only']))
def test_pip_only_modules_are_pinned_installed_and_documented(module):
    """What rosdep cannot install, `make setup` (both modes) and the image install instead."""
    entry = KEYS['pip_only'][module]
    distribution = entry['distribution']
    assert entry['reason'].strip()
    pins = set()
    for requirements in ('python.txt', 'python-system.txt'):
        lines = (ROOT / 'requirements' / requirements).read_text().splitlines()
        found = [line for line in lines if line.startswith(f'{distribution}==')]
        assert len(found) == 1, f'requirements/{requirements} must pin {distribution} exactly'
        pins.update(found)
    assert len(pins) == 1, f'the two requirements files pin {distribution} differently: {pins}'
    pin = pins.pop()
    # A RUN instruction continues over lines that end in a backslash: read it as one line.
    dockerfile = (ROOT / 'docker' / 'Dockerfile').read_text().replace('\\\n', ' ').splitlines()
    assert any('pip3 install' in line and pin in line.split() for line in dockerfile), (
        f'docker/Dockerfile does not pip-install {pin}')
    for package in entry['packages']:
        text = (PACKAGES[package] / 'package.xml').read_text()
        assert distribution in text, f'{package}/package.xml does not say why {distribution} ' \
                                     'is not one of its dependencies'
        assert f'>{distribution}<' not in text, f'{distribution} is not a rosdep key'


def test_the_interface_package_builds_with_what_it_declares():
    declared = dependencies('pma_interfaces')
    cmake = (PACKAGES['pma_interfaces'] / 'CMakeLists.txt').read_text()
    for found in re.findall(r'find_package\((\w+) REQUIRED\)', cmake):
        assert found in declared, f'CMakeLists.txt finds {found}, package.xml lacks it'
    for field_type in {line.split()[0].split('/')[0]
                       for path in PACKAGES['pma_interfaces'].rglob('*.*')
                       if path.suffix in ('.msg', '.srv', '.action')
                       for line in path.read_text().splitlines()
                       if '/' in line.split('#')[0].split(' ')[0]}:
        assert field_type in declared, f'an interface uses {field_type}, package.xml lacks it'


def test_no_package_reads_another_packages_share_against_the_dependencies():
    """A launch file may find only packages its own package.xml depends on."""
    for package, root in PACKAGES.items():
        if not is_python(package):
            continue
        found = set()
        for path in (root / 'launch').glob('*.py'):
            found |= set(re.findall(r"FindPackage(?:Share|Prefix)\('(\w+)'\)", path.read_text()))
        missing = found - {package} - dependencies(package, RUN_TAGS)
        assert not missing, f'{package} launch files use {sorted(missing)} without depending'


def test_every_packages_tests_are_collected_by_make_test():
    """A package whose test/ is missing from pytest's testpaths has tests nobody runs."""
    import tomllib

    testpaths = tomllib.loads((ROOT / 'pyproject.toml').read_text())['tool']['pytest'][
        'ini_options']['testpaths']
    collected = {(ROOT / path).resolve() for path in testpaths}
    for package, source in PACKAGES.items():
        if (source / 'test').is_dir():
            assert (source / 'test').resolve() in collected, (
                f'{package}/test is not in pyproject.toml testpaths: make test skips it')


# --- Directions between the packages (docs/development.md, "Where things live") --------------

# pma_driver is the serial driver: pma_bringup starts it (and reads its config). Everything else
# reaches the device through ROS; the plain logic the driver shares with its clients (the
# protocol, calibrations, the parameter table, sweep plans, setpoint checks) is pma_common's,
# so the CLI needs no driver and the driver's tests can run against pma_sim without a cycle.
DRIVER_IMPORTERS = {'pma_driver', 'pma_bringup'}
BENCH = sorted((ROOT / 'bench').glob('*.py'))
TESTS_ON_PATH = re.compile(r'sys\.path\.(insert|append)\(.*tests')


def python_packages() -> list[str]:
    return [package for package in sorted(PACKAGES) if is_python(package)]


def importers_of(module: str, files: list[Path]) -> list[str]:
    return [str(path.relative_to(ROOT)) for path in files if module in imported_modules([path])]


def test_only_the_driver_and_its_bringup_import_pma_driver():
    for package in set(python_packages()) - DRIVER_IMPORTERS:
        files = code_files(package) + files_of_tests(package)
        assert not importers_of('pma_driver', files), (
            f'{package} imports pma_driver: {importers_of("pma_driver", files)}')
    assert not importers_of('pma_driver', BENCH), 'bench/ imports pma_driver'


def test_nothing_in_the_packages_or_bench_imports_from_tests():
    """tests/support is test plumbing: what a bench or a package needs lives in a package."""
    files = [path for package in python_packages()
             for path in code_files(package) + files_of_tests(package)] + BENCH
    for module in ('support', 'helpers'):
        assert not importers_of(module, files), f'{importers_of(module, files)} import {module}'
    on_path = [str(path.relative_to(ROOT)) for path in files
               if TESTS_ON_PATH.search(path.read_text())]
    assert not on_path, f'{on_path} put tests/ on sys.path'


def test_the_model_does_not_import_the_simulator():
    """pma_sim depends on pma_model (Bouc-Wen, the scoring harness), not the reverse."""
    assert not importers_of('pma_sim', code_files('pma_model') + files_of_tests('pma_model'))
    assert 'pma_sim' not in dependencies('pma_model')


def test_the_dependencies_have_no_cycle():
    """colcon orders the packages by every dependency, test ones too, and refuses a cycle."""
    graph = {package: dependencies(package) & set(PACKAGES) for package in PACKAGES}
    done: set[str] = set()

    def visit(package: str, path: tuple[str, ...]) -> None:
        assert package not in path, f'dependency cycle: {" -> ".join((*path, package))}'
        if package in done:
            return
        for needed in sorted(graph[package]):
            visit(needed, (*path, package))
        done.add(package)

    for package in sorted(graph):
        visit(package, ())
