"""A Foxglove WebSocket protocol client, as the Foxglove app speaks it: foxglove_live's tests,
its bench (bench/bench_foxglove.py) and anyone checking a running live view without the app.

foxglove_live answers subprotocol `foxglove.websocket.v1` (the published spec's name) and
`foxglove.sdk.v1` (foxglove-sdk's, and foxglove_bridge 3.x's), whichever the client lists first;
`FoxgloveClient(url, subprotocols=[...])` offers what a given viewer offers (default: both) and
`.subprotocol` is the one the server chose. Text frames are JSON: `serverInfo`, `advertise`
({channels: [{id, topic, encoding, schemaName, schema, schemaEncoding}]}), `unadvertise`,
`status`. After {"op": "subscribe", "subscriptions": [{"id", "channelId"}]} the server sends
binary frames: 0x01, subscription id (uint32 LE), log time (uint64 LE, ns), the payload.

`FoxgloveClient.follow(topics)` subscribes to each of those topics whenever a channel for it
is advertised, now or later (a restarted type gets a new channel), the way the app does.

foxglove-sdk 0.30.3 queues a channel's `advertise` to a client before it records the channel
for that client, so a client that subscribes at once can be answered "Unknown channel ID"
(seen here under load, when a topic appears while a client is connected). This client then
subscribes again; `refused` counts how often that happened.
"""

from __future__ import annotations

import json
import re
import struct
import threading
import time
from dataclasses import dataclass

from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import connect

SUBPROTOCOLS = ['foxglove.sdk.v1', 'foxglove.websocket.v1']
MESSAGE_DATA = 0x01
_HEADER = struct.Struct('<BIQ')
_UNKNOWN = re.compile(r'Unknown channel ID: (\d+)')


@dataclass
class Received:
    topic: str
    channel_id: int
    log_time_ns: int
    payload: bytes
    received_ns: int          # time.time_ns() when the frame arrived here


class FoxgloveClient:
    def __init__(self, url: str, timeout: float = 10.0,
                 subprotocols: list[str] | tuple[str, ...] = SUBPROTOCOLS):
        self.url = url
        self.offered = list(subprotocols)
        self.subprotocol: str | None = None          # what the server answered
        self.ws = None
        self.server_info: dict | None = None
        self.channels: dict[int, dict] = {}          # advertised, by channel id
        self.unadvertised: list[int] = []
        self.refused = 0                              # subscriptions answered "unknown channel"
        self.messages: list[Received] = []
        self._followed: set[str] = set()
        self._subscriptions: dict[int, int] = {}      # subscription id -> channel id
        self._next_id = 1
        self._cond = threading.Condition()
        self._closed = False
        self._opened = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._pump, args=(timeout,), daemon=True)
        self._thread.start()
        if not self._opened.wait(timeout + 5) or self.ws is None:
            raise ConnectionError(f'could not connect to {url}: {self._error}')

    # -- frames --------------------------------------------------------------------------------

    def _pump(self, timeout: float) -> None:
        try:
            with connect(self.url, subprotocols=self.offered, max_size=None,
                         open_timeout=timeout, compression=None) as ws:
                self.ws = ws
                self.subprotocol = ws.subprotocol
                self._opened.set()
                for frame in ws:
                    if isinstance(frame, bytes):
                        self._on_binary(frame)
                    else:
                        self._on_text(json.loads(frame))
        except ConnectionClosed:
            pass
        except (OSError, WebSocketException) as exc:   # refused, timed out, a bad handshake
            self._error = exc
        finally:
            self._opened.set()
            with self._cond:
                self._closed = True
                self._cond.notify_all()

    def _on_binary(self, frame: bytes) -> None:
        now = time.time_ns()
        if frame[0] != MESSAGE_DATA:
            return
        _, subscription, log_time = _HEADER.unpack_from(frame)
        with self._cond:
            channel_id = self._subscriptions.get(subscription)
            if channel_id is None:
                return
            topic = self.channels.get(channel_id, {}).get('topic', '')
            self.messages.append(Received(topic, channel_id, log_time,
                                          frame[_HEADER.size:], now))
            self._cond.notify_all()

    def _on_text(self, message: dict) -> None:
        subscribe = []
        with self._cond:
            op = message.get('op')
            if op == 'serverInfo':
                self.server_info = message
            elif op == 'advertise':
                for channel in message['channels']:
                    self.channels[channel['id']] = channel
                    if channel['topic'] in self._followed:
                        subscribe.append(channel['id'])
            elif op == 'unadvertise':
                for channel_id in message['channelIds']:
                    self.channels.pop(channel_id, None)
                    self.unadvertised.append(channel_id)
            elif op == 'status' and _UNKNOWN.match(message.get('message', '')):
                channel_id = int(_UNKNOWN.match(message['message']).group(1))
                for subscription, channel in list(self._subscriptions.items()):
                    if channel == channel_id:
                        del self._subscriptions[subscription]
                if channel_id in self.channels:
                    self.refused += 1
                    subscribe.append(channel_id)
            self._cond.notify_all()
        if subscribe:
            self.subscribe(subscribe)

    # -- requests ------------------------------------------------------------------------------

    def subscribe(self, channel_ids: list[int]) -> None:
        with self._cond:
            subscriptions = []
            for channel_id in channel_ids:
                if channel_id in self._subscriptions.values():
                    continue
                self._subscriptions[self._next_id] = channel_id
                subscriptions.append({'id': self._next_id, 'channelId': channel_id})
                self._next_id += 1
        if subscriptions:
            self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subscriptions}))

    def follow(self, topics: list[str]) -> None:
        """Subscribe to these topics' channels, those advertised now and any advertised later."""
        with self._cond:
            self._followed.update(topics)
            ids = [c['id'] for c in self.channels.values() if c['topic'] in self._followed]
        self.subscribe(ids)

    # -- waiting -------------------------------------------------------------------------------

    def wait(self, predicate, timeout: float, what: str):
        """Block until predicate(self) is true (checked under the lock); return its value."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                value = predicate(self)
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed:
                    raise TimeoutError(f'{what}: not within {timeout} s '
                                       f'(connection closed: {self._closed}); advertised '
                                       f'{sorted(c["topic"] for c in self.channels.values())}, '
                                       f'{len(self.messages)} messages')
                self._cond.wait(min(remaining, 0.2))

    def channel_for(self, topic: str, timeout: float = 10.0) -> dict:
        return self.wait(lambda c: next((ch for ch in c.channels.values()
                                         if ch['topic'] == topic), None),
                         timeout, f'a channel for {topic}')

    def received(self, topic: str) -> list[Received]:
        with self._cond:
            return [m for m in self.messages if m.topic == topic]

    def close(self) -> None:
        self.ws.close()
        self._thread.join(5)
