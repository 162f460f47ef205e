"""fake_arduino as a real process on a real pty, read with pyserial like the driver does."""

import itertools
import os
import re
import signal
import threading
import time

import pytest
import serial

from pma_common import protocol
from pma_common.calibration import PressureCalibration
from pma_common.protocol import Ack, FrameDecoder, Hello, Sample
from pma_common.sequence import SequenceStats, SequenceTracker
from pma_common.stop import StopRequest
from pma_sim import fake_arduino
from pma_sim.device import DeviceConfig, SimDevice

DEVICE_LINE = re.compile(r'^fake_arduino: device at (/dev/pts/\d+)$')
STATS_FIELDS = ('sent', 'bad_checksum', 'garbage', 'dropped', 'split', 'echo_timeouts')
STATS_LINE = re.compile(
    r'^fake_arduino: stats ' + ' '.join(rf'{name}=(\d+)' for name in STATS_FIELDS) + '$')


def stats_lines(output: str) -> list[dict[str, int]]:
    return [dict(zip(STATS_FIELDS, map(int, match.groups()), strict=True))
            for match in map(STATS_LINE.match, output.splitlines()) if match]


def start(procs, *args):
    proc = procs.ros2_run('pma_sim', 'fake_arduino', *args)
    line = proc.wait_for_line(lambda text: DEVICE_LINE.match(text) is not None, timeout=20)
    return proc, DEVICE_LINE.match(line).group(1)


class Port:
    """pyserial on the slave side plus a decoder, as the driver will use them."""

    def __init__(self, path):
        self.serial = serial.Serial(str(path), 115200, timeout=0.02)
        self.decoder = FrameDecoder(drop_first_partial=True)
        self.arrivals = []    # (monotonic time, frame)

    def send(self, command, *args):
        self.serial.write(protocol.encode_command(command, *args))

    def collect(self, seconds, heartbeat_s=0.2, until=None):
        """Read for `seconds` (sending HB), or until `until(frame)` is true; return frames."""
        frames = []
        end = time.monotonic() + seconds
        next_hb = 0.0
        while time.monotonic() < end:
            now = time.monotonic()
            if heartbeat_s and now >= next_hb:
                self.send('HB')
                next_hb = now + heartbeat_s
            for frame in self.decoder.feed(self.serial.read(4096)):
                frames.append(frame)
                self.arrivals.append((time.monotonic(), frame))
                if until and until(frame):
                    return frames
        return frames

    def close(self):
        self.serial.close()


def samples_of(frames):
    return [f for f in frames if isinstance(f, Sample)]


def lost_samples(samples) -> SequenceStats:
    tracker = SequenceTracker()
    for sample in samples:
        tracker.add(sample.seq)
    return tracker.stats()


def test_banner_samples_at_the_rate_and_clean_exit(procs, tmp_path):
    link = tmp_path / 'ttyPMA'
    proc, path = start(procs, '--link', link)
    assert os.path.realpath(link) == path
    port = Port(link)
    port.send('HELLO')
    frames = port.collect(2.0)
    hello = next(f for f in frames if isinstance(f, Hello))
    assert (hello.proto, hello.rate_hz, hello.max_rate_hz, hello.ceiling_pa, hello.limit_pa,
            hello.hb_timeout_ms) == (1, 20, 1000, 500_000, 500_000, 1000)
    samples = samples_of(frames)
    assert 35 <= len(samples) <= 42
    assert {b.seq - a.seq for a, b in itertools.pairwise(samples)} == {1}
    assert {b.t_ms - a.t_ms for a, b in itertools.pairwise(samples)} == {50}
    assert port.decoder.dropped_total == 0
    port.close()
    proc.signal(signal.SIGINT)
    assert proc.popen.wait(5) == 0
    assert not os.path.lexists(link)
    proc.wait_for_line(STATS_LINE.match, timeout=5)


def test_sigterm_removes_the_link_and_prints_the_stats(procs, tmp_path):
    link = tmp_path / 'ttyPMA'
    proc, _ = start(procs, '--link', link)
    assert os.path.islink(link)
    proc.signal(signal.SIGTERM)
    assert proc.popen.wait(5) == 0
    assert not os.path.lexists(link)
    proc.wait_for_line(STATS_LINE.match, timeout=5)
    assert stats_lines(proc.output) == [dict.fromkeys(STATS_FIELDS, 0)]   # no host, no lines


def test_stats_on_exit_equal_what_the_host_decoded(procs):
    proc, path = start(procs, '--rate', '200', '--seed', '5', '--garbage-rate', '0.1',
                       '--bad-checksum-rate', '0.1', '--drop-rate', '0.1', '--split-rate', '0.2',
                       '--echo-timeout-rate', '0.2', '--stall-after', '2.0', '--stall-for', '100')
    port = Port(path)
    frames = port.collect(2.6)   # output stops for good at 2 s: read all of it
    proc.signal(signal.SIGINT)
    assert proc.popen.wait(5) == 0
    proc.wait_for_line(STATS_LINE.match, timeout=5)
    [stats] = stats_lines(proc.output)
    samples = samples_of(frames)
    dropped = port.decoder.dropped
    assert stats['sent'] == len(samples) > 200
    assert stats['bad_checksum'] == dropped['checksum'] > 10
    assert stats['garbage'] == port.decoder.dropped_total - dropped['checksum'] > 10
    assert stats['echo_timeouts'] == sum(s.echo_us == 0 for s in samples) > 10
    assert stats['dropped'] > 10 and stats['split'] > 10
    gaps = lost_samples(samples).lost
    assert 0 < gaps <= stats['dropped'] + stats['bad_checksum']


def test_commanded_sweep_reaches_each_setpoint(procs):
    _, path = start(procs, '--rate', '100')
    port = Port(path)
    sensor = PressureCalibration()
    lengths = {}
    for setpoint in (100_000, 300_000, 500_000, 200_000, 0):
        port.send('SET', setpoint)
        frames = port.collect(2.0)
        assert Ack('SET', setpoint) in frames
        settled = samples_of(frames)[-20:]
        pressures = [sensor.adc_to_pa(s.adc) for s in settled]
        assert abs(sum(pressures) / len(pressures) - setpoint) < 10_000, setpoint
        assert all(s.setpoint_pa == setpoint and s.status == 0 for s in settled)
        lengths[setpoint] = sum(s.echo_us for s in settled) / len(settled)
    # Contraction lengthens the echo (sensor faces the free end): monotone in pressure.
    assert lengths[0] < lengths[100_000] < lengths[300_000] < lengths[500_000]


def test_set_above_ceiling_is_refused_over_the_wire(procs):
    _, path = start(procs, '--ceiling-pa', '300000')
    port = Port(path)
    port.send('SET', 300_001)
    frames = port.collect(1.0, until=lambda f: isinstance(f, protocol.Nak))
    assert frames[-1] == protocol.Nak('SET', 'RANGE')


def test_heartbeat_loss_over_the_wire(procs):
    _, path = start(procs, '--rate', '50')
    port = Port(path)
    port.send('SET', 100_000)
    port.collect(0.5)
    frames = port.collect(2.0, heartbeat_s=0)
    lost = [s for s in samples_of(frames) if s.status & protocol.STATUS_HEARTBEAT_LOST]
    assert lost and all(s.valve == protocol.Valve.VENT for s in lost)


def test_what_a_host_wrote_just_before_it_closed_is_still_received():
    """A board's UART receives what was on the wire when the host closed the port.

    The driver writes VENT as it closes. fake_arduino read nothing from a closed pty, so
    when it saw the close before the bytes the VENT was lost and the device kept its
    setpoint (CI: test_ctrl_c_under_launch_vents_the_muscle, the device at 150 kPa).
    """
    port = fake_arduino.PtyPort()
    try:
        host = os.open(port.path, os.O_RDWR | os.O_NOCTTY)
        assert port.check_host()
        vent = protocol.encode_command(protocol.Command.VENT)
        os.write(host, vent)
        os.close(host)
        assert not port.check_host()          # the close is noticed first
        assert port.wait_readable(0.0)
        assert port.read() == vent
        assert not port.wait_readable(0.0)    # then nothing: no busy loop on a closed pty
    finally:
        port.close()


class SlowDevice(SimDevice):
    """SimDevice taking 1.5 ms of wall time per simulated millisecond, as simavr does on a
    loaded machine."""

    def _step(self):
        super()._step()
        time.sleep(0.0015)


@pytest.mark.parametrize('in_chunks', [True, False])
def test_a_device_behind_the_wall_clock_gets_the_heartbeats_sent_meanwhile(in_chunks):
    """Two seconds of device time run in three of wall time while the host sends a heartbeat
    every 200 ms. Handed over as they come (fake_arduino.advance, 50 ms at a time), the device
    holds; run in one go, it goes a second without them and vents (the simavr failures of the
    full runs: status 'heartbeat lost' while holding 200 kPa)."""
    port = fake_arduino.PtyPort()
    host = os.open(port.path, os.O_RDWR | os.O_NOCTTY)
    stop = threading.Event()

    def heartbeats():
        while not stop.wait(0.2):
            os.write(host, protocol.encode_command('HB'))

    try:
        assert port.check_host()
        device = SlowDevice(DeviceConfig(rate_hz=50))
        device.receive(protocol.encode_command('SET', 100_000))
        sender = threading.Thread(target=heartbeats)
        sender.start()
        if in_chunks:
            while fake_arduino.advance(device, port, 2_000):
                pass
        else:
            device.advance_to(2_000)
        samples = samples_of(FrameDecoder().feed(b''.join(device.take_output())))
        vented = [s.t_ms for s in samples if s.status & protocol.STATUS_HEARTBEAT_LOST]
        assert len(samples) >= 90
        assert (not vented) == in_chunks, vented[:3]
    finally:
        stop.set()
        os.close(host)
        port.close()


def test_a_device_slower_than_real_time_keeps_talking_while_it_falls_behind(tmp_path):
    """The loop with a device at 2/3 of real time (simavr on a loaded machine), read as the
    driver reads it: answers come late, but samples keep arriving, never a second apart (the
    driver's stall timeout). When the loop caught a lag up in one go, output stopped for as
    long as the catch-up took (CI: 'link no data during the sweep' with simavr)."""
    args = fake_arduino.parse_args(['--rate', '20', '--link', str(tmp_path / 'link')])
    stop = StopRequest()
    loop = threading.Thread(target=fake_arduino.run, args=(args, stop),
                            kwargs={'make_device': lambda config, rig: SlowDevice(config)})
    loop.start()
    try:
        link = tmp_path / 'link'
        deadline = time.monotonic() + 10
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        port = Port(link)
        frames = port.collect(6.0)
        port.close()
    finally:
        stop.request('test over')
        loop.join(30)
    arrivals = [at for at, frame in port.arrivals if isinstance(frame, Sample)]
    samples = samples_of(frames)
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    device_s = (samples[-1].t_ms - samples[0].t_ms) / 1e3 if samples else 0.0
    behind_s = (arrivals[-1] - arrivals[0]) - device_s if samples else 0.0
    assert len(samples) >= 40, len(samples)
    assert behind_s > 1.0, f'the device kept up ({behind_s:.2f} s behind): not the case tested'
    assert max(gaps) < 0.5, f'{max(gaps):.2f} s without a sample ({behind_s:.2f} s behind)'
    assert not any(s.status & protocol.STATUS_HEARTBEAT_LOST for s in samples)


def test_host_may_open_close_and_stop_reading(procs):
    _, path = start(procs, '--rate', '1000')
    for _ in range(4):
        port = Port(path)
        frames = port.collect(0.3)
        assert len(samples_of(frames)) > 150
        port.close()
        time.sleep(0.2)
    port = Port(path)
    time.sleep(2.0)                   # open but not reading: the pty buffer fills up
    port.serial.reset_input_buffer()
    port.decoder.reset()
    port.send('HELLO')
    frames = port.collect(1.0, until=lambda f: isinstance(f, Hello))
    assert isinstance(frames[-1], Hello)
    recent = samples_of(port.collect(0.3))
    assert len(recent) > 150


@pytest.mark.parametrize('flag, check', [
    ('--garbage-rate', lambda d, gaps: d.dropped['framing'] + d.dropped['overlong'] > 10
     and gaps == 0),
    ('--bad-checksum-rate', lambda d, gaps: d.dropped['checksum'] > 10),
    ('--drop-rate', lambda d, gaps: gaps > 10 and d.dropped_total == 0),
    ('--echo-timeout-rate', lambda d, gaps: d.dropped_total == 0 and gaps == 0),
])
def test_each_fault_flag_does_what_it_says(procs, flag, check):
    _, path = start(procs, '--rate', '200', flag, '0.2', '--seed', '7')
    port = Port(path)
    samples = samples_of(port.collect(1.5))
    gaps = lost_samples(samples).lost
    assert len(samples) > 150
    assert check(port.decoder, gaps), (dict(port.decoder.dropped), gaps)
    timeouts = [s for s in samples if s.echo_us == 0]
    if flag == '--echo-timeout-rate':
        assert 0.1 * len(samples) < len(timeouts) < 0.3 * len(samples)
        assert all(s.status & protocol.STATUS_ECHO_TIMEOUT for s in timeouts)
    else:
        assert not timeouts


def test_split_lines_arrive_in_two_parts_and_decode_whole(procs):
    _, path = start(procs, '--rate', '20', '--split-rate', '0.5', '--seed', '3')
    link = serial.Serial(path, 115200, timeout=0.002)
    pending, started, pauses, lines = b'', None, [], 0
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        data = link.read(4096)
        if not data:
            continue
        now = time.monotonic()
        if pending and started is not None:
            pauses.append(now - started)
        pending += data
        lines += pending.count(b'\n')
        pending = pending[pending.rfind(b'\n') + 1:]
        started = now if pending else None
    link.close()
    assert lines > 30
    assert sum(p >= 0.015 for p in pauses) >= 5       # the second half came ~20 ms later


def test_stall_stops_output_then_resumes_with_a_seq_gap(procs):
    _, path = start(procs, '--rate', '50', '--stall-after', '1.0', '--stall-for', '1.0')
    port = Port(path)
    port.collect(3.0)
    times = [t for t, f in port.arrivals if isinstance(f, Sample)]
    samples = [f for _, f in port.arrivals if isinstance(f, Sample)]
    longest = max(b - a for a, b in itertools.pairwise(times))
    assert 0.85 < longest < 1.3
    sequence = lost_samples(samples)
    assert sequence.lost >= 40 and sequence.gaps == 1   # one gap: the device kept running


def test_disconnect_then_reconnect_on_a_new_pty_with_the_link_re_pointed(procs, tmp_path):
    link = tmp_path / 'ttyPMA'
    proc, _ = start(procs, '--link', link, '--rate', '50', '--disconnect-after', '1.0',
                        '--reconnect-after', '1.0')
    port = Port(link)
    port.send('SET', 150_000)
    with pytest.raises(serial.SerialException):
        port.collect(3.0)                      # the unplug ends the read loop
    before = samples_of(f for _, f in port.arrivals)
    assert before and before[-1].t_ms >= 900
    port.close()
    assert not os.path.lexists(link)           # the device node is gone while unplugged
    deadline = time.monotonic() + 5
    while len(device_lines := [t for t in proc.output.splitlines() if DEVICE_LINE.match(t)]) < 2:
        assert time.monotonic() < deadline, proc.output
        time.sleep(0.05)
    second = DEVICE_LINE.match(device_lines[1]).group(1)   # the kernel may reuse the number
    deadline = time.monotonic() + 2
    while not os.path.lexists(link) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert os.path.realpath(link) == second
    port = Port(link)
    port.send('HELLO')
    frames = port.collect(1.0)
    assert any(isinstance(f, Hello) for f in frames)
    samples = samples_of(frames)
    assert samples and samples[0].t_ms < 1500 and samples[0].seq < 75   # rebooted
    assert samples[-1].setpoint_pa == 0                                 # setpoint lost
    port.close()
    # The stats at the unplug (between the two device lines), then totals again at exit.
    kinds = ['device' if DEVICE_LINE.match(text) else 'stats'
             for text in proc.output.splitlines()
             if DEVICE_LINE.match(text) or STATS_LINE.match(text)]
    assert kinds == ['device', 'stats', 'device']
    proc.signal(signal.SIGINT)
    assert proc.popen.wait(5) == 0
    at_unplug, at_exit = stats_lines(proc.output)
    assert len(before) <= at_unplug['sent'] < at_exit['sent']


def test_bad_options_exit_with_a_message(procs):
    proc = procs.ros2_run('pma_sim', 'fake_arduino', '--rate', '2000')
    assert proc.popen.wait(10) == 2
    proc.wait_for_line('rate_hz must be within', timeout=5)
