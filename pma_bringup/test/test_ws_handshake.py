"""The handshake layer in front of foxglove-sdk (pma_bringup.ws_handshake): the header rewrite,
and the proxy against a stand-in server on 127.0.0.1 (no ROS, no foxglove-sdk)."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from pma_bringup.ws_handshake import (
    HandshakeProxy,
    choose_subprotocol,
    offered_subprotocols,
    rewrite_request,
    rewrite_response,
)

OLD, SDK = 'foxglove.websocket.v1', 'foxglove.sdk.v1'


def request(*protocol_lines: str) -> bytes:
    lines = ['GET / HTTP/1.1', 'Host: 127.0.0.1:8765', 'Upgrade: websocket',
             'Connection: Upgrade', 'Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==',
             *protocol_lines, 'Sec-WebSocket-Version: 13']
    return '\r\n'.join(lines).encode()


SWITCHED = (b'HTTP/1.1 101 Switching Protocols\r\nconnection: Upgrade\r\nupgrade: websocket\r\n'
            b'sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n'
            b'sec-websocket-protocol: foxglove.sdk.v1')


def protocol_values(head: bytes) -> list[str]:
    return [line.split(b':', 1)[1].strip().decode() for line in head.split(b'\r\n')[1:]
            if line.lower().startswith(b'sec-websocket-protocol')]


def test_the_first_name_the_client_lists_that_is_spoken_here_wins():
    assert choose_subprotocol([OLD]) == OLD
    assert choose_subprotocol([SDK, OLD]) == SDK
    assert choose_subprotocol([OLD, SDK]) == OLD
    assert choose_subprotocol(['x', 'foxglove.sdk.v1.1', OLD]) == 'foxglove.sdk.v1.1'
    assert choose_subprotocol(['foxglove.websocket.v2', '']) is None


def test_offered_names_are_read_from_every_header_line_in_order():
    head = request(f'sec-websocket-protocol:  x.y ,{OLD}', f'Sec-WebSocket-Protocol: {SDK}')
    assert offered_subprotocols(head) == ['x.y', OLD, SDK]
    assert offered_subprotocols(request()) == []


@pytest.mark.parametrize('offered,chosen,asked', [
    ([OLD], OLD, SDK), ([SDK], SDK, SDK), ([OLD, SDK], OLD, SDK), ([SDK, OLD], SDK, SDK)])
def test_the_sdk_is_asked_for_its_name_and_the_client_gets_its_own(offered, chosen, asked):
    head = request(f'Sec-WebSocket-Protocol: {", ".join(offered)}')
    rewritten, got = rewrite_request(head)
    assert got == chosen
    assert protocol_values(rewritten) == [asked]
    # everything else as it was, in its order
    assert [line for line in rewritten.split(b'\r\n') if b'Protocol' not in line] == \
        [line for line in head.split(b'\r\n') if b'Protocol' not in line]
    answer = rewrite_response(SWITCHED, got)
    assert protocol_values(answer) == [chosen]
    assert answer.split(b'\r\n')[:4] == SWITCHED.split(b'\r\n')[:4]


def test_what_is_not_spoken_here_passes_unchanged():
    head = request('Sec-WebSocket-Protocol: foxglove.websocket.v2')
    assert rewrite_request(head) == (head, None)
    assert rewrite_request(request()) == (request(), None)
    refused = b'HTTP/1.1 400 Bad Request\r\ncontent-length: 45'
    assert rewrite_response(refused, OLD) == refused
    assert rewrite_response(SWITCHED, None) == SWITCHED


class StandIn:
    """A server on 127.0.0.1 that answers an upgrade as the SDK does, then sends `payload`
    once and echoes what it reads."""

    def __init__(self, payload: bytes = b''):
        self.sock = socket.create_server(('127.0.0.1', 0))
        self.port = self.sock.getsockname()[1]
        self.payload = payload
        self.heads: list[bytes] = []
        self.sent = 0
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self) -> None:
        try:
            self._serve()
        except OSError:          # the proxy closed it: the test is over
            pass

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        with conn:
            data = b''
            while b'\r\n\r\n' not in data:
                data += conn.recv(4096)
            head, rest = data.split(b'\r\n\r\n', 1)
            self.heads.append(head)
            conn.sendall(SWITCHED + b'\r\n\r\n')
            view = memoryview(self.payload)
            while self.sent < len(view):
                self.sent += conn.send(view[self.sent:self.sent + 65536])
            if rest:
                conn.sendall(rest)
            while chunk := conn.recv(4096):
                conn.sendall(chunk)


def read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    data = b''
    while b'\r\n\r\n' not in data:
        data += sock.recv(4096)
    return tuple(data.split(b'\r\n\r\n', 1))


def test_the_proxy_rewrites_the_handshake_then_pipes_bytes_both_ways():
    server = StandIn()
    proxy = HandshakeProxy('127.0.0.1', 0, server.port)
    try:
        with socket.create_connection(('127.0.0.1', proxy.port), timeout=10) as sock:
            sock.sendall(request(f'Sec-WebSocket-Protocol: {OLD}') + b'\r\n\r\nearly')
            head, rest = read_head(sock)
            assert protocol_values(head) == [OLD]
            assert protocol_values(server.heads[0]) == [SDK]
            while len(rest) < 5:
                rest += sock.recv(100)
            assert rest == b'early'
            frame = bytes(range(256)) * 400
            sock.sendall(frame)
            got = b''
            while len(got) < len(frame):
                got += sock.recv(65536)
            assert got == frame
        deadline = time.monotonic() + 5
        while proxy.open_connections() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proxy.open_connections() == 0
    finally:
        proxy.close()
    assert not any(t.name == 'fg-handshake' for t in threading.enumerate())


def test_a_viewer_that_does_not_read_holds_the_server_back_not_the_proxys_memory():
    """64 MB offered to a viewer that reads nothing: the proxy stops reading from the server
    (so the server's own per-client limit applies) instead of buffering it all."""
    server = StandIn(b'x' * 64_000_000)
    proxy = HandshakeProxy('127.0.0.1', 0, server.port)
    try:
        with socket.create_connection(('127.0.0.1', proxy.port), timeout=10) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)
            sock.sendall(request(f'Sec-WebSocket-Protocol: {SDK}') + b'\r\n\r\n')
            read_head(sock)
            time.sleep(1.0)
            sent = server.sent
            time.sleep(0.5)
            assert server.sent == sent, 'the server still sends: nothing holds it back'
            assert sent < 16_000_000, f'{sent} bytes left the server for a viewer reading none'
            buffered = []
            connection = next(iter(proxy.connections))
            proxy.loop.call_soon_threadsafe(
                lambda: buffered.append(connection.client.transport.get_write_buffer_size()))
            time.sleep(0.2)
            assert buffered and buffered[0] <= 1_000_000, buffered
    finally:
        proxy.close()


def test_a_port_in_use_is_refused_at_once():
    taken = socket.create_server(('127.0.0.1', 0))
    try:
        with pytest.raises(OSError, match='Address already in use'):
            HandshakeProxy('127.0.0.1', taken.getsockname()[1], 1)
    finally:
        taken.close()
    assert not any(t.name == 'fg-handshake' for t in threading.enumerate())
