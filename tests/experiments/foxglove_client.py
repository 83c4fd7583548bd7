"""A Foxglove WebSocket client for the live-view tests (test_live_view, test_live): it
negotiates the subprotocol the SDK serves, reads `serverInfo` and every `advertise`,
subscribes to every channel it is told about, and decodes the binary message frames
(opcode 0x01, uint32 subscription id, uint64 log time, payload): protobuf payloads with a
message class built from the FileDescriptorSet in the advertisement only, JSON payloads
as JSON."""

from __future__ import annotations

import asyncio
import base64
import json
import re
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

SUBPROTOCOL = "foxglove.sdk.v1"
TIMEOUT_S = 20.0  # generous: the machine is shared; nothing here asserts on timing


def _message_class(schema_name: str, fds_b64: str) -> type:
    """The protobuf class of `schema_name` from an advertised FileDescriptorSet alone."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(fds_b64))
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # dependencies first
        ready = [f for f in pending if all(pool_has(pool, d) for d in f.dependency)]
        assert ready, "the descriptor set lacks a dependency"
        for f in ready:
            pool.Add(f)
            pending.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def pool_has(pool: descriptor_pool.DescriptorPool, name: str) -> bool:
    try:
        pool.FindFileByName(name)
        return True
    except KeyError:
        return False


class Client:
    """A Foxglove WebSocket client in a background thread that subscribes to everything."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.subprotocol: str | None = None
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> its advertisement
        self.received: dict[str, list[tuple[int, bytes]]] = {}  # topic -> (log ns, payload)
        self.errors: list[BaseException] = []
        self.statuses: list[dict[str, Any]] = []
        self._subs: dict[int, str] = {}  # subscription id -> topic
        self._by_channel: dict[int, int] = {}  # channel id -> subscription id
        self._classes: dict[str, type] = {}
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._loop.run_until_complete(self._session())
        except BaseException as e:  # surfaced by wait()
            self.errors.append(e)

    async def _session(self) -> None:
        self._stop = asyncio.Event()
        async with websockets.connect(
            self.url, subprotocols=[SUBPROTOCOL], max_size=None, open_timeout=TIMEOUT_S
        ) as ws:
            self.subprotocol = ws.subprotocol
            reader = asyncio.ensure_future(self._read(ws))
            stopper = asyncio.ensure_future(self._stop.wait())
            await asyncio.wait({reader, stopper}, return_when=asyncio.FIRST_COMPLETED)
            for task in (reader, stopper):  # the one still pending (the server closed, or
                task.cancel()  # close() was called) ends here, not at garbage collection
            await asyncio.gather(reader, stopper, return_exceptions=True)
            if not reader.cancelled() and reader.exception():
                raise reader.exception()

    async def _read(self, ws) -> None:
        async for frame in ws:
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    self.server_info = msg
                elif msg["op"] == "advertise":
                    subs = []
                    with self._lock:
                        for ch in msg["channels"]:
                            self.channels[ch["topic"]] = ch
                            sub_id = len(self._subs) + 1
                            self._subs[sub_id] = ch["topic"]
                            self._by_channel[int(ch["id"])] = sub_id
                            subs.append({"id": sub_id, "channelId": int(ch["id"])})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif msg["op"] == "status":
                    self.statuses.append(msg)
                    refused = re.fullmatch(r"Unknown channel ID: (\d+)", msg["message"])
                    if refused and int(refused[1]) in self._by_channel:
                        # The SDK advertises a new channel a moment before it takes
                        # subscriptions to it: ask again.
                        await asyncio.sleep(0.05)
                        sub = {
                            "id": self._by_channel[int(refused[1])],
                            "channelId": int(refused[1]),
                        }
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
            elif frame[0] == 0x01:
                sub_id, log_ns = struct.unpack_from("<IQ", frame, 1)
                with self._lock:
                    topic = self._subs[sub_id]
                    self.received.setdefault(topic, []).append((log_ns, bytes(frame[13:])))

    def close(self) -> None:
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(TIMEOUT_S)

    def wait(self, condition: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + TIMEOUT_S
        while not condition():
            if self.errors:
                raise self.errors[0]
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            time.sleep(0.01)

    def messages(self, topic: str) -> list[tuple[int, Any]]:
        """(log time ns, decoded message) received on topic."""
        with self._lock:
            ch, items = self.channels[topic], list(self.received.get(topic, []))
        if ch["encoding"] == "json":
            return [(ns, json.loads(data)) for ns, data in items]
        assert ch["encoding"] == "protobuf" and ch["schemaEncoding"] == "protobuf"
        cls = self._classes.get(topic)
        if cls is None:
            cls = self._classes[topic] = _message_class(ch["schemaName"], ch["schema"])
        return [(ns, cls.FromString(data)) for ns, data in items]

    def wait_count(self, topic: str, n: int) -> list[tuple[int, Any]]:
        self.wait(lambda: len(self.received.get(topic, [])) >= n, f"{n} messages on {topic}")
        return self.messages(topic)
