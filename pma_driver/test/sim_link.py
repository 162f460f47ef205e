"""The host side of protocol v1 over an in-memory wire to a SimDevice, in simulated time.

What SerialLink offers DeviceControl (state, hello, send, send_async), with the device's
bytes going through the real encoder, SimDevice.receive and the real FrameDecoder. Time is
the device's: `SimClock.sleep` advances it (sending heartbeats as the link thread would), so
a sweep that holds for minutes runs in milliseconds and every timeout is exact.
"""

from __future__ import annotations

from collections.abc import Callable

from pma_common import protocol
from pma_common.protocol import Ack, Command, Hello, Nak, Sample
from pma_driver.link import LinkError, LinkState
from pma_sim.device import SimDevice


class SimLink:
    def __init__(self, device: SimDevice, on_sample: Callable[[Sample], None] | None = None,
                 heartbeat_period_ms: int = 200, command_timeout_ms: int = 500):
        self.device = device
        self.on_sample = on_sample
        self.heartbeat_period_ms = heartbeat_period_ms
        self.command_timeout_ms = command_timeout_ms
        self.state = LinkState.HANDSHAKE
        self.hello: Hello | None = None
        self.lost_replies = 0             # the next this many replies are lost on the wire
        # > 0: send_async answers after this many device ms (as a real serial link does),
        # from `advance`; 0: at once, inside send_async.
        self.reply_delay_ms = 0
        self._delayed: list[tuple[int, object, object]] = []   # (due ms, callback, reply)
        self.sent: list[tuple[int, str, tuple[int, ...]]] = []   # (device ms, command, args)
        self._decoder = protocol.FrameDecoder()
        self._next_heartbeat_ms = 0
        self._read()                      # the boot banner

    @property
    def connected(self) -> bool:
        return self.state in (LinkState.STREAMING, LinkState.STALLED)

    def advance(self, ms: int) -> None:
        for _ in range(ms):
            if self.connected and self.device.t_ms >= self._next_heartbeat_ms:
                self._write(Command.HEARTBEAT)
                self._next_heartbeat_ms = self.device.t_ms + self.heartbeat_period_ms
            self.device.advance(1)
            self._read()
            due = [d for d in self._delayed if d[0] <= self.device.t_ms]
            self._delayed = [d for d in self._delayed if d[0] > self.device.t_ms]
            for _, callback, reply in due:
                callback(reply)

    def send(self, command: Command, *args: int, timeout: float | None = None) -> Ack | Nak:
        if not self.connected:
            raise LinkError(f'{command.value} not sent: link {self.state.value}')
        replies = [r for r in self._write(command, *args) if r.command == command.value]
        if self.lost_replies or not replies:
            self.lost_replies = max(0, self.lost_replies - 1)
            self.advance(self.command_timeout_ms)
            raise LinkError(f'no reply to {command.value} within '
                            f'{self.command_timeout_ms / 1000:g} s')
        return replies[0]

    def send_async(self, command: Command, *args: int, on_reply=None) -> None:
        try:
            reply = self.send(command, *args)
        except LinkError:
            if not self.connected:
                raise
            reply = None
        if on_reply is None:
            return
        if self.reply_delay_ms:
            self._delayed.append((self.device.t_ms + self.reply_delay_ms, on_reply, reply))
        else:
            on_reply(reply)

    def commands(self, name: str) -> list[tuple[int, ...]]:
        return [args for _, command, args in self.sent if command == name]

    def _write(self, command: Command, *args: int) -> list[Ack | Nak]:
        self.sent.append((self.device.t_ms, command.value, args))
        self.device.receive(protocol.encode_command(command, *args))
        return self._read()

    def _read(self) -> list[Ack | Nak]:
        replies = []
        for frame in self._decoder.feed(b''.join(self.device.take_output())):
            if isinstance(frame, Hello):
                self.hello = frame
                self.state = LinkState.STREAMING
            elif isinstance(frame, Sample) and self.on_sample is not None:
                self.on_sample(frame)
            elif isinstance(frame, Ack | Nak):
                replies.append(frame)
        return replies


class SimClock:
    """Simulated seconds; `sleep` runs the device (and its link) for that long."""

    def __init__(self, link: SimLink, on_tick: Callable[[float], None] | None = None):
        self.link = link
        self.on_tick = on_tick    # called after every sleep with the time: events mid-run

    def __call__(self) -> float:
        return self.link.device.t_ms / 1000.0

    def sleep(self, seconds: float) -> None:
        self.link.advance(max(1, round(seconds * 1000)))
        if self.on_tick is not None:
            self.on_tick(self())

