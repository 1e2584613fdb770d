"""Foxglove: the MCAP export read back with the mcap reader, and the live WebSocket server
with a real client on loopback (subprotocol ``foxglove.sdk.v1``)."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the foxglove extra is not installed")
mcap_reader = pytest.importorskip("mcap.reader", reason="the mcap package is not installed")
websockets = pytest.importorskip("websockets", reason="the websockets package is not installed")

from kmea.sim.renderer import Renderer  # noqa: E402
from kmea.sim.scenes import scene_from_spec  # noqa: E402
from kmea.vision.overlay import OverlayMarker  # noqa: E402
from kmead import cli  # noqa: E402
from kmead.tools import kmea_cli  # noqa: E402
from kmead.viewers.foxglove import (  # noqa: E402
    TOPICS,
    FoxgloveServer,
    FrameView,
    MarkerView,
    RobotView,
    quaternion_xyzw,
)
from kmead.viewers.mcap_export import export_mcap  # noqa: E402

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
FAST = ["--set", "source.width=640", "--set", "source.height=480", "--set", "source.fps=0"]
N_FRAMES = 12


def pb_fields(buf: bytes) -> list[tuple[int, object]]:
    """Top-level (field number, value) pairs of a protobuf message (varint, 64-bit,
    length-delimited as bytes, 32-bit): enough to check a few fields without protobuf."""
    out, i = [], 0

    def varint() -> int:
        nonlocal i
        v = shift = 0
        while True:
            b = buf[i]
            i += 1
            v |= (b & 0x7F) << shift
            shift += 7
            if b < 0x80:
                return v

    while i < len(buf):
        key = varint()
        num, wt = key >> 3, key & 7
        if wt == 0:
            out.append((num, varint()))
        elif wt == 1:
            out.append((num, buf[i:i + 8]))
            i += 8
        elif wt == 2:
            n = varint()
            out.append((num, buf[i:i + n]))
            i += n
        elif wt == 5:
            out.append((num, buf[i:i + 4]))
            i += 4
        else:
            raise ValueError(f"wire type {wt}")
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("fox")
    rec, log = d / "rec.jsonl", d / "out.csv"
    assert cli.main(["--source", "sim", "--headless", "--frames", str(N_FRAMES), "--record",
                     str(rec), "--log", str(log), *FAST, *NET]) == 0
    return rec, log


def _read_mcap(path: Path):
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f)
        summary = reader.get_summary()
        msgs = [(ch.topic, sch.name, m) for sch, ch, m in reader.iter_messages()]
    return summary, msgs


def test_mcap_export_reads_back_with_channels_and_counts(recorded, tmp_path):
    rec, log = recorded
    out = tmp_path / "run.mcap"
    s = export_mcap(rec, out, log)
    assert s.frames == N_FRAMES and not s.truncated
    summary, msgs = _read_mcap(out)
    topics = {ch.topic for ch in summary.channels.values()}
    assert topics == set(TOPICS) - {"/camera/image"}  # a recording holds no images
    schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert schemas["/camera/annotations"] == "foxglove.ImageAnnotations"
    assert schemas["/floor/map"] == "foxglove.SceneUpdate"
    assert schemas["/robots/poses"] == "foxglove.PosesInFrame"
    assert schemas["/tf"] == "foxglove.FrameTransforms"
    count = {t: sum(1 for tt, _, _ in msgs if tt == t) for t in topics}
    assert count["/floor/map"] == 1
    for t in topics - {"/floor/map"}:
        assert count[t] == N_FRAMES, t
    assert s.messages == count

    # Annotations: one outline (field 2) per recorded marker with corners.
    frames = [json.loads(line) for line in rec.read_text().splitlines()[1:]]
    ann = [m for t, _, m in msgs if t == "/camera/annotations"]
    for m, fr in zip(ann, frames, strict=True):
        n_points = sum(1 for num, _ in pb_fields(m.data) if num == 2)
        assert n_points == len(fr["markers"]) > 10
    # Log times are the recording's frame times.
    assert [m.log_time for m in ann] == [round(fr["t"] * 1e9) for fr in frames]
    # Poses: both robots of the CSV in each frame (field 3: poses).
    poses = [m for t, _, m in msgs if t == "/robots/poses"]
    assert all(sum(1 for num, _ in pb_fields(m.data) if num == 3) == 2 for m in poses)
    # The map scene: the floor and every map marker.
    (scene,) = [m for t, _, m in msgs if t == "/floor/map"]
    entities = [v for num, v in pb_fields(scene.data) if num == 2]
    from kmea.maps.files import default_map
    assert len(entities) == 1 + len(default_map())


def test_mcap_export_reads_a_compressed_recording_whole_and_cut(tmp_path, capsys):
    rec, log = tmp_path / "rec.jsonl.zst", tmp_path / "out.csv"
    assert cli.main(["--source", "sim", "--headless", "--frames", "6", "--record",
                     str(rec), "--log", str(log), *FAST, *NET]) == 0
    s = export_mcap(rec, tmp_path / "whole.mcap", log)
    assert s.frames == 6 and not s.truncated and s.bad_lines == 0
    _, msgs = _read_mcap(tmp_path / "whole.mcap")
    assert sum(1 for t, _, _ in msgs if t == "/camera/annotations") == 6
    # What a kill leaves: the bytes up to somewhere inside the last frame.
    cut = tmp_path / "cut.jsonl.zst"
    cut.write_bytes(rec.read_bytes()[:-40])
    s = export_mcap(cut, tmp_path / "cut.mcap", log)
    assert s.frames == 5 and s.truncated


def test_export_cli_one_line_errors_and_warning(recorded, tmp_path, capsys):
    rec, log = recorded
    out = tmp_path / "a.mcap"
    assert kmea_cli.main(["export", "mcap", str(rec), "--csv", str(log), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith(f"wrote {out}: {N_FRAMES} frames")
    # Existing output: refused, one line.
    assert kmea_cli.main(["export", "mcap", str(rec), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0]
    # A bad CSV: the file and line named.
    bad = tmp_path / "bad.csv"
    bad.write_text(log.read_text().splitlines()[0] + "\n0,0.1,kmea,marker,x,1,2,3,0,,4\n")
    assert kmea_cli.main(["export", "mcap", str(rec), "--csv", str(bad), "--out",
                          str(tmp_path / "b.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv: line 2" in err[0]
    # Not a recording.
    assert kmea_cli.main(["export", "mcap", str(bad), "--out", str(tmp_path / "c.mcap")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a kmead recording" in err[0]
    # A recording cut by a kill: the whole frames, and a warning.
    cut = tmp_path / "cut.jsonl"
    text = rec.read_text()
    cut.write_text(text[:len(text) - 200])
    assert kmea_cli.main(["export", "mcap", str(cut), "--out", str(tmp_path / "d.mcap")]) == 0
    cap = capsys.readouterr()
    assert f"{N_FRAMES - 1} frames" in cap.out
    assert "partial line" in cap.err


def test_quaternion_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        x, y, z, w = quaternion_xyzw(R)
        g = np.array([w, x, y, z])
        assert min(np.abs(g - q).max(), np.abs(g + q).max()) < 1e-9


async def _client(port: int, want: dict[str, int], timeout: float = 10.0
                  ) -> dict[str, list[bytes]]:
    """Connect, subscribe to the topics of ``want``, collect that many messages of each."""
    topics = set(want)
    got: dict[str, list[bytes]] = {t: [] for t in topics}
    async with websockets.connect(f"ws://127.0.0.1:{port}",
                                  subprotocols=["foxglove.sdk.v1"]) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        subs: dict[int, str] = {}
        deadline = time.monotonic() + timeout
        while any(len(got[t]) < n for t, n in want.items()):
            msg = await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic()))
            if isinstance(msg, str):
                d = json.loads(msg)
                if d.get("op") == "advertise":
                    new = [{"id": len(subs) + k + 1, "channelId": c["id"]}
                           for k, c in enumerate(c for c in d["channels"]
                                                 if c["topic"] in topics)]
                    for s, c in zip(new, [c for c in d["channels"] if c["topic"] in topics],
                                    strict=True):
                        subs[s["id"]] = c["topic"]
                        assert c["encoding"] == "protobuf"
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif msg[0] == 0x01:  # message data: op, subscription id, log time, payload
                sub_id, _log_time = struct.unpack_from("<IQ", msg, 1)
                got[subs[sub_id]].append(bytes(msg[13:]))
    return got


def test_live_server_sends_image_and_scene_to_a_websocket_client():
    scene = scene_from_spec("sim:default?width=640&height=480")
    frame = Renderer(scene).render(0)
    truth = frame.truth
    outlines = [OverlayMarker(i, c) for i, c in truth.corners.items()]
    markers = [MarkerView(i, T[:3, 3], 0.0) for i, T in truth.markers.items()]
    robots = [RobotView(n, x, y, th) for n, (x, y, th) in truth.robots.items()]
    server = FoxgloveServer(scene.effective_map(), scene.camera, port=0, image_hz=0)
    stop = threading.Event()

    def publish() -> None:
        i = 0
        while not stop.is_set():
            server.publish(FrameView(time.time(), i, frame.image, outlines, markers, robots,
                                     truth.cam2world))
            i += 1
            time.sleep(0.02)

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        # The map is static: sent once on subscription (and every few seconds).
        want = {"/camera/image": 2, "/floor/map": 1, "/robots/poses": 2,
                "/camera/annotations": 2, "/tf": 2}
        got = asyncio.run(_client(server.port, want))
    finally:
        stop.set()
        t.join(2)
        server.close()
    img = got["/camera/image"][0]
    jpeg = next(v for _, v in pb_fields(img) if isinstance(v, bytes) and v[:2] == b"\xff\xd8")
    decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded.shape == frame.image.shape
    assert np.abs(decoded.astype(int) - frame.image).mean() < 4  # the same picture
    assert any(v == b"jpeg" for _, v in pb_fields(img))
    entities = [v for num, v in pb_fields(got["/floor/map"][0]) if num == 2]
    assert len(entities) == 1 + len(scene.effective_map())
    assert sum(1 for num, _ in pb_fields(got["/robots/poses"][0]) if num == 3) == len(robots)
    n_out = sum(1 for num, _ in pb_fields(got["/camera/annotations"][0]) if num == 2)
    assert n_out == len(outlines)
    # world -> camera and world -> each robot.
    assert sum(1 for num, _ in pb_fields(got["/tf"][0]) if num == 1) == 1 + len(robots)


def test_port_in_use_is_an_os_error():
    scene = scene_from_spec("sim:scenario1?width=320&height=240")
    a = FoxgloveServer(scene.effective_map(), scene.camera, port=0)
    try:
        with pytest.raises(OSError, match="foxglove: cannot serve"):
            FoxgloveServer(scene.effective_map(), scene.camera, port=a.port)
    finally:
        a.close()


def test_kmead_serves_foxglove_when_enabled(tmp_path):
    from kmead.config.layers import load_config
    from kmead.run.daemon import Daemon

    cfg = load_config(None, ["source.width=640", "source.height=480", "source.fps=8",
                             'network.telemetry="tcp://127.0.0.1:*"',
                             'network.control="tcp://127.0.0.1:*"',
                             "foxglove.enabled=true", "foxglove.port=0",
                             "foxglove.image_hz=4"])
    d = Daemon(cfg)
    t = threading.Thread(target=d.run, daemon=True)
    t.start()
    try:
        got = asyncio.run(_client(d.foxglove.port, {"/camera/image": 1, "/floor/map": 1,
                                                    "/floor/markers": 2, "/robots/poses": 2},
                                  timeout=30))
    finally:
        d.stop()
        t.join(10)
        d.close()
    jpeg = next(v for _, v in pb_fields(got["/camera/image"][0])
                if isinstance(v, bytes) and v[:2] == b"\xff\xd8")
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED).shape == (480, 640)
    entities = [v for num, v in pb_fields(got["/floor/markers"][-1]) if num == 2]
    cubes = [v for num, v in pb_fields(entities[0]) if num == 8]  # SceneEntity.cubes
    assert len(cubes) > 20  # the markers estimated in that frame
    assert sum(1 for num, _ in pb_fields(got["/robots/poses"][-1]) if num == 3) == 2
