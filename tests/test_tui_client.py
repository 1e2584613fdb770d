"""DaemonClient on real ZeroMQ sockets: the lazy-pirate REQ never hangs and recovers."""

from __future__ import annotations

import asyncio
import time

import pytest
import zmq
import zmq.asyncio
from deadlines import DEADLINE

from kmea.wire import protocol
from kmea_tui.client import DaemonClient


@pytest.fixture
async def published():
    """(a PUB socket on loopback, a DaemonClient subscribed to it), closed afterwards."""
    ctx = zmq.asyncio.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    client = DaemonClient(f"tcp://127.0.0.1:{port}", "tcp://127.0.0.1:1", timeout=0.2)
    await client.open()
    try:
        yield pub, client
    finally:
        client.close()
        pub.close(linger=0)
        ctx.term()


async def test_request_times_out_then_recovers_with_a_fresh_socket() -> None:
    ctx = zmq.asyncio.Context()
    rep = ctx.socket(zmq.REP)
    rep.setsockopt(zmq.LINGER, 0)
    port = rep.bind_to_random_port("tcp://127.0.0.1")
    client = DaemonClient("tcp://127.0.0.1:1", f"tcp://127.0.0.1:{port}", timeout=0.3)
    await client.open()
    try:
        # 1) The server reads the request but never answers: the client gives up.
        pending = asyncio.ensure_future(client.request("ping"))
        first = protocol.decode_body(await rep.recv())
        reply = await pending
        assert first["cmd"] == "ping"
        assert reply["ok"] is False and "no reply" in reply["error"]
        # The REP socket must answer before it can read again; the answer goes nowhere
        # (that REQ socket was closed), which is exactly what the lazy pirate expects.
        await rep.send(protocol.encode_body({"ok": True}))

        # 2) The next request goes through a new REQ socket and gets its reply.
        async def serve_once() -> dict:
            req = protocol.decode_body(await rep.recv())
            await rep.send(protocol.encode_body({"ok": True, "cmd": req["cmd"], "echo": req}))
            return req

        server = asyncio.ensure_future(serve_once())
        reply = await client.request("set", key="filter.alpha", value=0.5)
        got = await server
        assert reply["ok"] is True and reply["cmd"] == "set"
        assert got == {"v": protocol.PROTOCOL_VERSION, "cmd": "set", "key": "filter.alpha",
                       "value": 0.5}

        # 3) A reply that is not protocol JSON is reported, not raised.
        async def serve_garbage() -> None:
            await rep.recv()
            await rep.send(b"\xff garbage")

        server = asyncio.ensure_future(serve_garbage())
        reply = await client.request("ping")
        await server
        assert reply["ok"] is False and "bad reply" in reply["error"]
    finally:
        client.close()
        rep.close(linger=0)
        ctx.term()


async def test_recv_decodes_and_counts_bad_messages(published) -> None:
    pub, client = published
    got: list = []
    # Publish until the subscription is through (PUB drops while SUB is joining).
    for i in range(200):
        await pub.send_multipart(protocol.encode("event", {"t": float(i), "level": "info",
                                                           "text": f"event {i}"}))
        await pub.send_multipart([b"frame", b"not json"])
        # Right version, but not a frame body (the typed decoder refuses it).
        await pub.send_multipart(protocol.encode("frame", {"frame": i}))
        await pub.send_multipart(protocol.encode("robot.amr1", {"seq": i}))
        got += await client.recv(0.02)
        if got:
            break
    assert got, "no telemetry received"
    assert all(t == "event" and b["text"].startswith("event") for t, b in got)  # no robot.*
    end = time.monotonic() + DEADLINE  # the bad ones sent with the first event received
    while time.monotonic() < end and client.bad_messages < 2:
        got += await client.recv(0.1)
    assert client.bad_messages >= 2 and "frame: field " in client.last_error


async def test_drain_raw_returns_what_waits_without_waiting(published) -> None:
    """The UI drains the telemetry socket once per repaint: everything queued meanwhile
    comes at once, in order, undecoded; a message that is not [topic, body] is counted."""
    pub, client = published
    assert client.drain_raw() == []  # nothing there: no wait, nothing
    for _ in range(200):  # until the subscription is through
        await pub.send_multipart(protocol.encode("frame", {"frame": -1}))
        await asyncio.sleep(0.01)
        if client.drain_raw():
            break
    else:
        raise AssertionError("the subscription never came through")
    for i in range(50):
        await pub.send_multipart(protocol.encode("event", {"t": float(i), "level": "info",
                                                           "text": f"event {i}"}))
    await pub.send_multipart([b"event", b"{}", b"a third frame"])
    got: list = []
    end = time.monotonic() + DEADLINE
    while time.monotonic() < end and not (len(got) >= 50 and client.bad_messages):
        await asyncio.sleep(0.01)
        got += client.drain_raw()
    assert [t for t, _ in got] == ["event"] * 50
    texts = [client.decode_raw(frames)[1]["text"] for _, frames in got]  # type: ignore[index]
    assert texts == [f"event {i}" for i in range(50)]
    assert client.bad_messages == 1 and "got 3" in client.last_error
