"""Every executable finishes its shutdown whatever stop signals arrive, exits 0, says so quietly.

A Ctrl-C under `ros2 launch` sends SIGINT to the process group and launch then sends each
child its own SIGINT, and SIGTERM after a timeout; `docker stop` sends SIGTERM, a closed
terminal SIGHUP. The trials here send such bursts at random moments (before, during and
after start-up) to processes started as `ros2 launch` starts them: their own process group,
default signal dispositions. The seed of each trial is in its name, so a failure repeats.

The trials start once the process has installed its stop handlers (pma_common.stop.entry_point,
before rclpy is imported), seen from outside in /proc/PID/status: before that, Python is
still importing what its console-script wrapper needs (importlib.metadata), none of our code
has run and nothing is open, and a SIGINT there gets Python's default (KeyboardInterrupt).
That takes about 0.1 s on an idle machine, and over 0.25 s when CI starts four at once. From
the entry point on, every signal is a clean stop.
"""

from __future__ import annotations

import itertools
import os
import random
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import serial
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from std_msgs.msg import Float64

from pma_bag import BagWriter
from pma_common import names, protocol
from pma_common.stop import STOP_SIGNALS
from pma_interfaces.msg import LengthSetpoint, PmaState
from support import firmware
from support.domains import another_domain
from support.procs import (
    ROOT,
    Proc,
    ProcessGroup,
    children_of,
    kill_group,
    popen_in_own_group,
    running,
)
from support.ros import SpinningNode, publish_until, shutdown, wait_until

pytestmark = pytest.mark.integration

ALARMING = ('Traceback', 'KeyboardInterrupt', 'failed to shutdown', 'rcl_shutdown')
TRIALS = 4


def handlers_installed(pid: int) -> bool:
    """True once the process catches every stop signal: Python alone catches only SIGINT,
    so this is pma_common.stop.entry_point at work."""
    try:
        status = Path(f'/proc/{pid}/status').read_text()
    except OSError:    # gone already
        return True
    caught = int(next(line for line in status.splitlines()
                      if line.startswith('SigCgt:')).split()[1], 16)
    return all(caught & (1 << (sig - 1)) for sig in STOP_SIGNALS)


def start_moment(proc: Proc, rng: random.Random, latest_s: float) -> None:
    """Wait for the stop handlers, then a random moment of start-up (rclpy's import and on)."""
    wait_until(lambda: handlers_installed(proc.popen.pid), 20,
               f'{proc.name} installing its stop handlers')
    time.sleep(rng.uniform(0.0, latest_s))


def burst(rng: random.Random) -> list[tuple[float, int, bool]]:
    """(delay before it [s], signal, to the whole group?) - a Ctrl-C under launch and more."""
    plan = [(0.0, signal.SIGINT, True),                        # the terminal's, to the group
            (rng.uniform(0.0, 0.05), signal.SIGINT, False)]    # launch's own
    for _ in range(rng.randint(0, 3)):
        plan.append((rng.uniform(0.0, 0.3), rng.choice((signal.SIGINT, signal.SIGTERM,
                                                        signal.SIGHUP)), False))
    return plan


def send(proc: Proc, plan: list[tuple[float, int, bool]]) -> None:
    for delay, sig, group in plan:
        time.sleep(delay)
        try:
            os.killpg(proc.popen.pid, sig) if group else proc.popen.send_signal(sig)
        except ProcessLookupError:
            return


def finish(proc: Proc, timeout: float = 20.0) -> str:
    """Wait for the exit; it must be 0 and the output free of alarms."""
    try:
        code = proc.popen.wait(timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f'{proc.name} still running {timeout} s after the signals; its stacks:\n'
                    f'{proc.abort_with_stacks()[-6000:]}')
    proc._reader.join(5)
    output = proc.output
    assert code == 0, f'{proc.name} exited {code}:\n{output[-3000:]}'
    for word in ALARMING:
        assert word not in output, f'{proc.name} said {word!r}:\n{output[-3000:]}'
    return output


def processes_running(executable: Path) -> list[int]:
    """Pids of the processes running `executable`, from /proc."""
    found = []
    for entry in Path('/proc').iterdir():
        try:
            argv0 = (entry / 'cmdline').read_bytes().split(b'\0', 1)[0]
        except OSError:              # not a process, or it ended meanwhile
            continue
        if entry.name.isdigit() and argv0 == bytes(executable):
            found.append(int(entry.name))
    return found


def trials(seed: int) -> list[random.Random]:
    return [random.Random(seed * 100 + k) for k in range(TRIALS)]


def run_parallel(function, rngs: list[random.Random]) -> None:
    with ThreadPoolExecutor(len(rngs)) as pool:
        for future in [pool.submit(function, k, rng) for k, rng in enumerate(rngs)]:
            future.result()


def device_setpoint_pa(port: Path) -> int:
    """What the simulated device regulates to now, read from its own sample lines."""
    decoder = protocol.FrameDecoder()
    with serial.Serial(str(port), 115200, timeout=0.2) as link:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            for frame in decoder.feed(link.read(4096)):
                if isinstance(frame, protocol.Sample):
                    return frame.setpoint_pa
    raise TimeoutError(f'no sample from {port}')


@pytest.mark.parametrize('seed', [1, 2])
def test_driver_node_closes_the_port_under_any_burst(procs, tmp_path, seed):
    def trial(k: int, rng: random.Random) -> None:
        port = tmp_path / f'pma{k}'
        fake = procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port))
        fake.wait_for_line('device at', 20)
        driver = procs.ros2_run('pma_driver', 'driver_node', name=f'driver{k}',
                                ros_args=['-r', f'__ns:=/t{seed}_{k}', '-p', f'port:={port}'])
        start_moment(driver, rng, 2.75)
        send(driver, burst(rng))
        output = finish(driver)
        if 'configured:' in output:                # the port was open: it must be closed
            assert 'closed ' in output, output[-3000:]

    run_parallel(trial, trials(seed))


def test_ctrl_c_under_launch_vents_the_muscle(procs, tmp_path):
    """The reproduction from the report: SIGINT, SIGINT 20 ms later, while at 150 kPa."""
    port = tmp_path / 'pma'
    # Without the device's heartbeat check, only the driver's own VENT brings it to 0 Pa.
    fake = procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port),
                          '--no-heartbeat-check')
    fake.wait_for_line('device at', 20)
    probe = SpinningNode('signal_test_probe')
    states: list[PmaState] = []
    probe.node.create_subscription(PmaState, names.STATE, states.append, 100)
    setpoint = probe.node.create_publisher(Float64, names.PRESSURE_SETPOINT, 10)
    try:
        for attempt in range(3):
            driver = procs.ros2_run('pma_driver', 'driver_node', name=f'driver{attempt}',
                                    ros_args=['-p', f'port:={port}'])
            driver.wait_for_line('active: publishing', 30)
            # Published until the device has it, as `ros2 topic pub -r` would: the count of
            # subscribers may still include the previous attempt's driver, gone a moment ago.
            publish_until(setpoint, Float64(data=150_000.0),
                          lambda: bool(states) and states[-1].gauge_setpoint_pa == 150_000.0,
                          10, 'the device at 150 kPa', period=0.2)
            send(driver, [(0.0, signal.SIGINT, True), (0.02, signal.SIGINT, False)])
            output = finish(driver)
            assert 'vented' in output, output[-3000:]
            assert device_setpoint_pa(port) == 0
    finally:
        probe.close()
        shutdown()


@pytest.mark.parametrize('seed', [3])
def test_a_controller_holding_a_lease_lets_go_cleanly_under_any_burst(procs, tmp_path, seed):
    """Ctrl-C under launch (and more signals) while the length controller streams a length,
    holding a commander lease: it releases the lease before it exits, so the driver never
    takes it for lost, and the muscle keeps the pressure it had (docs/control.md: a stopped
    controller leaves the pressure where it is; a lost one would have been vented)."""
    port = tmp_path / 'pma'
    procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(port),
                   name='lease_fake').wait_for_line('device at', 20)
    namespace = f'/lease{seed}'
    driver = procs.ros2_run('pma_driver', 'driver_node', name='lease_driver',
                            ros_args=['-r', f'__ns:={namespace}', '-p', f'port:={port}'])
    driver.wait_for_line('active: publishing', 30)
    probe = SpinningNode('lease_signal_probe')
    states: list[PmaState] = []
    probe.node.create_subscription(PmaState, f'{namespace}/{names.STATE}', states.append, 100)
    lengths = probe.node.create_publisher(LengthSetpoint,
                                          f'{namespace}/{names.LENGTH_SETPOINT}', 10)
    try:
        for k, rng in enumerate(trials(seed)[:2]):
            controller = procs.ros2_run('pma_control', 'length_controller',
                                        name=f'lease_controller{k}',
                                        ros_args=['-r', f'__ns:={namespace}'])
            controller.wait_for_line('length_controller ready', 30)
            mark = driver.mark()

            def pressurised() -> bool:
                lengths.publish(LengthSetpoint(length_m=0.27))
                return bool(states) and states[-1].gauge_pressure_pa > 150_000.0

            wait_until(pressurised, 30, 'the controller filling the muscle', period=0.05)
            send(controller, burst(rng))
            finish(controller)
            first = len(states)
            time.sleep(1.5)                  # past the driver's 0.8 s commander timeout
            said = driver.lines_since(mark)
            assert 'lost: no renewal' not in said, said
            since = states[first:]
            assert len(since) > 15, 'pma/state stopped'
            # Held, not vented: the states in flight when the controller exited may still
            # show the setpoint before its last one, so at most one change, to a non-zero one.
            setpoints = [s.gauge_setpoint_pa for s in since]
            changes = [(a, b) for a, b in itertools.pairwise(setpoints) if a != b]
            assert len(changes) <= 1 and min(setpoints) > 0.0, setpoints
            assert since[-1].gauge_pressure_pa > 150_000.0, since[-1]
    finally:
        probe.close()
        shutdown()


def test_a_killed_demo_takes_its_children_with_it_and_the_rig_vents(procs, tmp_path):
    """The demo's six children run in sessions of their own (a terminal's Ctrl-C reaches only
    the demo, which stops them in order). A demo that crashed (a segfault, 2026-11-28) or was
    SIGKILLed left them all running, the simulated rig too, for an hour, until found slowing
    the tests that followed. Each now gets SIGTERM when the demo ends, however it ends."""
    demo = procs.ros2_run('pma_bringup', 'demo', '--runs-dir', str(tmp_path), '--live-port',
                          '0', name='demo', env={'ROS_DOMAIN_ID': str(another_domain())})
    children = []
    try:
        demo.wait_for_line('3/8', 90)        # every child started, the rig streaming
        children = children_of(demo.popen.pid)
        assert len(children) >= 6, children
        os.kill(demo.popen.pid, signal.SIGKILL)
        demo.popen.wait(10)
        wait_until(lambda: not any(running(pid) for pid in children), 30,
                   'the children to end with the demo')
    finally:
        for pid in children:                 # not to burden the tests that follow
            if running(pid):
                os.kill(pid, signal.SIGKILL)
    (driver_log,) = tmp_path.glob('*/logs/driver_node.log')
    assert '(vented)' in driver_log.read_text(), driver_log.read_text()[-2000:]


@pytest.mark.parametrize('seed', [3])
def test_model_node_and_fake_arduino_exit_quietly(procs, tmp_path, seed):
    def trial(k: int, rng: random.Random) -> None:
        if k % 2:
            proc = procs.ros2_run('pma_model', 'model_node', name=f'model{k}',
                                  ros_args=['-r', f'__ns:=/m{k}'])
        else:
            proc = procs.ros2_run('pma_sim', 'fake_arduino', '--link', str(tmp_path / f'f{k}'),
                                  name=f'fake{k}')
        start_moment(proc, rng, 2.25)
        send(proc, burst(rng))
        output = finish(proc)
        if proc.name.startswith('fake') and 'device at' in output:
            assert 'fake_arduino: stats' in output

    run_parallel(trial, trials(seed))


@pytest.mark.parametrize('seed', [6])
def test_simavr_arduino_exits_quietly_and_ends_its_simulator(procs, tmp_path, seed):
    build = firmware.require_simulator(firmware.session_build())

    def trial(k: int, rng: random.Random) -> None:
        proc = procs.ros2_run('pma_sim', 'simavr_arduino', '--link', str(tmp_path / f's{k}'),
                              *build.simavr_args(), name=f'simavr{k}')
        start_moment(proc, rng, 2.25)
        send(proc, burst(rng))
        output = finish(proc)
        if 'device at' in output:
            assert 'simavr_arduino: stats' in output and 'simavr_arduino: firmware' in output

    run_parallel(trial, trials(seed))
    # The simulators (in sessions of their own, out of reach of the bursts) went with them.
    assert not processes_running(build.simulator), 'pma_simavr outlived simavr_arduino'


@pytest.mark.parametrize('seed', [4])
def test_recorder_finishes_its_bag_under_any_burst(procs, tmp_path, seed):
    def trial(k: int, rng: random.Random) -> None:
        bag = tmp_path / f'bag{k}'
        recorder = procs.ros2_run('pma_bag', 'record', '-o', str(bag), name=f'record{k}',
                                  ros_args=['-r', f'__ns:=/r{k}'])
        start_moment(recorder, rng, 2.75)
        send(recorder, burst(rng))
        finish(recorder)
        assert (bag / 'metadata.yaml').is_file(), sorted(bag.iterdir())
        with AnyReader([bag]) as reader:           # closed cleanly: an independent reader agrees
            assert reader.message_count == sum(1 for _ in reader.messages())

    run_parallel(trial, trials(seed))


@pytest.mark.parametrize('seed', [6])
def test_live_bridge_stops_its_server_quietly_under_any_burst(procs, seed):
    def trial(k: int, rng: random.Random) -> None:
        bridge = procs.ros2_run('pma_bringup', 'foxglove_live', name=f'live{k}',
                                ros_args=['-r', f'__ns:=/l{k}', '-p', 'port:=0'])
        start_moment(bridge, rng, 2.75)
        send(bridge, burst(rng))
        output = finish(bridge)
        if 'ws://' in output:                 # the server was up: it was stopped
            assert 'foxglove_live: stopped' in output, output[-3000:]

    run_parallel(trial, trials(seed))


def write_bag(path: Path, count: int = 2000) -> Path:
    writer = BagWriter(path)
    writer.add_topic('/signal_test', 'std_msgs/msg/Float64', [])
    start = time.time_ns()
    for k in range(count):
        writer.write('/signal_test', serialize_message(Float64(data=float(k))),
                     start + k * 5_000_000)
    writer.close()
    return path


@pytest.mark.parametrize('seed', [5])
def test_player_stops_quietly_while_looping(procs, tmp_path, seed):
    bag = write_bag(tmp_path / 'loop_bag')

    def trial(k: int, rng: random.Random) -> None:
        player = procs.ros2_run('pma_bag', 'play', str(bag), '--loop', '--rate', '20',
                                name=f'play{k}', ros_args=['-r', f'__ns:=/p{k}'])
        start_moment(player, rng, 2.75)
        send(player, burst(rng))
        finish(player)

    run_parallel(trial, trials(seed))


def test_process_group_helper_sends_what_launch_sends(tmp_path):
    """The trials' own check: a plain Python child dies of the burst (so ours do not by luck)."""
    group = ProcessGroup(tmp_path)
    proc = group.start(['python3', '-c', 'import time; print("up", flush=True); time.sleep(30)'])
    proc.wait_for_line('up', 10)
    send(proc, [(0.0, signal.SIGINT, True), (0.02, signal.SIGINT, False)])
    assert proc.popen.wait(10) != 0
    group.stop_all()


def test_a_second_ctrl_c_in_a_teardown_leaves_no_process_behind(tmp_path):
    """`make test` stopped by a second Ctrl-C (as impatient users do) while a test's processes
    are being stopped: they are in process groups of their own, where the terminal's Ctrl-C
    does not reach, so the test process must kill them (support.procs)."""
    pids_file = tmp_path / 'pids'
    run = popen_in_own_group(
        [sys.executable, '-m', 'pytest', '-q', '-p', 'no:xdist',
         str(ROOT / 'tests' / 'helpers' / 'teardown_cut_short.py')],
        cwd=ROOT, env={**os.environ, 'PMA_PIDS_FILE': str(pids_file)},
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    pids = []
    try:
        wait_until(pids_file.exists, 60, 'the inner test to start its processes')
        pids = [int(pid) for pid in pids_file.read_text().split()]
        os.killpg(run.pid, signal.SIGINT)             # Ctrl-C: the test ends, its teardown
        time.sleep(1.0)                               # waits on the stubborn second process
        os.killpg(run.pid, signal.SIGINT)             # and a second Ctrl-C cuts that short
        out, _ = run.communicate(timeout=30)
        assert 'KeyboardInterrupt' in out, out
        wait_until(lambda: not any(running(pid) for pid in pids), 5,
                   f'the stubborn processes {pids} to be gone; pytest said:\n{out}')
    finally:
        for pid in pids:
            kill_group(pid)
        kill_group(run.pid)

