"""SerialLink over a real pty, against a small protocol-v1 device written with protocol.py."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path

import pytest

from pma_common import protocol
from pma_common.protocol import Ack, Command, Hello, Nak
from pma_driver.link import LinkError, LinkState, PortOpenError, SerialLink

CEILING_PA = 500_000


class PtyDevice:
    """A protocol-v1 device on the master side of a pty, reachable through a symlink.

    `unplug()` closes the pty and removes the link, as pulling the USB cable does;
    `replug()` makes a new pty behind the same link.
    """

    def __init__(self, link_path: Path, rate_hz: float = 50.0, answer_hello: bool = True,
                 mute_commands: tuple[str, ...] = ()):
        self.link_path = Path(link_path)
        self.rate_hz = rate_hz
        self.answer_hello = answer_hello
        self.mute_commands = mute_commands
        self.commands: list[protocol.HostCommand] = []
        self.streaming = True      # samples flow (False = stalled device)
        self.lose_every = 0        # > 0: every this many samples, two are lost on the way
        self.seq = 0
        self.t0 = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._master = None
        self._thread = None
        self.replug()

    def replug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self._slave = slave
        self._master = master
        self.seq = 0
        self.t0 = time.monotonic()
        tmp = self.link_path.with_suffix('.tmp')
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.link_path)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def unplug(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.link_path.unlink(missing_ok=True)
        os.close(self._master)
        os.close(self._slave)

    def write(self, data: bytes) -> None:
        with self._lock:
            os.write(self._master, data)

    def hello(self) -> Hello:
        return Hello(1, 'pty_device', '0.0.1', int(self.rate_hz), 1000, CEILING_PA, CEILING_PA,
                     1000)

    def _run(self) -> None:
        decoder = protocol.FrameDecoder(parse=protocol.parse_host_line)
        next_sample = time.monotonic()
        while not self._stop.is_set():
            timeout = max(0.0, next_sample - time.monotonic())
            readable, _, _ = select.select([self._master], [], [], min(timeout, 0.02))
            if readable:
                try:
                    data = os.read(self._master, 4096)
                except OSError:
                    data = b''
                for command in decoder.feed(data):
                    self.commands.append(command)
                    self._answer(command)
            if self.streaming and time.monotonic() >= next_sample:
                next_sample += 1.0 / self.rate_hz
                t_ms = int((time.monotonic() - self.t0) * 1000)
                adc = 102 + self.seq % 5
                self.write(protocol.encode_sample(
                    protocol.Sample(self.seq, t_ms, adc, 583, 0, 0, 0)))
                self.seq = (self.seq + 1) % protocol.U32
                if self.lose_every and self.seq % self.lose_every == 0:
                    self.seq += 2
            elif not self.streaming:
                next_sample = time.monotonic() + 0.02

    def _answer(self, command: protocol.HostCommand) -> None:
        name = command.command
        if name in self.mute_commands:
            return
        if name == 'HELLO':
            if self.answer_hello:
                self.write(protocol.encode_hello(self.hello()))
        elif name == 'HB':
            pass
        elif name in ('SET', 'MAX') and not 0 <= command.args[0] <= CEILING_PA:
            self.write(protocol.encode_nak(name, protocol.NakReason.RANGE))
        elif command.args:
            self.write(protocol.encode_ack(name, command.args[0]))
        else:
            self.write(protocol.encode_ack(name))

    def count(self, name: str) -> int:
        return sum(1 for c in self.commands if c.command == name)


def wait_until(predicate, timeout: float, what) -> float:
    """Seconds until predicate() held; `what` (text, or a callable giving it) names it."""
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > timeout:
            text = what() if callable(what) else what
            raise AssertionError(f'timed out after {timeout} s waiting for {text}')
        time.sleep(0.01)
    return time.monotonic() - start


class Recorder:
    """Collects what the link reports through its callbacks."""

    def __init__(self):
        self.samples: list[tuple[protocol.Sample, int]] = []
        self.hellos: list[Hello] = []
        self.events: list[tuple[int, str]] = []

    def kwargs(self) -> dict:
        return {'on_sample': lambda s, t: self.samples.append((s, t)),
                'on_hello': self.hellos.append,
                'on_event': lambda level, text: self.events.append((level, text))}


@pytest.fixture
def device(tmp_path):
    dev = PtyDevice(tmp_path / 'ttyPMA')
    yield dev
    if dev.link_path.exists():
        dev.unplug()


@pytest.fixture
def make_link():
    links: list[SerialLink] = []

    def make(port, **kwargs) -> SerialLink:
        link = SerialLink(str(port), **kwargs)
        links.append(link)
        return link

    yield make
    for link in links:
        link.stop()


def test_handshake_then_samples_then_startup_commands(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, startup_commands=lambda hello: [
        (Command.RATE, (int(hello.rate_hz),)), (Command.MAX, (400_000,))], **seen.kwargs())
    link.open()
    link.start()
    wait_until(lambda: len(seen.samples) >= 10, 3.0, '10 samples')
    assert link.state is LinkState.STREAMING
    assert seen.hellos == [device.hello()]
    wait_until(lambda: link.stats().acks >= 2, 1.0, 'startup ACKs')
    assert [(c.command, c.args) for c in device.commands if c.command in ('RATE', 'MAX')] == [
        ('RATE', (50,)), ('MAX', (400_000,))]
    stats = link.stats()
    assert stats.connects == 1 and stats.dropped_total == 0 and stats.sequence.lost == 0
    stamps = [t for _, t in seen.samples]
    assert stamps == sorted(stamps)


def test_commands_are_matched_to_their_ack_or_nak(device, make_link):
    link = make_link(device.link_path)
    link.start()
    wait_until(lambda: link.connected, 3.0, 'handshake')
    assert link.send(Command.SET, 250_000) == Ack('SET', 250_000)
    assert link.send(Command.SET, 600_000) == Nak('SET', 'RANGE')
    assert link.send(Command.VENT) == Ack('VENT')
    stats = link.stats()
    assert (stats.acks, stats.naks, stats.last_nak) == (2, 1, 'SET RANGE')


def test_unanswered_command_times_out_and_is_counted(tmp_path, make_link):
    device = PtyDevice(tmp_path / 'tty', mute_commands=('TARE',))
    try:
        link = make_link(device.link_path, command_timeout_s=0.2)
        link.start()
        wait_until(lambda: link.connected, 3.0, 'handshake')
        start = time.monotonic()
        with pytest.raises(LinkError, match='no reply to TARE'):
            link.send(Command.TARE)
        assert time.monotonic() - start < 1.0
        assert link.stats().command_timeouts == 1
    finally:
        device.unplug()


def test_commands_refused_before_handshake(tmp_path, make_link):
    device = PtyDevice(tmp_path / 'tty', answer_hello=False)
    try:
        link = make_link(device.link_path)
        link.start()
        with pytest.raises(LinkError, match='not sent'):
            link.send_async(Command.SET, 1000)
    finally:
        device.unplug()


def test_a_port_that_vanishes_while_it_is_opened_does_not_end_the_link(tmp_path, make_link):
    """A cable pulled between open() and the port's configuration: pyserial then raises
    termios.error (not an OSError), which once ended the link thread for good (seen in CI as
    an unhandled exception in 'pma-link'). Ptys that come and go for a fraction of a
    millisecond hit that window now and then (pyserial's own loop: about one open in 150;
    the link: once in a few thousand reopens, so it runs 5000); the link must keep reopening
    and stream from the device that finally stays."""
    link_path = tmp_path / 'tty'
    seen = Recorder()
    link = make_link(link_path, reconnect_period_s=0.001, **seen.kwargs())
    link.start()
    deadline = time.monotonic() + 20.0
    while link.stats().disconnects < 5000 and time.monotonic() < deadline \
            and link._thread.is_alive():
        master, slave = os.openpty()
        tmp = link_path.with_suffix('.tmp')
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(link_path)
        os.close(slave)
        time.sleep(0.0005)
        os.close(master)
    assert link._thread.is_alive(), 'the link thread died while the port came and went'
    device = PtyDevice(link_path)
    try:
        # Streaming with samples, checked together: CI once saw 3 samples and then the
        # state 'disconnected' at the next look (not reproduced in 85 runs under load; a
        # late read error from a port of the churn is the likely cause). The link must
        # recover from that too, which is the claim; the events say what happened.
        wait_until(lambda: link.state is LinkState.STREAMING and len(seen.samples) >= 3, 5.0,
                   lambda: f'streaming from the device that stayed ({link.state}, '
                           f'{link.stats()}, {seen.events[-5:]})')
    finally:
        device.unplug()


def test_silent_device_is_reported_as_wrong_baud_or_firmware(tmp_path, make_link):
    device = PtyDevice(tmp_path / 'tty', answer_hello=False)
    device.write(b'\x8f\x13garbage at the wrong baud rate\n' * 3)
    try:
        seen = Recorder()
        link = make_link(device.link_path, handshake_timeout_s=0.5, **seen.kwargs())
        link.start()
        wait_until(lambda: link.state is LinkState.NO_HANDSHAKE, 2.0, 'handshake failure')
        stats = link.stats()
        assert 'no HELLO within 0.5 s' in stats.last_error
        assert 'wrong baud rate or not a PMA firmware?' in stats.last_error
        assert not seen.samples and stats.ignored_before_hello > 0
        assert device.count('HELLO') >= 2       # it keeps asking
        time.sleep(1.2)                          # repeats are not logged again
        assert sum('no HELLO' in text for _, text in seen.events) == 1
    finally:
        device.unplug()


def test_bad_lines_are_counted_by_reason_and_streaming_goes_on(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, **seen.kwargs())
    link.start()
    wait_until(lambda: len(seen.samples) >= 3, 3.0, 'samples')
    device.write(b'$S,1,2,3,4,0,0,0*00\n')          # bad checksum
    device.write(b'random noise\n')                  # no frame at all
    device.write(protocol.frame('S', 1, 2) )         # too few fields
    before = len(seen.samples)
    wait_until(lambda: len(seen.samples) >= before + 10, 3.0, 'samples after the junk')
    dropped = link.stats().dropped
    assert dropped == {'checksum': 1, 'framing': 1, 'fields': 1}
    assert link.state is LinkState.STREAMING


def test_sequence_gaps_are_counted(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, **seen.kwargs())
    link.start()
    wait_until(lambda: len(seen.samples) >= 3, 3.0, 'samples')
    device.lose_every = 5                               # two samples lost each time
    wait_until(lambda: link.stats().sequence.gaps >= 4, 2.0, 'gaps')
    sequence = link.stats().sequence
    assert sequence.lost == 2 * sequence.gaps


def test_heartbeats_flow_at_the_configured_period(device, make_link):
    link = make_link(device.link_path, heartbeat_period_s=0.05)
    link.start()
    wait_until(lambda: link.connected, 3.0, 'handshake')
    first = device.count('HB')
    time.sleep(1.0)
    assert 14 <= device.count('HB') - first <= 22


def test_stalled_device_is_reported_and_recovers(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, stall_timeout_s=0.3, **seen.kwargs())
    link.start()
    wait_until(lambda: len(seen.samples) >= 3, 3.0, 'samples')
    device.streaming = False
    wait_until(lambda: link.state is LinkState.STALLED, 1.0, 'stall detected')
    assert 'no data from' in link.stats().state_detail
    device.streaming = True
    wait_until(lambda: link.state is LinkState.STREAMING, 1.0, 'streaming again')


def test_missing_port_at_start_then_appearing(tmp_path, make_link):
    path = tmp_path / 'ttyLATER'
    seen = Recorder()
    link = make_link(path, reconnect_period_s=0.5, **seen.kwargs())
    with pytest.raises(PortOpenError, match='no such device') as error:
        link.open()
    assert error.value.missing and 'retrying every 0.5 s' in str(error.value)
    link.start()
    time.sleep(1.5)
    assert link.state is LinkState.DISCONNECTED
    assert sum('no such device' in text for _, text in seen.events) == 1   # said once
    device = PtyDevice(path)
    try:
        took = wait_until(lambda: len(seen.samples) > 0, 3.0, 'samples after the port appears')
        assert took < 1.5
    finally:
        device.unplug()


def test_unplug_and_replug_resumes_within_two_seconds(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, reconnect_period_s=1.0, **seen.kwargs())
    link.start()
    wait_until(lambda: len(seen.samples) >= 5, 3.0, 'samples')
    device.unplug()
    wait_until(lambda: link.state is LinkState.DISCONNECTED, 1.0, 'disconnect noticed')
    assert 'lost' in link.stats().last_error
    time.sleep(1.5)
    count = len(seen.samples)
    device.replug()
    took = wait_until(lambda: len(seen.samples) > count, 3.0, 'samples after replug')
    assert took < 2.0
    stats = link.stats()
    assert stats.connects == 2 and stats.disconnects == 1 and len(seen.hellos) == 2


def test_device_restart_is_a_new_handshake(device, make_link):
    seen = Recorder()
    link = make_link(device.link_path, **seen.kwargs())
    link.start()
    wait_until(lambda: len(seen.samples) >= 3, 3.0, 'samples')
    device.seq = 0
    device.write(protocol.encode_hello(device.hello()))  # unsolicited banner = reboot
    wait_until(lambda: len(seen.hellos) == 2, 1.0, 'second HELLO')
    assert link.stats().sequence.lost == 0


def test_stop_with_vent_tells_the_device(device, make_link):
    link = make_link(device.link_path)
    link.start()
    wait_until(lambda: link.connected, 3.0, 'handshake')
    link.stop(vent=True)
    wait_until(lambda: device.count('VENT') == 1, 1.0, 'VENT at the device')
    assert link.state is LinkState.STOPPED


def test_permission_denied_names_the_port_and_the_fix():
    master, slave = os.openpty()
    port = os.ttyname(slave)
    root = os.geteuid() == 0
    try:
        os.chmod(port, 0o000)
        if root:
            os.seteuid(65534)   # root opens anything: try it as nobody (the real uid stays 0)
        with pytest.raises(PortOpenError) as error:
            SerialLink(port).open()
    finally:
        if root:
            os.seteuid(0)
        os.close(master)
        os.close(slave)
    message = str(error.value)
    assert f'cannot open {port}: permission denied' in message
    assert 'sudo usermod -aG dialout $USER' in message
    assert 'log out and back in' in message
    assert not error.value.missing


def write_samples(device: PtyDevice, seqs) -> None:
    for seq in seqs:
        device.write(protocol.encode_sample(protocol.Sample(seq, seq * 20, 102, 583, 0, 0, 0)))


def test_out_of_order_and_repeated_sequence_numbers_lose_nothing(device, make_link):
    # One corrupt-but-valid number between 9 and 10 used to count as 65,535 lost samples.
    device.streaming = False
    link = make_link(device.link_path)
    link.start()
    wait_until(lambda: link.connected, 3.0, 'handshake')
    sent = [*range(10), 65546, *range(10, 20), 21, 20, 22, 22, 23, 25, 26, 24, 27, 30, 31]
    write_samples(device, sent)
    wait_until(lambda: link.stats().samples == len(sent), 3.0, 'every sample decoded')
    sequence = link.stats().sequence
    assert (sequence.lost, sequence.gaps) == (2, 1)          # 28 and 29, nothing else
    assert (sequence.stray, sequence.late, sequence.duplicates) == (1, 1, 1)


def test_a_device_restart_resets_the_sequence_accounting(device, make_link):
    device.streaming = False
    link = make_link(device.link_path)
    link.start()
    wait_until(lambda: link.connected, 3.0, 'handshake')
    write_samples(device, range(5000, 5010))
    device.write(protocol.encode_hello(device.hello()))      # rebooted: counting from 0 again
    write_samples(device, range(0, 10))
    wait_until(lambda: link.stats().samples == 20, 3.0, 'every sample decoded')
    sequence = link.stats().sequence
    assert (sequence.lost, sequence.gaps, sequence.duplicates, sequence.restarts) == (0, 0, 0, 0)


def test_a_second_link_on_the_same_port_is_refused_while_the_first_holds_it(device, make_link):
    """Two drivers on one port used to both run, each reading half of the device's lines
    (the first then reported 1 Hz and lost samples); the second is now refused, and takes the
    port once the first lets go."""
    first = make_link(device.link_path)
    first.open()
    with pytest.raises(PortOpenError) as error:
        make_link(device.link_path).open()
    message = str(error.value)
    assert f'cannot open {device.link_path}: another process holds it' in message
    assert 'second driver_node' in message and 'fuser' in message
    first.stop()
    make_link(device.link_path).open()
