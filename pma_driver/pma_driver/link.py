"""The serial link to the PMA firmware: open, handshake, read, heartbeat, reconnect.

Plain Python, no ROS (the driver node wraps it). One thread owns the port: it opens it
(a /dev/serial/by-id/... path or a udev symlink works like any path), waits for the
firmware's HELLO (opening resets an Arduino), decodes lines with protocol.FrameDecoder,
sends heartbeats, matches ACK/NAK replies to commands and, when the port goes away,
reopens it with a short backoff capped at `reconnect_period_s`. Callbacks run on that
thread and must return quickly.
"""

from __future__ import annotations

import collections
import enum
import errno
import logging
import math
import termios
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import serial

from pma_common import protocol
from pma_common.protocol import Ack, Command, Hello, Nak, Sample
from pma_common.sequence import SequenceStats, SequenceTracker

# What a port that goes away can raise from pyserial: a pulled cable between open() and the
# port's configuration or a flush surfaces as termios.error, which is not an OSError.
PORT_ERRORS = (serial.SerialException, OSError, termios.error)

_log = logging.getLogger('pma_driver.link')

DIALOUT_FIX = ('add your user to the dialout group: `sudo usermod -aG dialout $USER`, '
               'then log out and back in (or install a udev rule giving the device mode 0666)')


class LinkState(enum.Enum):
    STOPPED = 'stopped'
    DISCONNECTED = 'disconnected'          # port not open; retrying
    HANDSHAKE = 'handshake pending'        # port open, waiting for HELLO
    NO_HANDSHAKE = 'no answer to handshake'
    STREAMING = 'streaming'
    STALLED = 'no data'                    # handshake done, but the samples stopped


class LinkError(RuntimeError):
    """A command could not be sent or was not answered."""


class PortOpenError(LinkError):
    """The port could not be opened; the message names the port, the error and the fix."""

    def __init__(self, message: str, errno_: int | None):
        super().__init__(message)
        self.errno = errno_

    @property
    def missing(self) -> bool:
        return self.errno in (errno.ENOENT, errno.ENODEV, errno.ENXIO)


Reply = Ack | Nak | None   # None: no reply within the command timeout (or link lost)


def describe_open_error(port: str, error: BaseException, reconnect_period_s: float) -> str:
    """One line a user can act on: the port, what went wrong and the fix."""
    code = getattr(error, 'errno', None)
    if isinstance(error, PermissionError) or code in (errno.EACCES, errno.EPERM):
        return f'cannot open {port}: permission denied. Fix: {DIALOUT_FIX}'
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
        return (f'cannot open {port}: no such device (unplugged, or a wrong path?); retrying '
                f'every {reconnect_period_s:g} s. Tip: a /dev/serial/by-id/... path survives '
                f'replugging')
    if code == errno.EBUSY:
        return f'cannot open {port}: busy (another program has it open?)'
    if code in (errno.EAGAIN, errno.EWOULDBLOCK):
        return (f'cannot open {port}: another process holds it (a second driver_node on the '
                f'same port?). The port is opened exclusively, so two drivers never command '
                f'one muscle; `fuser {port}` names the holder. Retrying every '
                f'{reconnect_period_s:g} s')
    return f'cannot open {port}: {error}'


@dataclass
class LinkStats:
    """A snapshot of the link's counters (for diagnostics)."""

    state: LinkState
    state_detail: str
    hello: Hello | None
    frames: int
    samples: int
    dropped: dict[str, int]
    sequence: SequenceStats  # samples lost, late, repeated or stray, by their `seq`
    acks: int
    naks: int
    command_timeouts: int
    connects: int            # successful handshakes since start
    disconnects: int
    last_error: str
    last_nak: str
    ignored_before_hello: int

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())


@dataclass
class _Pending:
    command: str
    sent_at: float
    callback: Callable[[Reply], None] | None
    done: threading.Event = field(default_factory=threading.Event)
    reply: Reply = None


StartupCommands = Callable[[Hello], Sequence[tuple[Command, tuple[int, ...]]]]


class SerialLink:
    """The host side of protocol v1 over one serial port."""

    def __init__(self, port: str, baud: int = 115200, *,
                 on_sample: Callable[[Sample, int], None] | None = None,
                 on_hello: Callable[[Hello], None] | None = None,
                 on_event: Callable[[int, str], None] | None = None,
                 startup_commands: StartupCommands | None = None,
                 receive_clock_ns: Callable[[], int] = time.monotonic_ns,
                 reconnect_period_s: float = 1.0, handshake_timeout_s: float = 2.0,
                 heartbeat_period_s: float = 0.2, command_timeout_s: float = 0.5,
                 stall_timeout_s: float = 1.0):
        self.port = port
        self.baud = int(baud)
        self.on_sample = on_sample
        self.on_hello = on_hello
        self.on_event = on_event or _log.log
        self.startup_commands = startup_commands
        self.receive_clock_ns = receive_clock_ns
        self.reconnect_period_s = reconnect_period_s
        self.handshake_timeout_s = handshake_timeout_s
        self.heartbeat_period_s = heartbeat_period_s
        self.command_timeout_s = command_timeout_s
        self.stall_timeout_s = stall_timeout_s

        self._serial: serial.Serial | None = None
        self._write_lock = threading.Lock()
        self._lock = threading.Lock()            # counters, state and pending replies
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._decoder = protocol.FrameDecoder(drop_first_partial=True)
        self._pending: collections.deque[_Pending] = collections.deque()
        self._state = LinkState.STOPPED
        self._state_detail = ''
        self._hello: Hello | None = None
        # What is missing, told apart from late, repeated and stray numbers: counting how far
        # the number jumped made one corrupt-but-valid seq thousands of "lost" samples.
        self._sequence = SequenceTracker()
        self._samples = 0
        self._acks = 0
        self._naks = 0
        self._timeouts = 0
        self._connects = 0
        self._disconnects = 0
        self._ignored = 0
        self._last_error = ''
        self._last_nak = ''
        self._last_event_text = ''
        self._open_attempts = 0

    # -- public API ---------------------------------------------------------------------

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def hello(self) -> Hello | None:
        return self._hello

    @property
    def connected(self) -> bool:
        return self._state in (LinkState.STREAMING, LinkState.STALLED)

    def open(self) -> None:
        """Open the port now (raises PortOpenError); `start()` then takes it over."""
        if self._serial is None:
            self._serial = self._open_port()
            self._after_open()

    def start(self) -> None:
        """Start the link thread; it opens the port itself if `open()` was not called."""
        if self._thread is not None:
            return
        self._stop.clear()
        if self._serial is None:
            self._set_state(LinkState.DISCONNECTED, 'opening')
        self._thread = threading.Thread(target=self._run, name=f'pma-link {self.port}',
                                        daemon=True)
        self._thread.start()

    def stop(self, vent: bool = False) -> None:
        """Stop the thread and close the port; with `vent`, tell the device to vent first."""
        if vent and self._serial is not None:
            try:
                self._write(protocol.encode_command(Command.VENT))
            except LinkError:
                pass
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close()
        self._fail_pending()
        self._set_state(LinkState.STOPPED, '')

    def send_async(self, command: Command, *args: int,
                   on_reply: Callable[[Reply], None] | None = None) -> None:
        """Send a command; `on_reply(Ack | Nak | None)` runs on the link thread on its answer.

        Raises LinkError when there is no handshaken device to send to.
        """
        if not self.connected:
            raise LinkError(f'{command.value} not sent: link {self._state.value}')
        pending = _Pending(command.value, time.monotonic(), on_reply)
        with self._lock:
            self._pending.append(pending)
        try:
            self._write(protocol.encode_command(command, *args))
        except LinkError:
            with self._lock:
                if pending in self._pending:
                    self._pending.remove(pending)
            raise

    def send(self, command: Command, *args: int, timeout: float | None = None) -> Ack | Nak:
        """Send a command and wait for its ACK or NAK; LinkError on no answer.

        Blocks the caller: never call it from a link callback (use `send_async` there).
        """
        done = threading.Event()
        replies: list[Reply] = []

        def on_reply(reply: Reply) -> None:
            replies.append(reply)
            done.set()

        self.send_async(command, *args, on_reply=on_reply)
        wait = (self.command_timeout_s if timeout is None else timeout) + 0.5
        if not done.wait(wait) or replies[0] is None:
            raise LinkError(f'no reply to {command.value} within {self.command_timeout_s:g} s')
        return replies[0]

    def stats(self) -> LinkStats:
        with self._lock:
            return LinkStats(
                state=self._state, state_detail=self._state_detail, hello=self._hello,
                frames=self._decoder.frames, samples=self._samples,
                dropped=dict(self._decoder.dropped), sequence=self._sequence.stats(),
                acks=self._acks, naks=self._naks,
                command_timeouts=self._timeouts, connects=self._connects,
                disconnects=self._disconnects, last_error=self._last_error,
                last_nak=self._last_nak, ignored_before_hello=self._ignored)

    # -- the link thread -----------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._serial is None:
                try:
                    self._serial = self._open_port()
                except PortOpenError as error:
                    self._set_state(LinkState.DISCONNECTED, str(error))
                    self._event(logging.ERROR, str(error), dedupe=True)
                    self._open_attempts += 1
                    backoff = min(self.reconnect_period_s, 0.1 * 2 ** (self._open_attempts - 1))
                    self._stop.wait(backoff)
                    continue
                self._after_open()
            try:
                data = self._serial.read(self._serial.in_waiting or 1)
            except (*PORT_ERRORS, TypeError, AttributeError) as error:
                # TypeError/AttributeError: pyserial on a port closed under it by stop().
                if not self._stop.is_set():
                    self._lost_port(error)
                continue
            if data:
                received_ns = self.receive_clock_ns()
                with self._lock:   # stats() copies the decoder's counters
                    frames = self._decoder.feed(data)
                for frame in frames:
                    self._dispatch(frame, received_ns)
            self._housekeeping(time.monotonic())

    def _open_port(self) -> serial.Serial:
        try:
            # exclusive: an advisory lock (flock), so a second driver is refused, not fed
            # half of the device's lines.
            port = serial.Serial(self.port, self.baud, timeout=0.05, write_timeout=0.5,
                                 exclusive=True)
        except (*PORT_ERRORS, ValueError) as error:
            message = describe_open_error(self.port, error, self.reconnect_period_s)
            with self._lock:
                self._last_error = message
            raise PortOpenError(message, getattr(error, 'errno', None)) from error
        return port

    def _after_open(self) -> None:
        self._open_attempts = 0
        self._last_event_text = ''
        self._decoder.reset(drop_first_partial=True)
        try:
            self._serial.reset_input_buffer()
        except PORT_ERRORS:
            pass
        with self._lock:
            self._sequence.reset()      # a reopened port may be a rebooted device
        now = time.monotonic()
        self._handshake_deadline = now + self.handshake_timeout_s
        self._next_hello = now
        self._last_sample_at = now
        self._next_heartbeat = now
        self._set_state(LinkState.HANDSHAKE, f'waiting for HELLO from {self.port}')
        self._event(logging.INFO, f'opened {self.port} at {self.baud} baud; waiting for HELLO')

    def _lost_port(self, error: BaseException) -> None:
        message = f'lost {self.port}: {error}; reopening every {self.reconnect_period_s:g} s'
        with self._lock:
            self._disconnects += 1
            self._last_error = message
        self._close()
        self._fail_pending()
        self._set_state(LinkState.DISCONNECTED, message)
        self._event(logging.ERROR, message)
        self._stop.wait(min(0.1, self.reconnect_period_s))

    def _close(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            try:
                port.close()
            except PORT_ERRORS:
                pass

    def _dispatch(self, frame: protocol.Frame, received_ns: int) -> None:
        if isinstance(frame, Sample):
            self._last_sample_at = time.monotonic()
            if self._state is LinkState.STALLED:
                self._set_state(LinkState.STREAMING, '')
                self._event(logging.INFO, f'samples from {self.port} again')
            if self._state is not LinkState.STREAMING:
                with self._lock:
                    self._ignored += 1
                return
            with self._lock:
                self._samples += 1
                self._sequence.add(frame.seq)
            if self.on_sample is not None:
                self.on_sample(frame, received_ns)
        elif isinstance(frame, Hello):
            self._on_hello(frame)
        elif isinstance(frame, Ack | Nak):
            self._on_reply(frame)

    def _on_hello(self, hello: Hello) -> None:
        if hello.proto != protocol.PROTOCOL_VERSION:
            message = (f'{self.port} speaks protocol v{hello.proto}, this driver '
                       f'v{protocol.PROTOCOL_VERSION}: update the firmware or the driver')
            self._set_state(LinkState.NO_HANDSHAKE, message)
            self._event(logging.ERROR, message, dedupe=True)
            with self._lock:
                self._last_error = message
            # It answered, just in the wrong version: no "no HELLO" timeout may hide that.
            self._handshake_deadline = math.inf
            return
        restarted = self._state in (LinkState.STREAMING, LinkState.STALLED)
        with self._lock:
            self._hello = hello
            self._connects += 1
            self._sequence.reset()      # the device (re)started: its seq counts from 0 again
        self._last_sample_at = time.monotonic()
        self._set_state(LinkState.STREAMING, '')
        self._event(logging.INFO if not restarted else logging.WARNING,
                    f'{"device restarted: " if restarted else ""}{hello.firmware} '
                    f'{hello.fw_version} on {self.port} (protocol v{hello.proto}, '
                    f'{hello.rate_hz} Hz, ceiling {hello.ceiling_pa} Pa)')
        if self.on_hello is not None:
            self.on_hello(hello)
        if self.startup_commands is not None:
            for command, args in self.startup_commands(hello):
                try:
                    self.send_async(command, *args, on_reply=self._startup_reply(command, args))
                except LinkError as error:
                    self._event(logging.WARNING, str(error))

    def _startup_reply(self, command: Command, args: tuple[int, ...]):
        def report(reply: Reply) -> None:
            if not isinstance(reply, Ack):
                what = 'no reply' if reply is None else f'NAK {reply.reason}'
                self._event(logging.ERROR, f'device refused {command.value} {args}: {what}')
        return report

    def _on_reply(self, reply: Ack | Nak) -> None:
        with self._lock:
            if isinstance(reply, Ack):
                self._acks += 1
            else:
                self._naks += 1
                self._last_nak = f'{reply.command} {reply.reason}'
            match = next((p for p in self._pending if p.command == reply.command), None)
            if match is None and isinstance(reply, Nak) and reply.command == '?':
                match = self._pending[0] if self._pending else None
            if match is not None:
                self._pending.remove(match)
        if match is not None:
            self._complete(match, reply)

    def _complete(self, pending: _Pending, reply: Reply) -> None:
        pending.reply = reply
        pending.done.set()
        if pending.callback is not None:
            try:
                pending.callback(reply)
            except Exception:  # a caller's bug must not kill the link thread
                _log.exception('reply callback failed')

    def _fail_pending(self) -> None:
        with self._lock:
            pending, self._pending = list(self._pending), collections.deque()
        for item in pending:
            self._complete(item, None)

    def _housekeeping(self, now: float) -> None:
        state = self._state
        if state in (LinkState.HANDSHAKE, LinkState.NO_HANDSHAKE):
            if now >= self._next_hello:
                self._try_write(protocol.encode_command(Command.HELLO))
                self._next_hello = now + self.handshake_timeout_s / 4
            if now >= self._handshake_deadline:
                self._handshake_deadline = now + self.handshake_timeout_s
                message = (f'no HELLO within {self.handshake_timeout_s:g} s from {self.port} at '
                           f'{self.baud} baud: wrong baud rate or not a PMA firmware?')
                with self._lock:
                    self._last_error = message
                self._set_state(LinkState.NO_HANDSHAKE, message)
                self._event(logging.ERROR, message, dedupe=True)
        elif state in (LinkState.STREAMING, LinkState.STALLED):
            # No heartbeats while stalled: a host that cannot see the pressure must not keep
            # the device from venting (it vents after its heartbeat timeout).
            if state is LinkState.STREAMING and now >= self._next_heartbeat:
                self._try_write(protocol.encode_command(Command.HEARTBEAT))
                self._next_heartbeat = now + self.heartbeat_period_s
            silent = now - self._last_sample_at
            if state is LinkState.STREAMING and silent > self.stall_timeout_s:
                message = f'no data from {self.port} for {silent:.1f} s'
                with self._lock:
                    self._last_error = message
                self._set_state(LinkState.STALLED, message)
                self._event(logging.WARNING, message)
                self._next_hello = now + self.handshake_timeout_s
            elif state is LinkState.STALLED and now >= self._next_hello:
                # Probe: a device that reset (or lost our heartbeats) answers HELLO.
                self._try_write(protocol.encode_command(Command.HELLO))
                self._next_hello = now + self.handshake_timeout_s
        expired: list[_Pending] = []
        with self._lock:
            while self._pending and now - self._pending[0].sent_at > self.command_timeout_s:
                expired.append(self._pending.popleft())
                self._timeouts += 1
        for item in expired:
            self._complete(item, None)

    def _write(self, data: bytes) -> None:
        port = self._serial
        if port is None:
            raise LinkError(f'{self.port} is not open')
        try:
            with self._write_lock:
                port.write(data)
        except (*PORT_ERRORS, TypeError, AttributeError) as error:
            raise LinkError(f'write to {self.port} failed: {error}') from error

    def _try_write(self, data: bytes) -> None:
        try:
            self._write(data)
        except LinkError:
            pass  # the reader notices a lost port and reconnects

    def _set_state(self, state: LinkState, detail: str) -> None:
        with self._lock:
            self._state = state
            self._state_detail = detail

    def _event(self, level: int, message: str, dedupe: bool = False) -> None:
        """Report to the owner; `dedupe` silences a repeat of the same message (retry loops)."""
        if dedupe and message == self._last_event_text:
            return
        self._last_event_text = message
        try:
            self.on_event(level, message)
        except Exception:
            _log.exception('event callback failed')
