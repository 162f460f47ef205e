"""docker/ checked statically: no container engine runs on the development machines (the
docker client is there, but no daemon and no compose plugin), so nothing here builds an image.

What is checked: the Dockerfile's instructions, base image, COPY sources (present and not
excluded by its .dockerignore) and the commands it runs against what docker/README.md
documents; the entrypoint's shell syntax (bash -n); compose.yaml's services, profiles and
commands, whose executables and files must be ones the workspace installs (ros2_ws/install
stands in for the image's /ws/install) and whose arguments the executables' own parsers accept.
"""

from __future__ import annotations

import fnmatch
import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest
import yaml

from support.procs import INSTALL, ROOT

DOCKER = ROOT / 'docker'
KNOWN_INSTRUCTIONS = {'FROM', 'SHELL', 'ENV', 'WORKDIR', 'COPY', 'RUN', 'ENTRYPOINT', 'CMD',
                      'ARG', 'LABEL', 'USER', 'EXPOSE', 'VOLUME', 'HEALTHCHECK', 'STOPSIGNAL'}
PACKAGES = tuple(sorted(p.name for p in (ROOT / 'ros2_ws' / 'src').iterdir()))
# rosdep keys the Dockerfile skips, and the PyPI distribution that must replace each.
PIP_FOR_SKIPPED_KEY: dict[str, str] = {}


def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with continuation lines joined and comments dropped."""
    instructions, pending = [], ''
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith('#')):
            continue
        if pending and line.startswith('#'):
            continue
        if line.endswith('\\'):
            pending += line[:-1] + ' '
            continue
        full = pending + line
        pending = ''
        keyword, _, arguments = full.partition(' ')
        instructions.append((keyword.upper(), arguments.strip()))
    assert not pending, 'Dockerfile ends inside a continued line'
    return instructions


def ignored(relative: str, patterns: list[str]) -> bool:
    """Docker's rule: the last matching pattern wins; `!` re-includes; a parent's match counts."""
    parts = relative.split('/')
    candidates = ['/'.join(parts[:i]) for i in range(1, len(parts) + 1)]
    result = False
    for pattern in patterns:
        negate = pattern.startswith('!')
        glob = pattern[1:] if negate else pattern
        if any(fnmatch.fnmatch(c, glob) or fnmatch.fnmatch(c, glob.replace('**/', ''))
               for c in candidates):
            result = not negate
    return result


@pytest.fixture(scope='module')
def instructions():
    return dockerfile_instructions(DOCKER / 'Dockerfile')


@pytest.fixture(scope='module')
def compose():
    return yaml.safe_load((DOCKER / 'compose.yaml').read_text())


def run_commands(instructions) -> str:
    return '\n'.join(args for keyword, args in instructions if keyword == 'RUN')


def test_dockerfile_base_image_and_instructions(instructions):
    assert instructions[0] == ('FROM', 'ros:jazzy-ros-base')
    assert [k for k, _ in instructions if k == 'FROM'] == ['FROM'], 'one stage'
    unknown = {k for k, _ in instructions} - KNOWN_INSTRUCTIONS
    assert not unknown, f'unknown instructions {unknown}'
    workdir = [args for keyword, args in instructions if keyword == 'WORKDIR']
    assert workdir == ['/ws'], 'compose.yaml and entrypoint.sh expect the workspace at /ws'
    entrypoint = dict(instructions)['ENTRYPOINT']
    assert yaml.safe_load(entrypoint) == ['/entrypoint.sh']


def test_every_copy_source_exists_and_reaches_the_build_context(instructions):
    patterns = [line.strip() for line in
                (DOCKER / 'Dockerfile.dockerignore').read_text().splitlines()
                if line.strip() and not line.startswith('#')]
    copies = [args for keyword, args in instructions if keyword == 'COPY']
    sources = []
    for args in copies:
        words = [w for w in shlex.split(args) if not w.startswith('--')]
        sources += words[:-1]
    for source in sources:
        assert (ROOT / source).exists(), f'COPY source {source} missing'
        assert not ignored(source, patterns), f'{source} is excluded from the build context'
    for package in PACKAGES:
        assert package in sources and f'{package}/package.xml' in sources
    assert 'docker/entrypoint.sh' in sources
    # The context stays small: the development venv and build trees are never sent.
    for heavy in ('.venv', 'ros2_ws/install', 'runs', 'pma_driver/test/__pycache__'):
        assert ignored(heavy, patterns), f'{heavy} would be sent to the daemon'


def test_dockerfile_installs_dependencies_the_ros_way(instructions):
    commands = run_commands(instructions)
    assert re.search(r'rosdep install --from-paths src --ignore-src -y', commands)
    assert 'colcon build' in commands
    assert 'ros-${ROS_DISTRO}-rosbag2-storage-mcap' in commands
    # pip keys (mcap-ros2-support) need pip, and leave to install on Ubuntu 24.04's Python.
    assert commands.index('python3-pip') < commands.index('rosdep install')
    assert ('ENV', 'PIP_BREAK_SYSTEM_PACKAGES=1') in instructions
    pinned = [line for line in (ROOT / 'requirements' / 'python.txt').read_text().splitlines()
              if line.startswith(('mcap==', 'mcap-ros2-support=='))]
    assert len(pinned) == 2 and all(pin in commands for pin in pinned)
    skipped = re.findall(r'--skip-keys\s+(\S+)', commands)
    pins = {line.split('==')[0]: line for line in
            (ROOT / 'requirements' / 'python.txt').read_text().splitlines() if '==' in line}
    for key in skipped:
        distribution = PIP_FOR_SKIPPED_KEY[key]
        assert 'pip3 install' in commands and pins[distribution] in commands, (
            f'{key} is skipped in rosdep but {pins[distribution]} is not pip-installed')
        depends = '\n'.join((ROOT / p / 'package.xml').read_text() for p in PACKAGES)
        assert f'>{key}<' in depends, f'skip-key {key} is not a dependency of ours'


def test_readme_documents_the_commands_the_files_use(instructions):
    readme = (DOCKER / 'README.md').read_text()
    assert 'No container engine' in readme or 'no container engine' in readme.lower()
    for documented in ('rosdep install --from-paths', 'colcon build',
                       'rosbag2-storage-mcap', 'docker compose -f docker/compose.yaml build',
                       '--profile sim', '--profile hardware', "c 166:* rmw"):
        assert documented in readme, f'docker/README.md does not mention {documented!r}'
    commands = run_commands(instructions)
    assert 'rosdep install --from-paths' in commands and 'colcon build' in commands


def test_entrypoint_sources_ros_and_workspace_then_execs():
    entrypoint = DOCKER / 'entrypoint.sh'
    assert os.access(entrypoint, os.X_OK)
    subprocess.run(['bash', '-n', str(entrypoint)], check=True)
    text = entrypoint.read_text()
    assert 'source "/opt/ros/${ROS_DISTRO:-jazzy}/setup.bash"' in text
    assert 'source /ws/install/setup.bash' in text
    assert text.rstrip().endswith('exec "$@"')


def installed(path: str) -> Path:
    """The image's /ws/install/... as this machine's ros2_ws/install/..."""
    assert path.startswith('/ws/install/'), path
    return INSTALL / path.removeprefix('/ws/install/')


def test_compose_services_profiles_and_commands(compose):
    from pma_sim.fake_arduino import parse_args as fake_arduino_args

    services = compose['services']
    assert set(services) == {'driver', 'sim', 'model', 'recorder'}
    assert services['driver']['profiles'] == ['hardware']
    assert services['sim']['profiles'] == ['sim']
    assert 'profiles' not in services['model'] and 'profiles' not in services['recorder']
    for name, service in services.items():
        build = service['build']
        assert (DOCKER / build['context'] / build['dockerfile']).resolve() == (
            DOCKER / 'Dockerfile').resolve(), name
        assert service['network_mode'] == 'host' and service['stop_signal'] == 'SIGINT'
        command = service['command']
        words = shlex.split(command[2]) if command[:2] == ['bash', '-c'] else command
        executables = [w for w in words if re.fullmatch(r'/ws/install/\w+/lib/\w+/\w+', w)]
        assert executables, f'{name}: no installed executable in {command}'
        for word in words:
            if word.startswith('/ws/install/'):
                path = installed(word)
                assert path.exists(), f'{name}: {word} is not installed ({path})'
                if word in executables:
                    assert os.access(path, os.X_OK), f'{name}: {word} is not executable'
                if word.endswith('.yaml'):
                    assert list(yaml.safe_load(path.read_text())) == ['/**'], word

    driver = services['driver']
    [device] = driver['devices']
    assert device.split(':')[-1] == '/dev/ttyACM0'
    assert 'port:=/dev/ttyACM0' in driver['command']
    sim_words = shlex.split(services['sim']['command'][2])
    fake = sim_words.index('/ws/install/pma_sim/lib/pma_sim/fake_arduino')
    link = fake_arduino_args(sim_words[fake + 1:sim_words.index('&')]).link
    assert f'port:={link}' in sim_words, 'the sim driver must open the pty fake_arduino links'
    recorder = services['recorder']
    assert recorder['volumes'] == ['bags:/bags'] and recorder['working_dir'] == '/bags'
    assert 'bags' in compose['volumes']


def test_compose_documents_the_hotplug_variant():
    text = (DOCKER / 'compose.yaml').read_text()
    assert "device_cgroup_rules: ['c 166:* rmw']" in text and "'/dev:/dev'" in text


def test_ignore_rules_follow_docker_semantics():
    """The little matcher above, on the cases the real file relies on."""
    patterns = ['*', '!pma_driver', '**/__pycache__']
    assert ignored('.venv', patterns)
    assert not ignored('pma_driver/setup.py', patterns)
    assert ignored('pma_driver/pma_driver/__pycache__', patterns)
