"""``talkmesh serve``: the WebSocket streaming protocol, its limits and errors, and the HTTP routes."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pygltflib
import pytest
from starlette.testclient import TestClient
from websockets.sync.client import connect

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import load_head
from talkmesh.face.head_stream import HeadMotionStream
from talkmesh.serve.protocol import (
    CLOSE_BUSY,
    CLOSE_GOING_AWAY,
    CLOSE_NORMAL,
    CLOSE_POLICY,
    CLOSE_TOO_BIG,
    decode_frame,
    encode_frame,
)
from talkmesh.serve.server import create_app
from talkmesh.serve.stream import StreamFrame

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s, "he was not an ill disposed young man"
CHUNK = 2 * SAMPLE_RATE // 10  # bytes of 100 ms of 16-bit PCM
FPS = 30.0


@pytest.fixture(autouse=True)
def _speech_clip():
    assert CLIP.exists(), f"{CLIP} is missing: run `make setup` (pocketsphinx-testdata)"


@dataclass
class Reply:
    """Everything a session sent until it closed."""

    texts: list[dict]
    frames: list[StreamFrame]
    code: int


def read_until_close(ws) -> Reply:
    texts, frames = [], []
    while True:
        message = ws.receive()
        if message["type"] == "websocket.close":
            return Reply(texts, frames, message.get("code", CLOSE_NORMAL))
        if message.get("bytes") is not None:
            frames.append(decode_frame(message["bytes"]))
        else:
            texts.append(json.loads(message["text"]))


def assert_error(reply: Reply, code: int, *fragments: str) -> None:
    assert reply.code == code, reply
    assert [t["type"] for t in reply.texts] == ["error"], reply.texts
    message = reply.texts[0]["message"]
    assert "\n" not in message and "Traceback" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


@pytest.fixture(scope="module")
def pcm() -> bytes:
    """The clip as the wire carries it: 16 kHz mono int16 little-endian."""
    wave = load_audio(CLIP)
    return (np.clip(wave, -1, 1) * 32767).astype("<i2").tobytes()


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app()) as c:  # one event loop for every session, as under uvicorn
        yield c


@pytest.fixture(scope="module")
def alone(client, pcm) -> Reply:
    """The clip streamed in 100 ms chunks with no other session open."""
    with client.websocket_connect("/ws/stream") as ws:
        ws.receive_json()
        for i in range(0, len(pcm), CHUNK):
            ws.send_bytes(pcm[i : i + CHUNK])
        ws.send_json({"type": "end"})
        return read_until_close(ws)


@pytest.mark.parametrize("with_pose", [False, True])
def test_frame_encoding_round_trip(with_pose):
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 0.05, 6).astype(np.float32) if with_pose else None
    for offsets in (None, rng.normal(0, 0.01, (7, 3)).astype(np.float32)):
        frame = StreamFrame(41, 41 / FPS, rng.random(52).astype(np.float32), offsets, pose)
        data = encode_frame(frame)
        size = 16 + 4 * 52 + (0 if offsets is None else 42) + (24 if with_pose else 0)
        assert data[:4] == b"TMF1" and len(data) == size
        back = decode_frame(data)
        assert (back.index, back.time) == (41, np.float32(41 / FPS))
        np.testing.assert_array_equal(back.weights, frame.weights)
        if offsets is None:
            assert back.offsets is None
        else:
            np.testing.assert_allclose(back.offsets, offsets, atol=1e-5)
        if pose is None:
            assert back.head_pose is None
        else:
            np.testing.assert_array_equal(back.head_pose, pose)


def test_hello(client):
    with client.websocket_connect("/ws/stream?lookahead_ms=50") as ws:
        hello = ws.receive_json()
    assert hello == {
        "type": "hello",
        "fps": FPS,
        "sample_rate": SAMPLE_RATE,
        "lookahead_ms": 50.0,
        "model": "procedural",
        "names": list(ARKIT_NAMES),
    }


def test_speech_streams_as_consecutive_frames_that_move_the_jaw(alone, pcm):
    assert alone.code == CLOSE_NORMAL
    frames = alone.frames
    expected = round(len(pcm) / 2 / SAMPLE_RATE * FPS)  # 90
    assert abs(len(frames) - expected) <= 1
    assert alone.texts == [{"type": "end", "frames": len(frames)}]
    assert [f.index for f in frames] == list(range(len(frames)))
    np.testing.assert_allclose([f.time for f in frames], np.arange(len(frames)) / FPS, atol=1e-5)
    weights = np.stack([f.weights for f in frames])
    assert weights.shape == (len(frames), 52) and all(f.offsets is None for f in frames)
    assert weights.min() >= 0.0 and weights.max() <= 1.0
    jaw = weights[:, ARKIT_NAMES.index("jawOpen")]
    assert jaw.max() - jaw.min() > 0.1  # the mouth opens and closes with the syllables


def test_frames_carry_the_head_motion_of_the_audio_so_far(alone, pcm):
    """Each frame's head pose is what the head motion makes of the audio up to it, however the
    audio was cut: the session's poses are those of the whole clip at once."""
    audio = np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0
    motion, parts = HeadMotionStream(FPS), []
    for second in range(0, len(audio), SAMPLE_RATE):  # a second at a time, frames as they come
        motion.receive(audio[second : second + SAMPLE_RATE])
        done = sum(map(len, parts))
        parts.append(motion.poses(done, min(len(alone.frames), done + int(FPS) - 5)))
    parts.append(motion.poses(sum(map(len, parts)), len(alone.frames)))
    expected = np.concatenate(parts)
    got = np.stack([f.head_pose for f in alone.frames])
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.degrees(np.ptp(got[:, :3], axis=0)).min() > 0.05  # it nods, turns and tilts


def test_head_motion_zero_sends_no_head_pose(client, pcm):
    with client.websocket_connect("/ws/stream?head_motion=0") as ws:
        ws.receive_json()
        ws.send_bytes(pcm[: 5 * CHUNK])
        ws.send_json({"type": "end"})
        reply = read_until_close(ws)
    assert reply.code == CLOSE_NORMAL and len(reply.frames) == 15
    assert all(f.head_pose is None for f in reply.frames)


def test_when_the_audio_stops_the_face_keeps_moving(client, pcm):
    """1 s of speech, then 2.5 s without a message: idle frames (silence streamed in the
    client's place) keep coming, the head breathing and swaying, the eyes moving."""
    with client.websocket_connect("/ws/stream") as ws:
        ws.receive_json()
        for i in range(0, 10 * CHUNK, CHUNK):
            ws.send_bytes(pcm[i : i + CHUNK])
        time.sleep(2.5)
        ws.send_json({"type": "end"})
        reply = read_until_close(ws)
    assert reply.code == CLOSE_NORMAL
    idle = reply.frames[30:]
    assert len(idle) >= 15  # at least half a second of idle frames
    assert [f.index for f in reply.frames] == list(range(len(reply.frames)))
    poses = np.degrees(np.stack([f.head_pose[:3] for f in idle]))
    assert np.ptp(poses, axis=0).min() > 0.01
    jaw = np.array([f.weights[ARKIT_NAMES.index("jawOpen")] for f in idle[10:]])
    assert jaw.max() < 0.05  # silence: the mouth at rest once the cut-off syllable closes
    eyes = [i for i, n in enumerate(ARKIT_NAMES) if n.startswith("eye")]
    assert np.ptp(np.stack([f.weights[eyes] for f in idle]), axis=0).max() > 0.01


def test_the_silence_streamed_in_a_pause_is_announced_before_the_audio_after_it(client, pcm):
    """1 s of speech, 1.5 s without audio, 0.5 s more: a silence message names where the idle
    silence went and how long it was, before the frames of the later audio."""
    with client.websocket_connect("/ws/stream") as ws:
        ws.receive_json()
        ws.send_bytes(pcm[: 10 * CHUNK])
        time.sleep(1.5)
        ws.send_bytes(pcm[10 * CHUNK : 15 * CHUNK])
        ws.send_json({"type": "end"})
        order = []
        while (message := ws.receive())["type"] != "websocket.close":
            order.append(decode_frame(message["bytes"]) if message.get("bytes") else message)
    texts = [json.loads(m["text"]) for m in order if isinstance(m, dict)]
    frames = [m for m in order if not isinstance(m, dict)]
    (notice,) = [t for t in texts if t["type"] == "silence"]
    audio = 15 * CHUNK // 2  # samples the client sent (16-bit)
    # the wall clock passes the 1 s sent at once after 1 s; silence then until the audio at 1.5 s
    assert notice["sample"] == 10 * CHUNK // 2 and notice["samples"] >= SAMPLE_RATE // 5
    assert abs(len(frames) - (audio + notice["samples"]) / SAMPLE_RATE * FPS) <= 1
    first_after = int((notice["sample"] + notice["samples"]) / SAMPLE_RATE * FPS) + 1
    position = next(i for i, m in enumerate(order) if isinstance(m, dict))
    assert all(f.index < first_after for f in order[:position] if not isinstance(f, dict))


def test_idle_off_sends_only_the_audios_frames(client, pcm):
    with client.websocket_connect("/ws/stream?idle=0") as ws:
        ws.receive_json()
        ws.send_bytes(pcm[: 10 * CHUNK])
        time.sleep(1.5)
        ws.send_json({"type": "end"})
        reply = read_until_close(ws)
    assert reply.code == CLOSE_NORMAL and len(reply.frames) == 30


def test_offsets_on_request(client, pcm):
    with client.websocket_connect("/ws/stream?offsets=1") as ws:
        ws.receive_json()
        ws.send_bytes(pcm[: 10 * CHUNK])
        ws.send_json({"type": "end"})
        reply = read_until_close(ws)
    head = load_head()
    assert reply.code == CLOSE_NORMAL and len(reply.frames) == 30
    frame = reply.frames[-1]
    expected = np.tensordot(frame.weights, head.blendshapes, axes=1)
    np.testing.assert_allclose(frame.offsets, expected, atol=2e-4)  # float16 on the wire


@pytest.mark.parametrize(
    "query, messages, code, fragments",
    [
        ("", [b"\x01\x02\x03"], CLOSE_POLICY, ["3 bytes", "16-bit"]),
        ("", [bytes(70_000)], CLOSE_TOO_BIG, ["70000 bytes", "65536"]),
        ("", ["x" * 70_000], CLOSE_TOO_BIG, ["65536"]),
        ("", [bytes(CHUNK), "{not json"], CLOSE_POLICY, ["JSON", '{"type": "end"}']),
        ("", ['{"type": "stop"}'], CLOSE_POLICY, ["unknown message"]),
        ("", ['{"type": "emotion", "emotion": "glee"}'], CLOSE_POLICY, ["unknown emotion 'glee'"]),
        ("", ['{"type": "emotion", "emotion": "sad:2"}'], CLOSE_POLICY, ["from 0 to 1"]),
        ("", ['{"type": "emotion", "mood": "sad"}'], CLOSE_POLICY, ['"emotion": "happy:0.6"']),
        ("?model=nope", [], CLOSE_POLICY, ["unknown model 'nope'", "procedural"]),
        ("?model=/etc/passwd", [], CLOSE_POLICY, ["unknown model"]),
        ("?model=../data/models/codetalker-synth.safetensors", [], CLOSE_POLICY, ["unknown model"]),
        ("?lookahead_ms=soon", [], CLOSE_POLICY, ["lookahead_ms", "soon"]),
        ("?lookahead_ms=nan", [], CLOSE_POLICY, ["lookahead_ms"]),
        ("?lookahead_ms=5000", [], CLOSE_POLICY, ["look-ahead", "300"]),
        ("?offsets=yes", [], CLOSE_POLICY, ["offsets"]),
        ("?head_motion=2", [], CLOSE_POLICY, ["head_motion", "0 (still) to 1"]),
        ("?head_motion=lots", [], CLOSE_POLICY, ["head_motion", "lots"]),
        ("?idle=yes", [], CLOSE_POLICY, ["idle must be 0 or 1"]),
    ],
)
def test_bad_input_gets_an_error_and_the_right_close_code(client, query, messages, code, fragments):
    with client.websocket_connect("/ws/stream" + query) as ws:
        if query.startswith(("?model", "?lookahead", "?offsets", "?head_motion", "?idle")):
            reply = read_until_close(ws)  # refused before the hello
        else:
            assert ws.receive_json()["type"] == "hello"
            for m in messages:
                ws.send_bytes(m) if isinstance(m, bytes) else ws.send_text(m)
            reply = read_until_close(ws)
    assert_error(reply, code, *fragments)


def test_an_emotion_message_changes_the_face_from_then_on(client, pcm, alone):
    """Sad from the 15th chunk's frames on: the frames before are the neutral session's, the
    brows rise within the onset, the lips keep the speech's opening."""
    head = load_head()
    with client.websocket_connect("/ws/stream?offsets=1") as ws:
        ws.receive_json()
        chunks = [pcm[i : i + CHUNK] for i in range(0, len(pcm), CHUNK)]
        for k, chunk in enumerate(chunks):
            if k == 15:
                ws.send_json({"type": "emotion", "emotion": "sad"})
            ws.send_bytes(chunk)
        ws.send_json({"type": "end"})
        reply = read_until_close(ws)
    assert reply.code == CLOSE_NORMAL and len(reply.frames) == len(alone.frames)
    inner = ARKIT_NAMES.index("browInnerUp")
    moved = [
        f.index
        for f in reply.frames
        if abs(f.weights[inner] - alone.frames[f.index].weights[inner]) > 1e-3
    ]
    assert moved and moved == list(range(moved[0], len(reply.frames)))  # from one frame on
    assert moved[0] <= 1.5 * FPS + 6  # about when it was sent (15 chunks, the look-ahead)
    late = reply.frames[-1]
    assert late.weights[inner] > alone.frames[-1].weights[inner] + 0.5
    upper, lower = head.regions.lip_pair
    for f, g in zip(reply.frames, alone.frames):
        plain = head.template + np.tensordot(g.weights, head.blendshapes, axes=1)
        gap0 = np.linalg.norm(plain[upper] - plain[lower])
        gap = np.linalg.norm(
            (head.template + f.offsets)[upper] - (head.template + f.offsets)[lower]
        )
        assert abs(gap - gap0) < 3e-4 + 0.03 * gap0  # float16 offsets on the wire


def test_bad_sessions_do_not_disturb_a_good_one(client, pcm, alone):
    with (
        client.websocket_connect("/ws/stream") as good,
        client.websocket_connect("/ws/stream") as garbage,
        client.websocket_connect("/ws/stream") as leaver,
    ):
        for ws in (good, garbage, leaver):
            ws.receive_json()
        chunks = [pcm[i : i + CHUNK] for i in range(0, len(pcm), CHUNK)]
        for k, chunk in enumerate(chunks):
            good.send_bytes(chunk)
            leaver.send_bytes(chunk)
            if k == 5:
                garbage.send_bytes(b"\xff" * 1001)
            if k == 10:
                leaver.close(1006)  # gone mid-stream, without an end message
        good.send_json({"type": "end"})
        reply = read_until_close(good)
        assert_error(read_until_close(garbage), CLOSE_POLICY, "1001 bytes")
    assert reply.code == CLOSE_NORMAL and reply.texts == alone.texts
    assert len(reply.frames) == len(alone.frames)
    for a, b in zip(reply.frames, alone.frames):
        assert a.index == b.index and a.time == b.time
        np.testing.assert_array_equal(a.weights, b.weights)
    assert client.get("/health").json()["sessions"] == 0  # every session was let go


def test_one_session_too_many_is_refused_until_one_ends(client):
    health = client.get("/health").json()
    ticks, batched = health.pop("ticks"), health.pop("batched")  # the scheduler's work so far
    assert batched >= ticks > 0
    assert health == {
        "status": "ok",
        "sessions": 0,
        "max_sessions": 4,
        "jobs": 0,
        "queued": 0,
        "models": ["procedural"],
        "avatar": None,
        "workers": [],  # create_app's default: procedural sessions in the server process
    }
    with (
        client.websocket_connect("/ws/stream") as a,
        client.websocket_connect("/ws/stream") as b,
        client.websocket_connect("/ws/stream") as c,
        client.websocket_connect("/ws/stream") as d,
    ):
        for ws in (a, b, c, d):
            assert ws.receive_json()["type"] == "hello"
            ws.send_bytes(bytes(CHUNK))  # a first message: past the first-message timeout
        assert client.get("/health").json()["sessions"] == 4
        with client.websocket_connect("/ws/stream") as fifth:
            assert_error(read_until_close(fifth), CLOSE_BUSY, "busy", "4")
        a.send_json({"type": "end"})
        assert read_until_close(a).code == CLOSE_NORMAL
        with client.websocket_connect("/ws/stream") as again:
            assert again.receive_json()["type"] == "hello"
    assert client.get("/health").json()["sessions"] == 0


def test_idle_session_times_out_but_a_talking_one_does_not(pcm):
    with TestClient(create_app(idle_timeout=0.4)) as client:
        with client.websocket_connect("/ws/stream") as ws:
            ws.receive_json()
            for i in range(0, 8 * CHUNK, CHUNK):  # a chunk every 0.1 s for 0.8 s
                ws.send_bytes(pcm[i : i + CHUNK])
                time.sleep(0.1)
            ws.send_json({"type": "end"})
            assert read_until_close(ws).code == CLOSE_NORMAL
        with client.websocket_connect("/ws/stream") as ws:
            ws.receive_json()
            ws.send_bytes(pcm[:CHUNK])
            start = time.monotonic()
            assert_error(read_until_close(ws), CLOSE_POLICY, "no message for 0.4 s")
            assert time.monotonic() - start < 5


def test_head_glb_has_the_52_arkit_morph_targets(client):
    response = client.get("/head.glb")
    assert response.status_code == 200 and response.headers["content-type"] == "model/gltf-binary"
    gltf = pygltflib.GLTF2.load_from_bytes(response.content)
    mesh = gltf.meshes[0]
    assert len(mesh.primitives[0].targets) == 52
    assert mesh.extras["targetNames"] == list(ARKIT_NAMES)
    assert gltf.accessors[mesh.primitives[0].attributes.POSITION].count == load_head().num_vertices
    assert client.get("/head.glb").content == response.content  # built once


def test_animate_returns_a_glb_and_leaves_no_files(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with TestClient(create_app(max_upload_bytes=200_000)) as client:
        response = client.post("/animate?format=glb&model=procedural", content=CLIP.read_bytes())
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "model/gltf-binary"
        gltf = pygltflib.GLTF2.load_from_bytes(response.content)
        times = gltf.accessors[gltf.animations[0].samplers[0].input]
        assert times.count == 90  # 3.0 s at 30 fps
        assert gltf.meshes[0].extras["targetNames"] == list(ARKIT_NAMES)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "body, query, status, fragment",
    [
        (bytes(300_000), "", 413, "upload limit"),
        (iter([bytes(100_000)] * 3), "", 413, "upload limit"),  # chunked: no Content-Length
        (b"definitely not audio", "", 400, "not wav, flac, mp3 or ogg"),
        (b"RIFF\x10\x00\x00\x00WAVEgarbage" * 10, "", 400, "audio"),
        (b"RIFF", "?format=gif", 400, "format"),
        (b"RIFF", "?model=/etc/passwd", 400, "unknown model"),
    ],
)
def test_animate_refuses_bad_uploads(tmp_path, monkeypatch, body, query, status, fragment):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with TestClient(create_app(max_upload_bytes=200_000)) as client:
        response = client.post("/animate" + query, content=body)
    assert response.status_code == status
    message = response.json()["message"]
    assert fragment in message and str(tmp_path) not in message
    assert not list(tmp_path.iterdir())


def test_viewer_is_served_or_a_503_says_it_is_missing(tmp_path):
    (tmp_path / "index.html").write_text("<!doctype html><title>viewer</title>")
    with TestClient(create_app(static_dir=tmp_path)) as client:
        assert client.get("/").text == "<!doctype html><title>viewer</title>"
    with TestClient(create_app(static_dir=tmp_path / "missing")) as client:
        response = client.get("/")
        assert response.status_code == 503 and "not installed" in response.text
        assert client.get("/health").status_code == 200


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_cli_serves_and_stops_cleanly(pcm, stop):
    """The real server: a client that vanishes mid-stream, then Ctrl-C / SIGTERM: 1001, exit 0."""
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "talkmesh", "serve", "--port", str(port), "-q"],
        env=dict(os.environ, HF_HUB_OFFLINE="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                assert httpx.get(f"http://127.0.0.1:{port}/health").json()["status"] == "ok"
                break
            except httpx.TransportError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
                time.sleep(0.2)
        url = f"ws://127.0.0.1:{port}/ws/stream"
        with connect(url) as vanishing:
            json.loads(vanishing.recv())
            vanishing.send(pcm[: 5 * CHUNK])
            vanishing.socket.shutdown(socket.SHUT_RDWR)  # no close handshake: the line drops
        while httpx.get(f"http://127.0.0.1:{port}/health").json()["sessions"]:
            assert time.monotonic() < deadline, "the dropped session was never let go"
            time.sleep(0.1)
        with connect(url) as ws:
            assert json.loads(ws.recv())["type"] == "hello"
            ws.send(pcm[: 10 * CHUNK])
            first = decode_frame(ws.recv())
            assert first.index == 0
            proc.send_signal(stop)
            try:
                while True:
                    ws.recv(timeout=30)
            except Exception as e:  # websockets' ConnectionClosed carries the close frame
                assert getattr(e, "rcvd", None) is not None, e
                assert e.rcvd.code == CLOSE_GOING_AWAY, e
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "Traceback" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_model_sessions_at_once_get_the_frames_of_a_session_alone(tmp_path, pcm, tiny_stream_model):
    """Sessions of a streaming model share its steps (serve.batching): frames as if alone."""
    path = tiny_stream_model(num_vertices=load_head().num_vertices)
    chunks = [pcm[i : i + CHUNK] for i in range(0, len(pcm), CHUNK)]
    URL = "/ws/stream?lookahead_ms=100&idle=0"  # b and c wait for the others' frames: no idle
    with TestClient(create_app([str(path)], batch_wait_ms=20)) as client:

        def session(*others):
            with client.websocket_connect(URL) as ws:
                ws.receive_json()
                for k, chunk in enumerate(chunks):
                    ws.send_bytes(chunk)
                    for other in others:  # other sessions, one chunk behind
                        if k:
                            other.send_bytes(chunks[k - 1])
                ws.send_json({"type": "end"})
                return read_until_close(ws)

        alone = session()
        with (
            client.websocket_connect(URL) as b,
            client.websocket_connect(URL) as c,
        ):
            b.receive_json()
            c.receive_json()
            together = session(b, c)
            for other in (b, c):
                other.send_bytes(chunks[-1])
                other.send_json({"type": "end"})
                assert len(read_until_close(other).frames) == len(alone.frames)
    assert together.texts == alone.texts and len(alone.frames) == 90
    for a, b in zip(together.frames, alone.frames):
        np.testing.assert_allclose(a.weights, b.weights, atol=1e-4)


def test_ticks_wait_for_more_sessions_by_default(monkeypatch):
    """`talkmesh serve`, create_app and the scheduler share one --batch-wait-ms default, a
    wait of 10-20 ms (serve.batching.DEFAULT_BATCH_WAIT_MS says why)."""
    import inspect

    from talkmesh.cli import main
    from talkmesh.serve import server
    from talkmesh.serve.batching import DEFAULT_BATCH_WAIT_MS, Scheduler

    seen = {}
    monkeypatch.setattr(server, "serve", lambda *a, **k: seen.update(k))
    assert main(["serve"]) == 0
    assert 10.0 <= seen["batch_wait_ms"] == DEFAULT_BATCH_WAIT_MS <= 20.0
    app_default = inspect.signature(create_app).parameters["batch_wait_ms"].default
    assert app_default == DEFAULT_BATCH_WAIT_MS
    assert Scheduler().batch_wait_s == DEFAULT_BATCH_WAIT_MS / 1000


def test_each_worker_ticks_its_sessions_in_a_lane_of_its_own():
    """The server's own sessions wait --batch-wait-ms to batch their model steps; each worker's
    procedural sessions tick in a lane of their own, at once, never waiting for another lane's
    tick; a lane goes when its last session leaves."""
    import asyncio

    from talkmesh.serve.batching import Scheduler
    from talkmesh.serve.stream import open_stream
    from talkmesh.serve.workers import RemoteStream

    class FakeWorker:
        def __init__(self) -> None:
            self.sessions, self.closed = set(), []

    async def run() -> None:
        scheduler = Scheduler(0.015)
        w1, w2 = FakeWorker(), FakeWorker()
        remote = [RemoteStream(w, k, 30.0, 50.0, []) for k, w in enumerate((w1, w1, w2))]
        local = open_stream("procedural")
        works = [scheduler.join(s) for s in [*remote, local]]
        assert set(scheduler.lanes) == {w1, w2, None}
        assert works[0].lane is works[1].lane is scheduler.lanes[w1]
        assert scheduler.lanes[w1].batch_wait_s == scheduler.lanes[w2].batch_wait_s == 0.0
        assert scheduler.lanes[None].batch_wait_s == 0.015
        for work in works:
            scheduler.leave(work)
        assert scheduler.lanes == {} and scheduler.works == []
        await asyncio.sleep(0.05)  # the lanes' loops end
        assert all(w.lane.runner.done() for w in works)

    asyncio.run(run())


def test_the_bundled_default_streams(pcm):
    """`serve --model codetalker-synth` (animate's default): a session says the look-ahead it
    waits for (its default, 300 ms and the rest of a 3-frame block) and streams the clip's
    frames, the jaw moving in the speech."""
    from talkmesh.pipeline import available_models

    if "codetalker-synth" not in available_models():
        pytest.skip("the bundled CodeTalker is not installed")
    with TestClient(create_app(models=["codetalker-synth"])) as c:
        with c.websocket_connect("/ws/stream?idle=0") as ws:
            hello = ws.receive_json()
            for i in range(0, len(pcm), CHUNK):
                ws.send_bytes(pcm[i : i + CHUNK])
            ws.send_json({"type": "end"})
            reply = read_until_close(ws)
    assert hello["model"] == "codetalker-synth"
    assert hello["lookahead_ms"] == pytest.approx(300.0 + 2000.0 / 30)
    assert reply.code == CLOSE_NORMAL
    jaw = np.array([f.weights[list(ARKIT_NAMES).index("jawOpen")] for f in reply.frames])
    assert len(jaw) == round(len(pcm) / 2 / SAMPLE_RATE * FPS)
    assert jaw.max() > 0.2 and jaw.max() - jaw.min() > 0.2


def test_served_head_has_the_renderers_colours():
    """head.glb carries the mp4 renderer's vertex colours: dark pupils and irises on the eyes."""
    from talkmesh.face.look import PUPIL, head_colors
    from talkmesh.output.avatar import read_glb
    from talkmesh.output.gltf import _read_accessor
    from talkmesh.serve.files import neutral_head_glb

    data = neutral_head_glb()
    path = Path(tempfile.mkdtemp()) / "head.glb"
    path.write_bytes(data)
    gltf, binary = read_glb(path)
    primitive = gltf["meshes"][0]["primitives"][0]
    colors = _read_accessor(gltf, binary, primitive["attributes"]["COLOR_0"])
    head = load_head()
    srgb = head_colors(head)
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(colors, linear, atol=1e-6)
    pupils = np.flatnonzero(np.abs(srgb - np.asarray(PUPIL)).max(1) < 1e-6)
    assert len(pupils) > 0 and (head.regions.vertex_part[pupils] == 1).all()  # on the eyes
    base = gltf["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"]
    assert base == [1.0, 1.0, 1.0, 1.0]  # the vertex colours alone


def test_animate_mp4_keeps_the_uploads_own_sound(tmp_path):
    """POST /animate?format=mp4 muxes the uploaded file's sound (44.1 kHz stays 44.1 kHz)."""
    import soundfile as sf
    from imageio_ffmpeg import get_ffmpeg_exe

    clip, rate = sf.read(CLIP, dtype="float32")
    wide = tmp_path / "wide.wav"
    t = np.arange(round(len(clip) / rate * 44100))
    sf.write(wide, np.interp(t * rate / 44100, np.arange(len(clip)), clip), 44100)
    with TestClient(create_app()) as client:
        response = client.post("/animate?format=mp4&model=procedural", content=wide.read_bytes())
    assert response.status_code == 200, response.text
    video = tmp_path / "out.mp4"
    video.write_bytes(response.content)
    probe = subprocess.run(
        [get_ffmpeg_exe(), "-hide_banner", "-i", str(video)], capture_output=True
    )
    (audio,) = [ln for ln in probe.stderr.decode().splitlines() if "Audio:" in ln]
    assert "44100 Hz" in audio, audio
