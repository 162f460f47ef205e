"""The rig computer and the workstation as two hosts (issue 49), in two network namespaces.

Two namespaces joined by a veth pair stand for the rig's small computer ("rig": fake_arduino,
driver_node) and the researcher's workstation ("workstation": model_node,
length_controller, the recorder, foxglove_live, `pma`), each with only the link's address and
loopback, so every message between them crosses the link. Discovery as docs/lab-network.md
says (SUBNET; static peers with multicast kept on the host), a sweep recorded on the
workstation, a move that settles, a Foxglove viewer on the workstation (either subprotocol
name), the state-to-prediction latency across the link against the same chain on one host,
and the link dropping (`ip link set ... down`) while the workstation commands: the driver
vents because it lost its commander, and says so once the link is back. A controller on the
rig itself is not vented when the link drops.

Needs root (network namespaces): CI runs as root; elsewhere the module is skipped, saying why.
The namespaces are removed on every exit path (fixture teardown and atexit).
"""

from __future__ import annotations

import atexit
import itertools
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message

from pma_bag.reader import BagReader
from pma_interfaces.msg import PmaState
from support.procs import ProcessGroup, executable

pytestmark = pytest.mark.integration

HELPERS = Path(__file__).resolve().parent / 'helpers'
RIG_ADDRESS, WORKSTATION_ADDRESS = '10.213.7.1', '10.213.7.2'
SUBNET = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}
# The documented worst case from the last lease renewal to VENT at the defaults
# (commander_timeout_s 0.8 s, checked every tenth of it), and what a machine running the
# suite beside this test adds (the driver's timer, the log line's way out).
LEASE_VENT_WITHIN_S = 0.8 + 0.08
LOAD_SLACK_S = 0.6
RIG_DDS = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(Path(__file__).resolve().parent / 'support'
                                                 / 'fastdds_rig_nonblocking.xml')}
LOG_STAMP = re.compile(r'\[(\d+\.\d+)\]')


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(['ip', *args], capture_output=True, text=True, check=check,
                          timeout=10)


class TwoHosts:
    """Two namespaces and a veth pair between them; `down`/`up` cut and mend the link."""

    def __init__(self):
        tag = os.getpid() % 100_000
        self.rig, self.workstation = f'pma-rig-{tag}', f'pma-ws-{tag}'
        self.rig_if, self.workstation_if = f'pmr{tag}', f'pmw{tag}'
        atexit.register(self.remove)
        for ns in (self.rig, self.workstation):
            _ip('netns', 'add', ns)
        _ip('link', 'add', self.rig_if, 'type', 'veth', 'peer', 'name', self.workstation_if)
        for ns, interface, address in ((self.rig, self.rig_if, RIG_ADDRESS),
                                       (self.workstation, self.workstation_if,
                                        WORKSTATION_ADDRESS)):
            _ip('link', 'set', interface, 'netns', ns)
            _ip('-n', ns, 'addr', 'add', f'{address}/24', 'dev', interface)
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
            _ip('-n', ns, 'link', 'set', interface, 'up')
            # DDS discovery's multicast goes out on the link (a LAN's default route does it).
            _ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', interface)

    def down(self) -> float:
        """Cut the link; the wall-clock time it was cut."""
        cut = time.time()
        _ip('-n', self.workstation, 'link', 'set', self.workstation_if, 'down')
        return cut

    def up(self) -> None:
        _ip('-n', self.workstation, 'link', 'set', self.workstation_if, 'up')
        _ip('-n', self.workstation, 'route', 'replace', '224.0.0.0/4', 'dev',
            self.workstation_if)

    def remove(self) -> None:
        for ns in (self.rig, self.workstation):     # the veth pair goes with them
            _ip('netns', 'del', ns, check=False)


def namespaces_possible() -> str:
    """Why network namespaces cannot be made here ('' when they can)."""
    if os.geteuid() != 0:
        return 'needs root for network namespaces (CI runs as root)'
    if shutil.which('ip') is None:
        return 'needs iproute2 (`ip`)'
    probe = f'pma-probe-{os.getpid()}'
    made = _ip('netns', 'add', probe, check=False)
    _ip('netns', 'del', probe, check=False)
    return '' if made.returncode == 0 else f'ip netns add failed: {made.stderr.strip()}'


class Lab:
    def __init__(self, hosts: TwoHosts, procs: ProcessGroup, work: Path):
        self.hosts, self.procs, self.work = hosts, procs, work
        self.port = work / 'pma'
        fake = self.run_on(hosts.rig, 'pma_sim', 'fake_arduino', '--link', str(self.port),
                           '--rate', '50', '--seed', '5')
        fake.wait_for_line('device at', 20)
        self.driver = self.run_on(hosts.rig, 'pma_driver', 'driver_node', env=RIG_DDS, ros_args=[
            '-p', f'port:={self.port}', '-p', 'sample_rate_hz:=50.0'])
        self.driver.wait_for_line('active: publishing', 30)
        self.model = self.run_on(hosts.workstation, 'pma_model', 'model_node')
        self.controller = self.run_on(hosts.workstation, 'pma_control', 'length_controller')
        # Idle until a sweep's ~/start: no bag of its own.
        self.recorder = self.run_on(hosts.workstation, 'pma_bag', 'record', '--idle')
        # The live view on the workstation, for a viewer there (a free port of its own).
        self.live = self.run_on(hosts.workstation, 'pma_bringup', 'foxglove_live',
                                ros_args=['-p', 'port:=0'])
        self.live_url = re.search(r'ws://\S+', self.live.wait_for_line('ws://', 30)).group(0)
        self.model.wait_for_line('model_node ready', 30)
        self.controller.wait_for_line('length_controller ready', 30)

    def run_on(self, ns: str, package: str, name: str, *args: str, ros_args=(), env=None,
               label: str = ''):
        argv = ['ip', 'netns', 'exec', ns, executable(package, name), *args]
        if ros_args:
            argv += ['--ros-args', *ros_args]
        return self.procs.start(argv, name=label or f'{ns}-{name}', env={**SUBNET, **(env or {})},
                                cwd=self.work)

    def pma(self, ns: str, *args: str, env=None, timeout: float = 90.0):
        return subprocess.run(
            ['ip', 'netns', 'exec', ns, executable('pma_cli', 'pma'), *args],
            capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL,
            env={**os.environ, **SUBNET, **(env or {})}, check=False)

    def pma_in_background(self, ns: str, *args: str, label: str):
        return self.procs.start(['ip', 'netns', 'exec', ns, executable('pma_cli', 'pma'),
                                 *args], name=label, env=SUBNET)

    def vent(self) -> None:
        result = self.pma(self.hosts.workstation, 'vent', '--wait')
        assert result.returncode == 0, result.stdout + result.stderr


@pytest.fixture(scope='module')
def lab(tmp_path_factory):
    reason = namespaces_possible()
    if reason:
        pytest.skip(reason)
    hosts = TwoHosts()
    work = tmp_path_factory.mktemp('lab_network')
    procs = ProcessGroup(work / 'logs')
    try:
        yield Lab(hosts, procs, work)
    finally:
        procs.stop_all()
        hosts.remove()


def log_time(line: str) -> float:
    """The wall-clock stamp of an rclpy console line ('[LEVEL] [1796212611.40] [node]: ...')."""
    return float(LOG_STAMP.findall(line)[0])


def test_the_workstation_finds_the_rig_over_the_subnet(lab):
    result = lab.pma(lab.hosts.workstation, 'status')
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'streaming' in result.stdout and 'model_node' in result.stdout


def test_static_peers_find_a_rig_that_sends_no_multicast_beyond_its_host(lab):
    """A network without multicast (many Wi-Fi access points): each host keeps discovery to
    itself (LOCALHOST) and names the other in ROS_STATIC_PEERS. Without the peer nothing is
    found, which shows the link carried no multicast discovery."""
    local = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    port = lab.work / 'pma-peers'
    lab.run_on(lab.hosts.rig, 'pma_sim', 'fake_arduino', '--link', str(port), '--seed', '6',
               env=local, label='peers-fake').wait_for_line('device at', 20)
    lab.run_on(lab.hosts.rig, 'pma_driver', 'driver_node', env=local, label='peers-driver',
               ros_args=['-r', '__ns:=/peers', '-p', f'port:={port}']
               ).wait_for_line('active: publishing', 30)
    alone = lab.pma(lab.hosts.workstation, 'status', '--namespace', 'peers', env=local)
    assert alone.returncode != 0 and 'no driver in /peers' in alone.stderr, alone.stdout
    peered = lab.pma(lab.hosts.workstation, 'status', '--namespace', 'peers',
                     env={**local, 'ROS_STATIC_PEERS': RIG_ADDRESS})
    assert peered.returncode == 0, peered.stdout + peered.stderr
    assert 'streaming' in peered.stdout


def test_a_sweep_recorded_on_the_workstation_has_every_sample(lab):
    bag = lab.work / 'across'
    result = lab.pma(lab.hosts.workstation, 'sweep', '--max', '200kPa', '--step', '100kPa',
                     '--hold', '1s', '--record', str(bag))
    assert result.returncode == 0, result.stdout + result.stderr
    with BagReader(bag) as reader:
        seqs = [deserialize_message(m.data, PmaState).seq
                for m in reader.messages(['/pma/state'])]
    assert len(seqs) > 200
    assert [b - a for a, b in itertools.pairwise(seqs) if b != a + 1] == []


def test_a_move_from_the_workstation_settles(lab):
    result = lab.pma(lab.hosts.workstation, 'move', '27cm')
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'move succeeded' in result.stdout
    lab.vent()


@pytest.mark.parametrize('subprotocol', ['foxglove.websocket.v1', 'foxglove.sdk.v1'])
def test_a_viewer_on_the_workstation_sees_the_rig(lab, subprotocol):
    """foxglove_live on the workstation forwards the rig's states and the workstation's
    predictions to a viewer offering only one of the protocol's two names."""
    viewer = lab.procs.start(['ip', 'netns', 'exec', lab.hosts.workstation, 'python3',
                              HELPERS / 'foxglove_viewer.py', lab.live_url, '--subprotocol',
                              subprotocol, '--topic', '/pma/state', '--topic',
                              '/pma/prediction', '--count', '50'], name=f'viewer-{subprotocol}')
    assert viewer.popen.wait(60) == 0, viewer.output
    said = json.loads(viewer.output.strip().splitlines()[-1])
    assert said['subprotocol'] == subprotocol
    assert min(said['counts'].values()) >= 50, said


def latencies_s(path: Path) -> np.ndarray:
    """Receive time minus the state's stamp, per prediction, from subscriber.py's dump."""
    received = json.loads(path.read_text())
    return np.array([(got - stamp) / 1e9 for got, stamp in received])


def test_state_to_prediction_latency_across_the_link_against_one_host(lab, record_property):
    """The same chain twice at once: model_node on the workstation (pma/state crosses the
    link) and one on the rig (remapped to pma/prediction_local), each read where it runs."""
    lab.run_on(lab.hosts.rig, 'pma_model', 'model_node', label='rig-model', ros_args=[
        '-r', '__node:=model_node_local', '-r', 'pma/prediction:=pma/prediction_local',
        '-r', 'pma/model_params:=pma/model_params_local',
        '-r', 'pressure_for_length:=pressure_for_length_local']
    ).wait_for_line('model_node ready', 30)
    stamp = ['--field', 'header.stamp', '--timeout', '12']
    across = lab.procs.start(['ip', 'netns', 'exec', lab.hosts.workstation, 'python3',
                              HELPERS / 'subscriber.py', '--topic', '/pma/prediction', '--type',
                              'pma_interfaces/msg/PmaPrediction', *stamp,
                              '--out', lab.work / 'across.json'], name='sub-across', env=SUBNET)
    local = lab.procs.start(['ip', 'netns', 'exec', lab.hosts.rig, 'python3',
                             HELPERS / 'subscriber.py', '--topic', '/pma/prediction_local',
                             '--type', 'pma_interfaces/msg/PmaPrediction', *stamp,
                             '--out', lab.work / 'local.json'], name='sub-local', env=SUBNET)
    assert across.popen.wait(40) == 0 and local.popen.wait(40) == 0
    far, near = latencies_s(lab.work / 'across.json'), latencies_s(lab.work / 'local.json')
    assert far.size > 300 and near.size > 300, (far.size, near.size)    # 50 Hz, ~10 s each
    ratios = {f'p{q}': float(np.percentile(far, q) / np.percentile(near, q)) for q in (50, 99)}
    record_property('latency_ms', {'across_p50': 1e3 * float(np.median(far)),
                                   'local_p50': 1e3 * float(np.median(near)), **ratios})
    print(f'state-to-prediction latency: across the link p50 {1e3 * np.median(far):.2f} ms, '
          f'p99 {1e3 * np.percentile(far, 99):.2f} ms; one host p50 '
          f'{1e3 * np.median(near):.2f} ms, p99 {1e3 * np.percentile(near, 99):.2f} ms; '
          f'ratio p50 {ratios["p50"]:.2f}, p99 {ratios["p99"]:.2f}')
    # A veth adds microseconds; a ratio far above 1 would be a discovery or transport fault
    # (a fallback, a retransmitting reader), not the link.
    assert ratios['p50'] < 3.0, ratios


def test_the_link_dropping_during_a_move_vents_the_rig_and_both_sides_say_why(lab):
    hosts = lab.hosts
    before_move = (lab.driver.mark(), lab.controller.mark())
    # A goal that is still running when the link drops: it would settle within seconds,
    # but asks to stay settled for 30 s.
    move = lab.pma_in_background(hosts.workstation, 'move', '25.5cm', '--settle', '30s',
                                 '--goal-timeout', '60s', label='pma-move')
    move.wait_for_line('moving to', 30)
    time.sleep(2.0)                                      # filled to ~300 kPa
    mark = lab.driver.mark()
    cut = hosts.down()
    try:
        try:
            line = lab.driver.wait_for_line(
                lambda text: 'length_controller' in text and 'lost: no renewal' in text, 10,
                after=mark)
        except TimeoutError as error:     # seen once in CI, with nothing said since the cut
            pytest.fail(f'{error}\n--- driver since the move began:\n'
                        f'{lab.driver.lines_since(before_move[0])[-3000:]}\n--- controller:\n'
                        f'{lab.controller.lines_since(before_move[1])[-3000:]}\n--- pma move:\n'
                        f'{move.output[-2000:]}')
        print(f'link down to the vent of the driver, during a move: {log_time(line) - cut:.3f} s')
        assert log_time(line) - cut <= LEASE_VENT_WITHIN_S + LOAD_SLACK_S, \
            (log_time(line) - cut, line)
        assert line.endswith('vented')
        time.sleep(1.5)
    finally:
        hosts.up()
    assert move.popen.wait(60) == 1, move.output
    assert 'move aborted' in move.output and 'no usable pma/state sample' in move.output, \
        move.output
    status = lab.pma(hosts.workstation, 'status', '--wait', '20s')
    said = status.stdout + status.stderr
    assert 'last lost: commander /length_controller' in said, said
    assert 'setpoint 0.0 kPa' in said, said
    assert 'commander' in lab.driver.lines_since(mark)


def test_the_link_dropping_during_a_sweep_aborts_it_on_the_rig(lab):
    hosts = lab.hosts
    mark = lab.driver.mark()
    sweep = lab.pma_in_background(hosts.workstation, 'sweep', '--max', '300kPa', '--step',
                                  '100kPa', '--hold', '4s', label='pma-sweep')
    lab.driver.wait_for_line('sweep: staircase', 30, after=mark)
    time.sleep(3.0)
    cut = hosts.down()
    try:
        line = lab.driver.wait_for_line(
            lambda text: 'commander pma sweep' in text and 'lost: no renewal' in text, 10,
            after=mark)
        print(f'link down to the loss of the sweep commander: {log_time(line) - cut:.3f} s')
        assert log_time(line) - cut <= LEASE_VENT_WITHIN_S + LOAD_SLACK_S, log_time(line) - cut
        time.sleep(1.0)
    finally:
        hosts.up()
    assert sweep.popen.wait(60) == 1, sweep.output
    # The sweep aborts and vents on the lost lease. Without the rig's non-blocking profile the
    # driver's serial link stalled while the link was down (docs/lab-network.md, "The rig
    # computer's DDS profile") and the stall could abort the sweep first: vented all the same,
    # so either reason is taken; the lease's loss and its timing are checked above.
    said = lab.driver.lines_since(mark)
    assert re.search(r'sweep aborted: (commander pma sweep|.*stalled|.*no data)', said), said
    assert 'sweep aborted' in sweep.output, sweep.output


def test_a_controller_on_the_rig_itself_keeps_the_muscle_when_the_link_drops(lab):
    """Commanded from the rig computer, the muscle has lost nobody when the workstation's
    link drops: no vent."""
    hosts = lab.hosts
    assert lab.controller.stop() == 0              # one controller per muscle
    local = lab.run_on(hosts.rig, 'pma_control', 'length_controller', label='rig-controller')
    local.wait_for_line('length_controller ready', 30)
    try:
        result = lab.pma(hosts.rig, 'move', '27cm')
        assert result.returncode == 0, result.stdout + result.stderr
        mark = lab.driver.mark()
        hosts.down()
        time.sleep(3.0)
        hosts.up()
        assert 'lost: no renewal' not in lab.driver.lines_since(mark)
        status = lab.pma(hosts.rig, 'status')
        assert 'holding' in status.stdout or 'hold' in status.stdout, status.stdout
        assert 'setpoint 0.0 kPa' not in status.stdout, status.stdout
    finally:
        lab.pma(hosts.rig, 'vent', '--wait')
        local.stop()
