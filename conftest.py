"""Test session setup shared by every test directory.

Each pytest session, and each test module in it, gets its own random ROS_DOMAIN_ID and
localhost-only discovery, so parallel runs on one machine never see each other's graphs. The
environment must come from `tools/env.sh` (the Makefile does this).
"""

import os
import random
import signal
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

ROOT = Path(__file__).resolve().parent

# The in_process tests run at nice 19 beside the process tests (tools/test.sh) and can wait
# seconds for the CPU: Hypothesis's wall-clock checks (a deadline per example, the too_slow
# health check on generating data) would measure that wait, not the code (CI: a protocol
# property test failed with "only generated 6 valid inputs after 1.19 seconds").
settings.register_profile('pma', deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile('pma')
sys.path.insert(0, str(ROOT / 'tests'))

from support import filesystems  # noqa: E402
from support.domains import another_domain, worker_domains  # noqa: E402
from support.procs import ProcessGroup  # noqa: E402


def pytest_configure(config):
    # A run started as a background job without job control (`make test &` in a script)
    # ignores SIGINT, and an ignored signal stays ignored through exec: every child would
    # shrug off Ctrl-C, and the signal tests would pass or fail by how the run was started.
    # `ros2 launch` handles SIGINT, so the nodes it starts get the default; handled here too,
    # ours do as well.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if 'PMA_TEST_DOMAIN_ID' in os.environ:
        domain = int(os.environ['PMA_TEST_DOMAIN_ID'])
    else:
        domain = random.SystemRandom().choice(worker_domains())
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    os.environ['PYTHONUNBUFFERED'] = '1'
    os.environ['RCUTILS_LOGGING_BUFFERED_STREAM'] = '0'
    profile = ROOT / 'tests' / 'support' / 'fastdds_fast_discovery.xml'
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(profile))
    config.stash[_DOMAIN_KEY] = domain


_DOMAIN_KEY = pytest.StashKey[int]()


# Fixtures that start processes; a test using one is not `in_process`.
PROCESS_FIXTURES = {'procs', 'module_procs'}


def pytest_collection_modifyitems(config, items):
    """Modules with a test marked `slow` run first, each module's tests kept together and in
    order. `make test` gives xdist the modules in this order (--no-loadscope-reorder), so a
    slow module is not left for last while the other worker has nothing to do: xdist's own
    order, by number of tests, started test_docs (4 tests, 2.5 minutes) last, and the run
    ended 2.5 minutes after the other worker's last test."""
    slow_modules = {getattr(item, 'module', None) for item in items
                    if item.get_closest_marker('slow')} - {None}
    items.sort(key=lambda item: getattr(item, 'module', None) not in slow_modules)   # stable
    for item in items:
        started = PROCESS_FIXTURES & set(getattr(item, 'fixturenames', ()))
        if item.get_closest_marker('in_process') and started:
            raise pytest.UsageError(
                f'{item.nodeid} is marked in_process but starts processes '
                f'({", ".join(sorted(started))}): `make test` runs in_process tests at a low '
                f'CPU priority, where a process on a deadline would starve')


def pytest_report_header(config):
    mode = os.environ.get('PMA_ROS_MODE', 'unknown (run through tools/env.sh)')
    return f'ROS_DOMAIN_ID={config.stash[_DOMAIN_KEY]} localhost-only; ROS mode: {mode}'


@pytest.fixture(autouse=True, scope='module')
def ros_domain_per_module():
    """A fresh ROS_DOMAIN_ID for every test module.

    Processes of one module cannot then see another module's: not its lingering nodes, nor
    the endpoints of a process it killed, which DDS keeps announcing until their lease ends
    (a recorder adapts its QoS to such ghosts). The in-process rclpy context follows: it is
    shut down at the end of the module, and the next module's probe starts it again.
    """
    os.environ['ROS_DOMAIN_ID'] = str(another_domain())
    yield
    import rclpy
    if rclpy.ok():
        rclpy.shutdown()


@pytest.fixture
def procs(tmp_path):
    """Start real processes; every one is ended (SIGINT, SIGTERM, SIGKILL) at teardown."""
    group = ProcessGroup(log_dir=tmp_path / 'logs')
    try:
        yield group
    finally:
        group.stop_all()


@pytest.fixture(scope='module')
def module_procs(tmp_path_factory):
    group = ProcessGroup(log_dir=tmp_path_factory.mktemp('logs'))
    try:
        yield group
    finally:
        group.stop_all()


@pytest.fixture
def small_filesystem():
    """support.filesystems.small_filesystem (a real tmpfs of a given size), for the packages'
    own tests, which take the repository's test plumbing as fixtures rather than imports."""
    return filesystems.small_filesystem
