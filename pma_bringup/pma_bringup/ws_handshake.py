"""A thin handshake layer in front of foxglove-sdk's WebSocket server (docs/live-view.md).

foxglove-sdk (0.30.3) accepts only the subprotocols `foxglove.sdk.v1` and `foxglove.sdk.v1.1`
and answers HTTP 400 to a client that offers only `foxglove.websocket.v1`, the name the
protocol's published specification gives and that PlotJuggler, Lichtblick before late 2025,
older Foxglove Studio and roslibjs-foxglove still offer; it has no setting for it. The two
names are the same protocol. So the public port is served here: the first HTTP request of a
connection (the upgrade) has its `Sec-WebSocket-Protocol` header rewritten to the name the SDK
speaks, the SDK's answer gets the name the client chose back, and from then on the bytes are
piped both ways untouched. The SDK server listens on an ephemeral loopback port.

One asyncio loop in one thread serves every connection (no thread per client); reading from
one side pauses while the other side's send buffer is full, so a slow viewer slows the SDK's
socket to it and the SDK's own per-client backlog (drop oldest) still applies. A connection
that does not finish its request head within HANDSHAKE_TIMEOUT_S, or sends a head larger than
MAX_HEAD_BYTES, is closed.
"""

from __future__ import annotations

import asyncio
import ctypes
import re
import socket
import threading

# What a client may offer, in no order; the value is the name the SDK is asked for.
SUBPROTOCOLS = {
    'foxglove.websocket.v1': 'foxglove.sdk.v1',   # the published spec's name: the same protocol
    'foxglove.sdk.v1': 'foxglove.sdk.v1',
    'foxglove.sdk.v1.1': 'foxglove.sdk.v1.1',     # foxglove-sdk 0.30.3 accepts it: passed on
}
HANDSHAKE_TIMEOUT_S = 10.0
MAX_HEAD_BYTES = 64 * 1024
THREAD_NAME = 'fg-handshake'
_PROTOCOL_HEADER = re.compile(rb'^sec-websocket-protocol[ \t]*:(.*)$', re.IGNORECASE)
_END = b'\r\n\r\n'


def choose_subprotocol(offered: list[str]) -> str | None:
    """The first name the client lists that is spoken here, or None."""
    return next((name for name in offered if name in SUBPROTOCOLS), None)


def _split_head(head: bytes) -> tuple[list[bytes], list[bytes]]:
    """(the protocol header lines' values, every other line) of a request/response head."""
    values, others = [], []
    for line in head.split(b'\r\n'):
        match = _PROTOCOL_HEADER.match(line)
        if match and others:          # never the request/status line
            values.append(match.group(1))
        else:
            others.append(line)
    return values, others


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols a request head offers, in its order (every header line, comma lists)."""
    values, _ = _split_head(head)
    return [name.strip() for value in values
            for name in value.decode('latin-1').split(',') if name.strip()]


def _with_protocol(head: bytes, name: str) -> bytes:
    """`head` (without its final blank line) with one protocol header of value `name`."""
    _, others = _split_head(head)
    return b'\r\n'.join([*others, b'Sec-WebSocket-Protocol: ' + name.encode('latin-1')])


def rewrite_request(head: bytes) -> tuple[bytes, str | None]:
    """(the request head for the SDK, the name the client gets); unchanged if none is spoken
    here (the SDK then refuses it as before)."""
    chosen = choose_subprotocol(offered_subprotocols(head))
    if chosen is None:
        return head, None
    return _with_protocol(head, SUBPROTOCOLS[chosen]), chosen


def rewrite_response(head: bytes, chosen: str | None) -> bytes:
    """The SDK's answer with the client's name, if it switched protocols to the SDK's name."""
    if chosen is None or not head.startswith(b'HTTP/1.1 101'):
        return head
    values, _ = _split_head(head)
    if [v.strip().decode('latin-1') for v in values] != [SUBPROTOCOLS[chosen]]:
        return head
    return _with_protocol(head, chosen)


class _Side(asyncio.Protocol):
    """One socket of a proxied connection; what it reads goes to its peer."""

    def __init__(self, connection: _Connection):
        self.connection = connection
        self.transport: asyncio.Transport | None = None
        self.peer: _Side | None = None
        self.head: bytearray | None = bytearray()     # until the head has passed

    def connection_made(self, transport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        if self.head is None:
            self.peer.transport.write(data)
            return
        self.head += data
        end = self.head.find(_END)
        if end < 0:
            if len(self.head) > MAX_HEAD_BYTES:
                self.connection.close()
            return
        head, rest = bytes(self.head[:end]), bytes(self.head[end + len(_END):])
        self.head = None
        self.on_head(head, rest)

    def on_head(self, head: bytes, rest: bytes) -> None:
        raise NotImplementedError

    def eof_received(self):
        self.connection.close()
        return False

    def connection_lost(self, exc) -> None:
        self.connection.close()

    # The peer's send buffer is full: stop reading here until it drains.
    def pause_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.resume_reading()


class _ClientSide(_Side):
    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self.connection.timer = self.connection.loop.call_later(
            HANDSHAKE_TIMEOUT_S, self.connection.handshake_timed_out)

    def on_head(self, head: bytes, rest: bytes) -> None:
        self.transport.pause_reading()            # until the SDK's side is connected
        request, self.connection.chosen = rewrite_request(head)
        self.connection.opening = self.connection.loop.create_task(    # kept: not collected
            self.connection.open_backend(request + _END + rest))


class _BackendSide(_Side):
    def on_head(self, head: bytes, rest: bytes) -> None:
        self.connection.handshake_done()
        self.peer.transport.write(rewrite_response(head, self.connection.chosen) + _END + rest)


class _Connection:
    """A viewer's connection and the one it gets to the SDK's server."""

    def __init__(self, proxy: HandshakeProxy):
        self.proxy = proxy
        self.loop = proxy.loop
        self.client = _ClientSide(self)
        self.backend: _BackendSide | None = None
        self.chosen: str | None = None
        self.timer: asyncio.TimerHandle | None = None
        self.opening: asyncio.Task | None = None
        self.closed = False
        proxy.connections.add(self)

    async def open_backend(self, first: bytes) -> None:
        if self.closed:
            return
        self.backend = _BackendSide(self)
        try:
            await self.loop.create_connection(lambda: self.backend, '127.0.0.1',
                                              self.proxy.backend_port)
        except OSError:
            self.close()
            return
        if self.closed:                    # the viewer left while we connected
            self.backend.transport.close()
            return
        self.backend.peer, self.client.peer = self.client, self.backend
        self.backend.transport.write(first)
        self.client.transport.resume_reading()

    def handshake_done(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None

    def handshake_timed_out(self) -> None:
        self.timer = None
        self.close()

    def close(self, abort: bool = False) -> None:
        """Both sides, after what each still has to send (transport.close flushes), or at
        once (`abort`: the server stops)."""
        if self.closed:
            return
        self.closed = True
        self.handshake_done()
        if abort and self.opening is not None:
            self.opening.cancel()
        for side in (self.client, self.backend):
            if side is not None and side.transport is not None:
                if abort:
                    side.transport.abort()
                else:
                    side.transport.close()
        self.proxy.connections.discard(self)


def _name_this_thread(name: str) -> None:
    """The OS thread's name (top -H, /proc/PID/task/*/comm); best effort, Linux only."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, name.encode()[:15], 0, 0, 0)     # PR_SET_NAME
    except (OSError, AttributeError):
        pass


class HandshakeProxy:
    """Listens on (host, port) and passes each connection to 127.0.0.1:backend_port.

    The listening socket is bound in the constructor, so a port in use raises OSError there
    (EADDRINUSE), before anything runs. `close()` stops accepting, closes every connection and
    ends the thread.
    """

    def __init__(self, host: str, port: int, backend_port: int):
        self.backend_port = backend_port
        self.connections: set[_Connection] = set()
        self.sock = _listen(host, port)
        self.port = self.sock.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        self._server: asyncio.base_events.Server | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=THREAD_NAME, daemon=True)
        self._thread.start()
        self._started.wait(10)
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        _name_this_thread(THREAD_NAME)
        asyncio.set_event_loop(self.loop)
        try:
            self._server = self.loop.run_until_complete(self.loop.create_server(
                lambda: _Connection(self).client, sock=self.sock))
        except BaseException as exc:       # reported by the constructor
            self._error = exc
            self._started.set()
            self.loop.close()
            return
        self._started.set()
        try:
            self.loop.run_forever()
        finally:
            self.loop.close()

    def open_connections(self) -> int:
        return len(self.connections)

    def close(self) -> None:
        if not self._thread.is_alive():
            return

        def shut() -> None:
            self._server.close()
            for connection in list(self.connections):
                connection.close(abort=True)
            self.loop.call_later(0.1, self.loop.stop)     # the transports' own callbacks

        self.loop.call_soon_threadsafe(shut)
        self._thread.join(5)


def _listen(host: str, port: int) -> socket.socket:
    """A listening TCP socket on (host, port): dual-stack for '::', as the SDK did."""
    if host == '::' and socket.has_dualstack_ipv6():
        return socket.create_server((host, port), family=socket.AF_INET6, backlog=128,
                                    dualstack_ipv6=True)
    family, _, _, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                  flags=socket.AI_PASSIVE)[0]
    return socket.create_server(address, family=family, backlog=128)
